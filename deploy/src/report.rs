//! `ctxrace report`: the paper's tables (Markdown and CSV) and figures from evaluation runs.
//!
//! Runs are grouped by algorithm, track and number of rivals; each run's metrics are averaged over
//! its in-distribution and its out-of-distribution contexts, and those per-run means are averaged
//! over the runs of a group (its training seeds): mean ± sample standard deviation.
//!
//! - Table I: track progress per algorithm, in and out of distribution, per track and rivals.
//! - Table II: PG, OT and A2A in and out of distribution; the best agent per column is marked
//!   (highest PG and OT, lowest A2A). Baselines are reference rows and never marked.
//! - Table III: change from in- to out-of-distribution, `100 (out − in) / |in|`, for PG and A2A.
//! - The paper's own values beside ours, with 95% bootstrap intervals over the seeds
//!   ([`crate::paper`]).

use crate::groups::{group, sections, Group, Metric, Run, Split, Stat};
use crate::table::Table;
use crate::TrackArgs;
use anyhow::{Context as _, Result};
use clap::Args;
use ctxrace_sim::masks::ContextMasks;
use std::path::{Path, PathBuf};

/// Arguments of `ctxrace report`.
#[derive(Args)]
pub struct ReportArgs {
    /// Evaluation directories (holding meta.json) or training run directories (holding
    /// eval/meta.json, and episodes.csv for the training curves).
    #[arg(required_unless_present = "parity")]
    runs: Vec<PathBuf>,
    /// A folder of `deploy/paper_parity.sh` (`{ctxrace,paper}/<algo>/seed<S>/episodes.csv`):
    /// one figure per algorithm of both sides' training curves (mean and 95% bootstrap
    /// interval over seeds), `parity_<algo>.png` and `.svg`.
    #[arg(long)]
    parity: Option<PathBuf>,
    /// Folder the tables and figures are written to (created if missing).
    #[arg(long, default_value = "report")]
    out: PathBuf,
    /// Race config TOML for the rivals of the speed-profile and race-line figures.
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    tracks: TrackArgs,
}

