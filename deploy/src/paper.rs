//! The paper's published results (Tables I–III of ../shared/paper/cmask-paper.tex) and their
//! comparison with ours: for every cell, our seed mean with a 95% bootstrap confidence interval
//! over the seeds, the paper's value, the difference, and whether our interval excludes it.
//!
//! The bootstrap resamples a group's per-seed means with replacement ([`RESAMPLES`] times, from a
//! fixed seed) and takes the 2.5th and 97.5th percentiles of the resampled means. With fewer than
//! two seeds the interval is a point and nothing is marked.

use crate::groups::{Group, Metric, Split};
use crate::table::Table;
use rand::Rng;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Bootstrap resamples per interval.
pub const RESAMPLES: usize = 10_000;

/// One published value: track (`f1_esp`, `f1_gbr`), rivals, algorithm, split, metric, value.
type Cell = (&'static str, usize, &'static str, Split, Metric, f64);

/// Table II, in the order the paper prints it (PG, OT, A2A per row), plus Table I's SAC rows
/// (PG only).
#[rustfmt::skip]
pub const TABLE2: &[Cell] = {
    use Metric::{A2a as A, Overtakes as O, Progress as P};
    use Split::{In as I, Out as X};
    &[
        ("f1_esp", 1, "dreamerv3", I, P, 0.5515), ("f1_esp", 1, "dreamerv3", I, O, 0.6231), ("f1_esp", 1, "dreamerv3", I, A, 17.1111),
        ("f1_esp", 1, "crssm", I, P, 0.5841), ("f1_esp", 1, "crssm", I, O, 0.4867), ("f1_esp", 1, "crssm", I, A, 9.3778),
        ("f1_esp", 1, "cmask", I, P, 0.4300), ("f1_esp", 1, "cmask", I, O, 0.2120), ("f1_esp", 1, "cmask", I, A, 26.6444),
        ("f1_esp", 1, "dreamerv3", X, P, 0.5255), ("f1_esp", 1, "dreamerv3", X, O, 0.4096), ("f1_esp", 1, "dreamerv3", X, A, 18.5850),
        ("f1_esp", 1, "crssm", X, P, 0.4888), ("f1_esp", 1, "crssm", X, O, 0.3484), ("f1_esp", 1, "crssm", X, A, 14.6550),
        ("f1_esp", 1, "cmask", X, P, 0.4175), ("f1_esp", 1, "cmask", X, O, 0.2113), ("f1_esp", 1, "cmask", X, A, 23.4100),
        ("f1_esp", 3, "dreamerv3", I, P, 0.5479), ("f1_esp", 3, "dreamerv3", I, O, 0.0667), ("f1_esp", 3, "dreamerv3", I, A, 18.4667),
        ("f1_esp", 3, "crssm", I, P, 0.5664), ("f1_esp", 3, "crssm", I, O, 0.0658), ("f1_esp", 3, "crssm", I, A, 20.2889),
        ("f1_esp", 3, "cmask", I, P, 0.6331), ("f1_esp", 3, "cmask", I, O, 0.0867), ("f1_esp", 3, "cmask", I, A, 14.6667),
        ("f1_esp", 3, "dreamerv3", X, P, 0.4416), ("f1_esp", 3, "dreamerv3", X, O, 0.2038), ("f1_esp", 3, "dreamerv3", X, A, 19.2650),
        ("f1_esp", 3, "crssm", X, P, 0.4732), ("f1_esp", 3, "crssm", X, O, 0.0538), ("f1_esp", 3, "crssm", X, A, 20.3500),
        ("f1_esp", 3, "cmask", X, P, 0.5335), ("f1_esp", 3, "cmask", X, O, 0.0759), ("f1_esp", 3, "cmask", X, A, 18.4063),
        ("f1_gbr", 1, "dreamerv3", I, P, 0.5057), ("f1_gbr", 1, "dreamerv3", I, O, 0.0080), ("f1_gbr", 1, "dreamerv3", I, A, 10.1111),
        ("f1_gbr", 1, "crssm", I, P, 0.4740), ("f1_gbr", 1, "crssm", I, O, 0.0342), ("f1_gbr", 1, "crssm", I, A, 10.6444),
        ("f1_gbr", 1, "cmask", I, P, 0.5993), ("f1_gbr", 1, "cmask", I, O, 0.0474), ("f1_gbr", 1, "cmask", I, A, 9.6222),
        ("f1_gbr", 1, "dreamerv3", X, P, 0.4446), ("f1_gbr", 1, "dreamerv3", X, O, 0.4096), ("f1_gbr", 1, "dreamerv3", X, A, 14.2650),
        ("f1_gbr", 1, "crssm", X, P, 0.4436), ("f1_gbr", 1, "crssm", X, O, 0.0542), ("f1_gbr", 1, "crssm", X, A, 12.3750),
        ("f1_gbr", 1, "cmask", X, P, 0.5463), ("f1_gbr", 1, "cmask", X, O, 0.0356), ("f1_gbr", 1, "cmask", X, A, 13.2700),
        ("f1_gbr", 3, "dreamerv3", I, P, 0.6243), ("f1_gbr", 3, "dreamerv3", I, O, 0.0529), ("f1_gbr", 3, "dreamerv3", I, A, 15.0444),
        ("f1_gbr", 3, "crssm", I, P, 0.6419), ("f1_gbr", 3, "crssm", I, O, 0.0036), ("f1_gbr", 3, "crssm", I, A, 3.6888),
        ("f1_gbr", 3, "cmask", I, P, 0.5395), ("f1_gbr", 3, "cmask", I, O, 0.0387), ("f1_gbr", 3, "cmask", I, A, 12.8000),
        ("f1_gbr", 3, "dreamerv3", X, P, 0.5309), ("f1_gbr", 3, "dreamerv3", X, O, 0.1217), ("f1_gbr", 3, "dreamerv3", X, A, 19.1349),
        ("f1_gbr", 3, "crssm", X, P, 0.5481), ("f1_gbr", 3, "crssm", X, O, 0.2820), ("f1_gbr", 3, "crssm", X, A, 10.5350),
        ("f1_gbr", 3, "cmask", X, P, 0.4924), ("f1_gbr", 3, "cmask", X, O, 0.0395), ("f1_gbr", 3, "cmask", X, A, 14.8900),
        ("f1_esp", 1, "sac", I, P, 0.2045), ("f1_gbr", 1, "sac", I, P, 0.2357), ("f1_esp", 1, "sac", X, P, 0.2103), ("f1_gbr", 1, "sac", X, P, 0.2038),
        ("f1_esp", 3, "sac", I, P, 0.1857), ("f1_gbr", 3, "sac", I, P, 0.2326), ("f1_esp", 3, "sac", X, P, 0.1756), ("f1_gbr", 3, "sac", X, P, 0.1999),
    ]
};

/// Table III: `(track, rivals, algorithm, ΔPG %, ΔA2A %)`.
#[rustfmt::skip]
pub const TABLE3: &[(&str, usize, &str, f64, f64)] = &[
    ("f1_esp", 1, "dreamerv3", -0.6527, 8.6137), ("f1_esp", 1, "crssm", -16.3157, 53.2733), ("f1_esp", 1, "cmask", -2.9070, -12.1391),
    ("f1_esp", 3, "dreamerv3", -19.4014, 4.3229), ("f1_esp", 3, "crssm", -16.4548, 0.3011), ("f1_esp", 3, "cmask", -15.7321, 25.4972),
    ("f1_gbr", 1, "dreamerv3", -12.0823, 41.0826), ("f1_gbr", 1, "crssm", -6.4135, 16.2583), ("f1_gbr", 1, "cmask", -8.8437, 37.9102),
    ("f1_gbr", 3, "dreamerv3", -14.9608, 27.1895), ("f1_gbr", 3, "crssm", -14.6129, 185.5942), ("f1_gbr", 3, "cmask", -8.7303, 16.3281),
];

/// The paper's value of one Table I/II cell, if it published one.
pub fn published(g: &Group, split: Split, metric: Metric) -> Option<f64> {
    TABLE2
        .iter()
        .find(|c| {
            (c.0, c.1, c.2, c.3, c.4)
                == (g.track.as_str(), g.rivals, g.algo.as_str(), split, metric)
        })
        .map(|c| c.5)
}