/// Writes the tables and figures, and prints the Markdown report.
pub fn run(args: ReportArgs) -> Result<()> {
    if let Some(dir) = &args.parity {
        let curves = crate::parity::load(dir)?;
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        for file in crate::figures::write_parity(&curves, &args.out)? {
            println!("{}", file.display());
        }
        if args.runs.is_empty() {
            return Ok(());
        }
    }
    let runs = args
        .runs
        .iter()
        .map(|p| Run::load(p))
        .collect::<Result<Vec<_>>>()?;
    let groups = group(runs);
    let cfg = crate::load_race_config(args.config.as_ref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let tables = [
        ("table1.csv", table1_csv(&groups)),
        ("table2.csv", table2_csv(&groups)),
        ("table3.csv", table3_csv(&groups)),
        ("paper.csv", crate::paper::comparison_csv(&groups)),
        ("masks.csv", masks_csv(&groups)),
    ];
    for (name, table) in &tables {
        table.write_csv(&args.out.join(name))?;
    }
    let figures = crate::figures::write_all(&groups, &args.out, &args.tracks, &cfg)?;
    let markdown = markdown(&groups, &figures, &args.out);
    let path = args.out.join("report.md");
    ctxrace_run::run_dir::write_atomic(&path, markdown.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    print!("{markdown}");
    Ok(())
}

/// Marks the best of `values` in the metric's direction among the entries that compete (ties all
/// marked; missing values never).
pub fn best_marks(values: &[(bool, Option<f64>)], higher_is_better: bool) -> Vec<bool> {
    let better = |a: f64, b: f64| if higher_is_better { a > b } else { a < b };
    let best = values
        .iter()
        .filter(|(competes, _)| *competes)
        .filter_map(|(_, v)| *v)
        .fold(None, |best: Option<f64>, v| match best {
            Some(b) if !better(v, b) => Some(b),
            _ => Some(v),
        });
    values
        .iter()
        .map(|&(competes, v)| competes && v.is_some() && v == best)
        .collect()
}

/// Best marks of one Table II column (`split`, `metric`) of a section.
fn stat_marks(section: &[Group], split: Split, metric: Metric) -> Vec<bool> {
    let values: Vec<(bool, Option<f64>)> = section
        .iter()
        .map(|g| (!g.is_baseline(), g.stat(split, metric).map(|s| s.mean)))
        .collect();
    best_marks(&values, metric.higher_is_better())
}

/// Best marks of one Table III column of a section.
fn delta_marks(section: &[Group], metric: Metric) -> Vec<bool> {
    let values: Vec<(bool, Option<f64>)> = section
        .iter()
        .map(|g| (!g.is_baseline(), g.delta_pct(metric)))
        .collect();
    best_marks(&values, metric.higher_is_better())
}

/// The Table III metrics.
const DELTA_METRICS: [Metric; 2] = [Metric::Progress, Metric::A2a];

/// `mean ± std`, bold when best, `–` when missing.
fn md_stat(stat: Option<Stat>, best: bool) -> String {
    match stat {
        Some(s) => bold(format!("{:.4} ± {:.4}", s.mean, s.std), best),
        None => "–".into(),
    }
}

/// A signed percentage, bold when best, `n/a` when missing.
fn md_delta(delta: Option<f64>, best: bool) -> String {
    match delta {
        Some(d) => bold(format!("{d:+.4}"), best),
        None => "n/a".into(),
    }
}

fn bold(text: String, best: bool) -> String {
    if best {
        format!("**{text}**")
    } else {
        text
    }
}

/// A number for the CSV files: six decimals, `n/a` when missing.
fn csv_num(v: Option<f64>) -> String {
    v.map_or_else(|| "n/a".into(), |v| format!("{v:.6}"))
}

/// The algorithms of all groups in table order, each with its display name.
fn algorithms(groups: &[Group]) -> Vec<(String, String)> {
    let mut sorted: Vec<&Group> = groups.iter().collect();
    sorted.sort_by_key(|g| {
        let (_, _, rank, algo) = g.order();
        (rank, algo)
    });
    let mut algos: Vec<(String, String)> = Vec::new();
    for g in sorted {
        if !algos.iter().any(|(a, _)| *a == g.algo) {
            algos.push((g.algo.clone(), g.display_name()));
        }
    }
    algos
}

/// cMask's mean masks per context as CSV: one row per group with masks and context, the
/// seeds' decisions pooled (no rows without cMask evaluations).
fn masks_csv(groups: &[Group]) -> Table {
    let mut table = Table::new([
        "track",
        "rivals",
        "algo",
        "seeds",
        "context_speed",
        "context_steer",
        "decisions",
        "mask_speed",
        "mask_steer",
    ]);
    for g in groups {
        let summaries: Vec<_> = g.runs.iter().filter_map(|r| r.masks.as_ref()).collect();
        let mut cells: Vec<ContextMasks> = Vec::new();
        for c in summaries.iter().flat_map(|m| &m.contexts) {
            match cells.iter_mut().find(|d| d.context() == c.context()) {
                Some(d) => {
                    d.count += c.count;
                    d.sum = [d.sum[0] + c.sum[0], d.sum[1] + c.sum[1]];
                }
                None => cells.push(ContextMasks {
                    along: Vec::new(),
                    longest_lap: Vec::new(),
                    ..c.clone()
                }),
            }
        }
        for c in cells {
            table.push(vec![
                g.track.clone(),
                g.rivals.to_string(),
                g.algo.clone(),
                summaries.len().to_string(),
                c.context_speed.to_string(),
                c.context_steer.to_string(),
                c.count.to_string(),
                format!("{:.4}", c.mean(0)),
                format!("{:.4}", c.mean(1)),
            ]);
        }
    }
    table
}

/// Table I in Markdown: PG per algorithm, an In and an Out column per section.
fn table1_md(groups: &[Group]) -> Table {
    let secs: Vec<&[Group]> = sections(groups).collect();
    let mut header = vec!["Algorithm".to_string()];
    for s in &secs {
        for split in Split::ALL {
            header.push(format!("{} {}", s[0].section(), split.label()));
        }
    }
    let mut table = Table::new(header);
    for (algo, name) in algorithms(groups) {
        let mut row = vec![name];
        for s in &secs {
            let g = s.iter().find(|g| g.algo == algo);
            for split in Split::ALL {
                row.push(md_stat(
                    g.and_then(|g| g.stat(split, Metric::Progress)),
                    false,
                ));
            }
        }
        table.push(row);
    }
    table
}

/// Table I as CSV: one row per group and split.
fn table1_csv(groups: &[Group]) -> Table {
    let mut table = Table::new([
        "track", "rivals", "algo", "seeds", "split", "pg_mean", "pg_std",
    ]);
    for g in groups {
        for split in Split::ALL {
            let s = g.stat(split, Metric::Progress);
            table.push(vec![
                g.track.clone(),
                g.rivals.to_string(),
                g.algo.clone(),
                g.runs.len().to_string(),
                split.label().into(),
                csv_num(s.map(|s| s.mean)),
                csv_num(s.map(|s| s.std)),
            ]);
        }
    }
    table
}

/// Table II of one section in Markdown.
fn table2_md(section: &[Group]) -> Table {
    let mut header = vec!["Algorithm".to_string(), "Seeds".to_string()];
    for split in Split::ALL {
        for m in Metric::ALL {
            header.push(format!("{} {} {}", m.label(), m.arrow(), split.label()));
        }
    }
    let mut table = Table::new(header);
    let marks: Vec<Vec<bool>> = Split::ALL
        .iter()
        .flat_map(|&split| Metric::ALL.map(|m| stat_marks(section, split, m)))
        .collect();
    for (i, g) in section.iter().enumerate() {
        let mut row = vec![g.display_name(), g.runs.len().to_string()];
        let mut col = marks.iter();
        for split in Split::ALL {
            for m in Metric::ALL {
                let best = col.next().is_some_and(|c| c[i]);
                row.push(md_stat(g.stat(split, m), best));
            }
        }
        table.push(row);
    }
    table
}

/// Table II as CSV: one row per group and split, a `best` flag per metric.
fn table2_csv(groups: &[Group]) -> Table {
    let mut header: Vec<String> = ["track", "rivals", "algo", "baseline", "seeds", "split"]
        .map(String::from)
        .to_vec();
    for m in Metric::ALL {
        let l = m.label().to_lowercase();
        header.extend([format!("{l}_mean"), format!("{l}_std"), format!("{l}_best")]);
    }
    let mut table = Table::new(header);
    for section in sections(groups) {
        for split in Split::ALL {
            let marks = Metric::ALL.map(|m| stat_marks(section, split, m));
            for (i, g) in section.iter().enumerate() {
                let mut row = vec![
                    g.track.clone(),
                    g.rivals.to_string(),
                    g.algo.clone(),
                    g.is_baseline().to_string(),
                    g.runs.len().to_string(),
                    split.label().into(),
                ];
                for (m, mark) in Metric::ALL.iter().zip(&marks) {
                    let s = g.stat(split, *m);
                    row.extend([
                        csv_num(s.map(|s| s.mean)),
                        csv_num(s.map(|s| s.std)),
                        mark[i].to_string(),
                    ]);
                }
                table.push(row);
            }
        }
    }
    table
}

/// Table III of one section in Markdown.
fn table3_md(section: &[Group]) -> Table {
    let mut table = Table::new(
        std::iter::once("Algorithm".to_string())
            .chain(DELTA_METRICS.map(|m| format!("Δ{} % {}", m.label(), m.arrow()))),
    );
    let marks = DELTA_METRICS.map(|m| delta_marks(section, m));
    for (i, g) in section.iter().enumerate() {
        let mut row = vec![g.display_name()];
        for (m, mark) in DELTA_METRICS.iter().zip(&marks) {
            row.push(md_delta(g.delta_pct(*m), mark[i]));
        }
        table.push(row);
    }
    table
}

/// Table III as CSV: one row per group.
fn table3_csv(groups: &[Group]) -> Table {
    let mut table = Table::new([
        "track",
        "rivals",
        "algo",
        "baseline",
        "delta_pg_pct",
        "delta_pg_best",
        "delta_a2a_pct",
        "delta_a2a_best",
    ]);
    for section in sections(groups) {
        let marks = DELTA_METRICS.map(|m| delta_marks(section, m));
        for (i, g) in section.iter().enumerate() {
            let mut row = vec![
                g.track.clone(),
                g.rivals.to_string(),
                g.algo.clone(),
                g.is_baseline().to_string(),
            ];
            for (m, mark) in DELTA_METRICS.iter().zip(&marks) {
                row.extend([csv_num(g.delta_pct(*m)), mark[i].to_string()]);
            }
            table.push(row);
        }
    }
    table
}

/// The training ranges of a section's runs, e.g. `±0.15`.
fn train_ranges(section: &[Group]) -> String {
    let mut ranges: Vec<f64> = Vec::new();
    for r in section.iter().flat_map(|g| &g.runs) {
        if !ranges.contains(&r.meta.train_range) {
            ranges.push(r.meta.train_range);
        }
    }
    ranges
        .iter()
        .map(|r| format!("±{r}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The whole Markdown report; `figures` are linked relative to `out`.
fn markdown(groups: &[Group], figures: &[PathBuf], out: &Path) -> String {
    let n_runs: usize = groups.iter().map(|g| g.runs.len()).sum();
    let mut md = format!(
        "# ctxrace report\n\n{n_runs} evaluation run(s) in {} group(s). In: contexts with both \
         values inside the training range; Out: the others. Values are mean ± sample standard \
         deviation over training seeds of each run's mean over its contexts. PG: track progress, \
         OT: overtakes per episode, A2A: ego–rival collisions per 50 laps. Best agent per column \
         in bold (baselines are reference rows).\n\n",
        groups.len()
    );
    md += "## Table I: track progress (PG)\n\n";
    md += &table1_md(groups).markdown();
    md += "\n## Table II: mean performance\n";
    for section in sections(groups) {
        md += &format!(
            "\n### {} (training range {})\n\n",
            section[0].section(),
            train_ranges(section)
        );
        md += &table2_md(section).markdown();
    }
    md += "\n## Table III: change from in- to out-of-distribution (%)\n";
    for section in sections(groups) {
        md += &format!("\n### {}\n\n", section[0].section());
        md += &table3_md(section).markdown();
    }
    let paper = crate::paper::comparison_md(groups);
    if !paper.rows.is_empty() {
        md += "\n## Beside the paper\n\nOur seed mean ± standard deviation with its 95% bootstrap \
               interval over seeds, and the paper's value with our difference from it (Tables I \
               and II); ✗ where our interval (of two or more seeds) excludes the paper's value.\n\n";
        md += &paper.markdown();
        md += "\n";
        md += &crate::paper::deltas_md(groups).markdown();
    }
    let images: Vec<String> = figures
        .iter()
        .map(|f| f.strip_prefix(out).unwrap_or(f).display().to_string())
        .filter(|rel| rel.ends_with(".png"))
        .map(|rel| format!("![{rel}]({rel})\n"))
        .collect();
    if !images.is_empty() {
        md += "\n## Figures\n\nEach also as SVG beside the PNG.\n\n";
        md += &images.join("\n");
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::groups::split_mean;
    use ctxrace_config::Context;
    use ctxrace_run::results::{write_csv, write_json, TrainingEpisode};
    use ctxrace_sim::evaluation::EvalMeta;
    use ctxrace_sim::evaluation::{ContextSummary, EvalEpisode};

    const TRAIN_RANGE: f64 = 0.15;

    /// A context with PG `pg`, OT `ot` and A2A `a2a`.
    fn ctx(cv: f64, ct: f64, pg: f64, ot: f64, a2a: f64) -> ContextSummary {
        ContextSummary {
            context_speed: cv,
            context_steer: ct,
            in_distribution: Context {
                speed: cv,
                steer: ct,
            }
            .within(TRAIN_RANGE),
            laps: 50,
            progress: pg,
            overtakes: ot,
            a2a,
            wall_crash: 0.0,
            lap_complete: 0.0,
            episode_return: 1.0,
        }
    }

    fn meta(algo: &str, seed: u64) -> EvalMeta {
        EvalMeta {
            algo: algo.into(),
            track: "f1_esp".into(),
            rivals: 1,
            train_seed: seed,
            train_range: TRAIN_RANGE,
            grid: 7,
            range: 0.3,
            laps: 50,
            seed: 0,
            source: format!("runs/{algo}-{seed}"),
            checkpoint: "best".into(),
            act: ctxrace_sim::driver::ActMode::Sample,
            preset: ctxrace_config::RacePreset::Default,
            contexts: None,
            told: Default::default(),
            mask: None,
        }
    }

    /// A run whose in-distribution contexts all have (pg_in, ot_in, a2a_in) and whose
    /// out-of-distribution ones all have (pg_out, ot_out, a2a_out).
    fn run(algo: &str, seed: u64, inside: [f64; 3], outside: [f64; 3]) -> Run {
        let [pi, oi, ai] = inside;
        let [po, oo, ao] = outside;
        Run {
            dir: PathBuf::from(format!("runs/{algo}-{seed}/eval")),
            meta: meta(algo, seed),
            contexts: vec![
                ctx(0.0, 0.0, pi, oi, ai),
                ctx(0.15, -0.15, pi, oi, ai),
                ctx(0.3, 0.0, po, oo, ao),
                ctx(-0.2, 0.3, po, oo, ao),
            ],
            training: Vec::new(),
            masks: None,
        }
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    #[test]
    fn split_means_separate_in_and_out_of_distribution_contexts() {
        let r = Run {
            contexts: vec![
                ctx(0.0, 0.0, 0.8, 1.0, 0.0),
                ctx(0.1, -0.1, 0.6, 0.0, 10.0),
                // on the training range's edge: still in-distribution
                ctx(0.15, 0.15, 0.7, 2.0, 5.0),
                ctx(0.2, 0.0, 0.4, -1.0, 20.0),
                ctx(-0.3, 0.3, 0.2, 0.0, 40.0),
            ],
            ..run("cmask", 0, [0.0; 3], [0.0; 3])
        };
        assert!(close(
            split_mean(&r, Split::In, Metric::Progress).unwrap(),
            0.7
        ));
        assert!(close(
            split_mean(&r, Split::In, Metric::Overtakes).unwrap(),
            1.0
        ));
        assert!(close(split_mean(&r, Split::In, Metric::A2a).unwrap(), 5.0));
        assert!(close(
            split_mean(&r, Split::Out, Metric::Progress).unwrap(),
            0.3
        ));
        assert!(close(
            split_mean(&r, Split::Out, Metric::Overtakes).unwrap(),
            -0.5
        ));
        assert!(close(
            split_mean(&r, Split::Out, Metric::A2a).unwrap(),
            30.0
        ));
        // a run evaluated only in distribution has no out-of-distribution mean
        let only_in = Run {
            contexts: vec![ctx(0.0, 0.1, 0.5, 0.0, 0.0)],
            ..r
        };
        assert_eq!(split_mean(&only_in, Split::Out, Metric::Progress), None);
    }

    #[test]
    fn seeds_are_averaged_with_sample_std() {
        let groups = group(vec![
            run("cmask", 0, [0.4, 0.0, 10.0], [0.3, 0.0, 20.0]),
            run("sac", 0, [0.2, 0.0, 30.0], [0.1, 0.0, 40.0]),
            run("cmask", 1, [0.5, 0.0, 10.0], [0.3, 0.0, 20.0]),
            run("cmask", 2, [0.9, 0.0, 10.0], [0.3, 0.0, 20.0]),
        ]);
        assert_eq!(groups.len(), 2);
        // paper order: SAC before cMask
        let (sac, cmask) = (&groups[0], &groups[1]);
        assert_eq!((sac.algo.as_str(), cmask.algo.as_str()), ("sac", "cmask"));
        let s = cmask.stat(Split::In, Metric::Progress).unwrap();
        assert_eq!(s.n, 3);
        assert!(close(s.mean, 0.6));
        // deviations 0.2, 0.1, 0.3: sqrt(0.14 / 2)
        assert!(close(s.std, 0.07_f64.sqrt()), "{s:?}");
        let a2a = cmask.stat(Split::Out, Metric::A2a).unwrap();
        assert!(close(a2a.mean, 20.0) && close(a2a.std, 0.0));
        // a single seed has std 0
        let one = sac.stat(Split::In, Metric::A2a).unwrap();
        assert_eq!((one.mean, one.std, one.n), (30.0, 0.0, 1));
        assert_eq!(Stat::of(&[]), None);
    }

    #[test]
    fn the_papers_values_stand_beside_ours_with_bootstrap_intervals() {
        // cMask on f1_esp against one rival: the paper has PG In 0.4300, A2A In 26.6444
        let groups = group(vec![
            run("cmask", 0, [0.60, 0.2, 26.0], [0.5, 0.2, 23.0]),
            run("cmask", 1, [0.62, 0.2, 27.0], [0.5, 0.2, 24.0]),
            run("cmask", 2, [0.61, 0.2, 26.5], [0.5, 0.2, 23.5]),
        ]);
        let g = &groups[0];
        let pg = crate::paper::compare(g, Split::In, Metric::Progress).unwrap();
        assert_eq!((pg.paper, pg.seeds), (0.43, 3));
        assert!(
            pg.ci.0 >= 0.60 && pg.ci.1 <= 0.62 && pg.excludes_paper(),
            "{pg:?}"
        );
        let a2a = crate::paper::compare(g, Split::In, Metric::A2a).unwrap();
        assert!(!a2a.excludes_paper(), "{a2a:?}");
        let md = markdown(&groups, &[], Path::new("."));
        assert!(md.contains("## Beside the paper"), "{md}");
        assert!(md.contains("| 0.4300 (+0.1800) ✗ |"), "{md}");
        // Table III beside the paper's: ours, then the paper's ΔPG
        assert!(md.contains("| -2.9070 |"), "{md}");
        let csv = crate::paper::comparison_csv(&groups);
        assert_eq!(csv.rows.len(), 6, "three metrics, two splits");
    }

    #[test]
    fn delta_is_relative_change_from_in_to_out_of_distribution() {
        let g = &group(vec![run("crssm", 0, [0.5, 0.0, 10.0], [0.4, 1.0, 15.0])])[0];
        assert!(close(g.delta_pct(Metric::Progress).unwrap(), -20.0));
        assert!(close(g.delta_pct(Metric::A2a).unwrap(), 50.0));
        // a negative base divides by its magnitude: -1 → -0.5 is +50 %
        let neg = &group(vec![run("crssm", 0, [0.0, -1.0, 0.0], [0.0, -0.5, 3.0])])[0];
        assert!(close(neg.delta_pct(Metric::Overtakes).unwrap(), 50.0));
        // no base: n/a
        assert_eq!(neg.delta_pct(Metric::A2a), None);
        assert_eq!(md_delta(neg.delta_pct(Metric::A2a), false), "n/a");
        assert_eq!(md_delta(Some(-20.0), true), "**-20.0000**");
        assert_eq!(md_delta(Some(50.0), false), "+50.0000");
    }

    #[test]
    fn best_marks_pick_highest_or_lowest_and_skip_baselines_and_gaps() {
        let v = [
            (true, Some(0.5)),
            (true, None),
            (false, Some(0.9)),
            (true, Some(0.2)),
        ];
        assert_eq!(best_marks(&v, true), [true, false, false, false]);
        assert_eq!(best_marks(&v, false), [false, false, false, true]);
        let tie = [(true, Some(1.0)), (true, Some(1.0)), (true, Some(0.0))];
        assert_eq!(best_marks(&tie, true), [true, true, false]);
        assert_eq!(best_marks(&[(false, Some(1.0))], true), [false]);
    }

    /// SAC, cMask and a pure-pursuit baseline that beats both (never marked).
    fn contest() -> Vec<Group> {
        group(vec![
            run("pure-pursuit", 0, [0.95, 0.9, 1.0], [0.9, 0.8, 2.0]),
            run("cmask", 0, [0.6, 0.1, 20.0], [0.5, 0.3, 30.0]),
            run("sac", 0, [0.2, 0.5, 10.0], [0.1, 0.2, 40.0]),
        ])
    }

    #[test]
    fn table2_marks_best_agents_not_baselines() {
        let groups = contest();
        assert!(groups[2].is_baseline() && !groups[1].is_baseline());
        let md = table2_md(&groups).markdown();
        let rows: Vec<&str> = md.lines().skip(2).collect();
        assert_eq!(
            rows,
            [
                "| SAC | 1 | 0.2000 ± 0.0000 | **0.5000 ± 0.0000** | **10.0000 ± 0.0000** \
                 | 0.1000 ± 0.0000 | 0.2000 ± 0.0000 | 40.0000 ± 0.0000 |",
                "| cMask | 1 | **0.6000 ± 0.0000** | 0.1000 ± 0.0000 | 20.0000 ± 0.0000 \
                 | **0.5000 ± 0.0000** | **0.3000 ± 0.0000** | **30.0000 ± 0.0000** |",
                "| pure-pursuit (baseline) | 1 | 0.9500 ± 0.0000 | 0.9000 ± 0.0000 \
                 | 1.0000 ± 0.0000 | 0.9000 ± 0.0000 | 0.8000 ± 0.0000 | 2.0000 ± 0.0000 |",
            ]
        );
        let csv = table2_csv(&groups);
        let col = |name: &str| csv.header.iter().position(|h| h == name).unwrap();
        let best: Vec<(&str, &str, &str, &str)> = csv
            .rows
            .iter()
            .map(|r| {
                let (algo, split) = (r[col("algo")].as_str(), r[col("split")].as_str());
                (
                    algo,
                    split,
                    r[col("pg_best")].as_str(),
                    r[col("a2a_best")].as_str(),
                )
            })
            .collect();
        assert!(best.contains(&("cmask", "In", "true", "false")));
        assert!(best.contains(&("sac", "In", "false", "true")));
        assert!(best.contains(&("pure-pursuit", "In", "false", "false")));
        assert!(best.contains(&("cmask", "Out", "true", "true")));
    }

    #[test]
    fn table3_marks_highest_progress_change_and_lowest_a2a_change() {
        // ΔPG: SAC -50 %, cMask -16.67 %; ΔA2A: SAC +300 %, cMask +50 %
        let md = table3_md(&contest()).markdown();
        assert!(md.contains("| SAC | -50.0000 | +300.0000 |"), "{md}");
        assert!(
            md.contains("| cMask | **-16.6667** | **+50.0000** |"),
            "{md}"
        );
        assert!(
            md.contains("| pure-pursuit (baseline) | -5.2632 | +100.0000 |"),
            "{md}"
        );
    }

    #[test]
    fn table1_has_an_in_and_out_column_per_track_and_rivals() {
        let mut runs = vec![run("cmask", 0, [0.6, 0.0, 0.0], [0.5, 0.0, 0.0])];
        let mut three = run("cmask", 0, [0.4, 0.0, 0.0], [0.3, 0.0, 0.0]);
        three.meta.rivals = 3;
        runs.push(three);
        let md = table1_md(&group(runs)).markdown();
        let lines: Vec<&str> = md.lines().collect();
        assert_eq!(
            lines[0],
            "| Algorithm | f1_esp, 1 rival In | f1_esp, 1 rival Out | f1_esp, 3 rivals In | f1_esp, 3 rivals Out |"
        );
        assert_eq!(
            lines[2],
            "| cMask | 0.6000 ± 0.0000 | 0.5000 ± 0.0000 | 0.4000 ± 0.0000 | 0.3000 ± 0.0000 |"
        );
    }

    #[test]
    fn loads_eval_dirs_and_training_runs_and_names_bad_paths() {
        let dir = tempfile::tempdir().unwrap();
        // a training run: eval/ with episodes only (summarised on load) and training episodes
        let eval = dir.path().join("run/eval");
        std::fs::create_dir_all(&eval).unwrap();
        write_json(&eval.join("meta.json"), &meta("cmask", 3)).unwrap();
        let episode = |cv: f64, progress: f64| EvalEpisode {
            context_speed: cv,
            context_steer: 0.0,
            lap: 0,
            seed: 0,
            progress,
            overtakes: 0,
            a2a: false,
            wall_crash: false,
            lap_complete: false,
            lap_time: None,
            steps: 1,
            episode_return: 0.0,
            leader: Some(1),
        };
        let eps = [episode(0.0, 0.4), episode(0.0, 0.6), episode(0.3, 0.1)];
        write_csv(&eval.join("episodes.csv"), &eps).unwrap();
        let training = TrainingEpisode {
            env_steps: 100,
            grad_steps: 10,
            actor: 0,
            episode: 0,
            context_speed: 0.0,
            context_steer: 0.0,
            progress: 0.3,
            overtakes: 0,
            a2a: false,
            wall_crash: true,
            episode_return: -1.0,
            steps: 100,
        };
        write_csv(&dir.path().join("run/episodes.csv"), &[training]).unwrap();
        let r = Run::load(&dir.path().join("run")).unwrap();
        assert_eq!((r.meta.train_seed, r.training.len()), (3, 1));
        assert!(close(
            split_mean(&r, Split::In, Metric::Progress).unwrap(),
            0.5
        ));
        assert!(close(
            split_mean(&r, Split::Out, Metric::Progress).unwrap(),
            0.1
        ));
        // the eval directory itself: no training episodes
        assert!(Run::load(&eval).unwrap().training.is_empty());

        let err = |p: &Path| format!("{:#}", Run::load(p).unwrap_err());
        let missing = dir.path().join("nope");
        assert!(err(&missing).contains("nope: no such directory"));
        assert!(err(dir.path()).contains("neither an evaluation directory"));
        std::fs::write(eval.join("meta.json"), "{").unwrap();
        assert!(err(&eval).contains("meta.json"), "{}", err(&eval));
        write_json(&eval.join("meta.json"), &meta("cmask", 3)).unwrap();
        std::fs::write(eval.join("episodes.csv"), "context_speed\nx\n").unwrap();
        assert!(err(&eval).contains("episodes.csv row 2"), "{}", err(&eval));
        std::fs::remove_file(eval.join("episodes.csv")).unwrap();
        assert!(err(&eval).contains("neither contexts.csv nor episodes.csv"));
    }
}