/// The paper's Table III values `(ΔPG %, ΔA2A %)` of a group, if it published them.
pub fn published_delta(g: &Group) -> Option<(f64, f64)> {
    TABLE3
        .iter()
        .find(|c| (c.0, c.1, c.2) == (g.track.as_str(), g.rivals, g.algo.as_str()))
        .map(|c| (c.3, c.4))
}

/// The 95% percentile-bootstrap interval of the mean of `values` (a point for one value).
pub fn bootstrap_ci(values: &[f64]) -> Option<(f64, f64)> {
    let n = values.len();
    match n {
        0 => None,
        1 => Some((values[0], values[0])),
        _ => {
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let mut means: Vec<f64> = (0..RESAMPLES)
                .map(|_| (0..n).map(|_| values[rng.random_range(0..n)]).sum::<f64>() / n as f64)
                .collect();
            means.sort_by(f64::total_cmp);
            let at = |q: f64| means[((RESAMPLES - 1) as f64 * q).round() as usize];
            Some((at(0.025), at(0.975)))
        }
    }
}

/// Our value of one cell beside the paper's.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    /// Seed mean.
    pub mean: f64,
    /// Seed standard deviation.
    pub std: f64,
    /// Seeds.
    pub seeds: usize,
    /// 95% bootstrap interval of the mean.
    pub ci: (f64, f64),
    /// The paper's value.
    pub paper: f64,
}

impl Comparison {
    /// Ours minus the paper's.
    pub fn difference(&self) -> f64 {
        self.mean - self.paper
    }

    /// Our interval (of at least two seeds) excludes the paper's value.
    pub fn excludes_paper(&self) -> bool {
        self.seeds >= 2 && !(self.ci.0..=self.ci.1).contains(&self.paper)
    }
}

/// Our cell of `g` beside the paper's, when both exist.
pub fn compare(g: &Group, split: Split, metric: Metric) -> Option<Comparison> {
    let paper = published(g, split, metric)?;
    let stat = g.stat(split, metric)?;
    let values: Vec<f64> = g
        .runs
        .iter()
        .filter_map(|r| crate::groups::split_mean(r, split, metric))
        .collect();
    Some(Comparison {
        mean: stat.mean,
        std: stat.std,
        seeds: stat.n,
        ci: bootstrap_ci(&values)?,
        paper,
    })
}

/// The comparison as Markdown: one row per group and split that the paper reports, per metric
/// our mean ± std, its interval, the paper's value and the difference; ✗ where the interval
/// excludes the paper's value.
pub fn comparison_md(groups: &[Group]) -> Table {
    let mut header = vec!["Setting".to_string(), "Algorithm".into(), "Split".into()];
    for m in Metric::ALL {
        header.push(format!("{} ours [95% CI]", m.label()));
        header.push(format!("{} paper (Δ)", m.label()));
    }
    let mut table = Table::new(header);
    for g in groups {
        for split in Split::ALL {
            let cells: Vec<Option<Comparison>> =
                Metric::ALL.iter().map(|&m| compare(g, split, m)).collect();
            if cells.iter().all(Option::is_none) {
                continue;
            }
            let mut row = vec![g.section(), g.display_name(), split.label().to_string()];
            for c in &cells {
                match c {
                    Some(c) => {
                        let mark = if c.excludes_paper() { " ✗" } else { "" };
                        row.push(format!(
                            "{:.4} ± {:.4} [{:.4}, {:.4}]",
                            c.mean, c.std, c.ci.0, c.ci.1
                        ));
                        row.push(format!("{:.4} ({:+.4}){mark}", c.paper, c.difference()));
                    }
                    None => row.extend(["–".to_string(), "–".to_string()]),
                }
            }
            table.push(row);
        }
    }
    table
}

/// The comparison as CSV: one row per group, split and metric the paper reports.
pub fn comparison_csv(groups: &[Group]) -> Table {
    let mut table = Table::new([
        "track",
        "rivals",
        "algo",
        "split",
        "metric",
        "seeds",
        "mean",
        "std",
        "ci_low",
        "ci_high",
        "paper",
        "difference",
        "ci_excludes_paper",
    ]);
    for g in groups {
        for split in Split::ALL {
            for m in Metric::ALL {
                if let Some(c) = compare(g, split, m) {
                    table.push(vec![
                        g.track.clone(),
                        g.rivals.to_string(),
                        g.algo.clone(),
                        split.label().into(),
                        m.label().into(),
                        c.seeds.to_string(),
                        format!("{:.6}", c.mean),
                        format!("{:.6}", c.std),
                        format!("{:.6}", c.ci.0),
                        format!("{:.6}", c.ci.1),
                        format!("{:.6}", c.paper),
                        format!("{:.6}", c.difference()),
                        c.excludes_paper().to_string(),
                    ]);
                }
            }
        }
    }
    table
}

/// Our Table III beside the paper's, for the groups it reports.
pub fn deltas_md(groups: &[Group]) -> Table {
    let mut table = Table::new([
        "Setting",
        "Algorithm",
        "ΔPG % ours",
        "ΔPG % paper",
        "ΔA2A % ours",
        "ΔA2A % paper",
    ]);
    for g in groups {
        let Some((pg, a2a)) = published_delta(g) else {
            continue;
        };
        let ours = |m| g.delta_pct(m).map_or("n/a".into(), |d| format!("{d:+.4}"));
        table.push(vec![
            g.section(),
            g.display_name(),
            ours(Metric::Progress),
            format!("{pg:+.4}"),
            ours(Metric::A2a),
            format!("{a2a:+.4}"),
        ]);
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every decimal number of the LaTeX between `start` and the next `end`, in order.
    fn numbers(tex: &str, start: &str, end: &str) -> Vec<f64> {
        let from = tex
            .find(start)
            .unwrap_or_else(|| panic!("no '{start}' in the paper"));
        let body = &tex[from..];
        let body = &body[..body.find(end).unwrap()];
        body.split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == '+'))
            .filter(|w| w.contains('.') && w.chars().any(|c| c.is_ascii_digit()))
            .filter_map(|w| w.trim_start_matches('+').parse::<f64>().ok())
            .collect()
    }

    #[test]
    fn the_embedded_tables_are_the_papers() {
        let dir =
            ctxrace_tracks::files::shared_reference("paper").unwrap_or_else(|e| panic!("{e}"));
        let tex = std::fs::read_to_string(dir.join("cmask-paper.tex")).unwrap();
        let cells = |range: std::ops::Range<usize>| -> Vec<f64> {
            TABLE2[range].iter().map(|c| c.5).collect()
        };
        // Table I: SAC vs one and three rivals (ESP In, GBR In, ESP Out, GBR Out), then DRM
        let table1 = numbers(&tex, "SAC vs One", "\\label{tab:sac}");
        assert_eq!(table1.len(), 16, "{table1:?}");
        assert_eq!(table1[..8], cells(72..80)[..], "Table I");
        // Table II in print order: ESP single and three, then GBR
        let table2 = numbers(&tex, "\\label{tab:sac}", "\\label{tab:means}");
        assert_eq!(table2, cells(0..72), "Table II");
        let table3 = numbers(&tex, "\\label{tab:means}", "\\label{tab:rel}");
        let embedded: Vec<f64> = TABLE3.iter().flat_map(|c| [c.3, c.4]).collect();
        assert_eq!(table3, embedded, "Table III");
    }

    #[test]
    fn the_bootstrap_interval_covers_the_mean_and_shrinks_with_agreement() {
        assert_eq!(bootstrap_ci(&[]), None);
        assert_eq!(bootstrap_ci(&[0.4]), Some((0.4, 0.4)));
        let (lo, hi) = bootstrap_ci(&[0.2, 0.4, 0.6, 0.8, 1.0]).unwrap();
        assert!(lo < 0.6 && hi > 0.6 && lo >= 0.2 && hi <= 1.0, "{lo} {hi}");
        let (lo2, hi2) = bootstrap_ci(&[0.58, 0.6, 0.62, 0.6, 0.6]).unwrap();
        assert!(hi2 - lo2 < 0.2 * (hi - lo));
        let c = Comparison {
            mean: 0.6,
            std: 0.01,
            seeds: 5,
            ci: (lo2, hi2),
            paper: 0.4,
        };
        assert!(c.excludes_paper() && (c.difference() - 0.2).abs() < 1e-12);
        assert!(!Comparison {
            seeds: 1,
            ..c.clone()
        }
        .excludes_paper());
    }
}
