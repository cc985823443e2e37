//! The training curves of a parity folder written by `deploy/paper_parity.sh`: ctxrace's and
//! the paper's own code's training episodes at the same budget, in ctxrace's format (a run
//! directory's `episodes.csv`, [`TrainingEpisode`]), as `<dir>/<side>/<algo>/seed<S>/episodes.csv`
//! where a side is `paper` (the paper's code) or a ctxrace side (`ctxrace`, or a name of its
//! own such as `ctxrace-paper-init` for a second ctxrace setting). `ctxrace report --parity DIR`
//! draws them ([`crate::figures::write_parity`]).

use anyhow::{bail, Context as _, Result};
use ctxrace_run::results::{read_csv, TrainingEpisode};
use ctxrace_run::run_dir::TRAINING_EPISODES;
use std::path::Path;

/// The paper's code's side of a parity folder (drawn last).
pub const PAPER_SIDE: &str = "paper";

/// The sides of a parity folder in drawing order: its folders by name, the paper's last.
fn sides(dir: &Path) -> Result<Vec<String>> {
    let mut names = folders(dir)?;
    names.sort_by_key(|name| name == PAPER_SIDE);
    Ok(names)
}

/// Each seed's training episodes, by seed.
pub type SeedCurves = Vec<(u64, Vec<TrainingEpisode>)>;

/// One algorithm's curves: per side, each seed's training episodes.
#[derive(Clone, Debug, PartialEq)]
pub struct ParityCurves {
    /// The algorithm (ctxrace's name).
    pub algo: String,
    /// Per side that has it: the side and each seed's episodes (by seed).
    pub sides: Vec<(String, SeedCurves)>,
}

/// The names of the folders under `dir`, sorted.
fn folders(dir: &Path) -> Result<Vec<String>> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("listing {}", dir.display()))?
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .filter_map(|e| e.file_name().to_str().map(str::to_owned))
        .collect();
    names.sort();
    Ok(names)
}

/// Reads a parity folder. Seeds without an `episodes.csv` (a run still starting) or without
/// episodes are left out; a folder with no curve at all is an error.
pub fn load(dir: &Path) -> Result<Vec<ParityCurves>> {
    if !dir.is_dir() {
        bail!(
            "--parity {}: no such folder (deploy/paper_parity.sh writes one)",
            dir.display()
        );
    }
    let mut curves: Vec<ParityCurves> = Vec::new();
    for side in sides(dir)? {
        let side_dir = dir.join(&side);
        for algo in folders(&side_dir)? {
            let mut seeds = Vec::new();
            for name in folders(&side_dir.join(&algo))? {
                let Some(seed) = name.strip_prefix("seed").and_then(|s| s.parse().ok()) else {
                    continue;
                };
                let csv = side_dir.join(&algo).join(&name).join(TRAINING_EPISODES);
                if !csv.is_file() {
                    tracing::warn!("{}: no training curve yet, left out", csv.display());
                    continue;
                }
                let episodes: Vec<TrainingEpisode> = read_csv(&csv)?;
                if !episodes.is_empty() {
                    seeds.push((seed, episodes));
                }
            }
            if seeds.is_empty() {
                continue;
            }
            seeds.sort_by_key(|(s, _)| *s);
            let index = match curves.iter().position(|c| c.algo == algo) {
                Some(i) => i,
                None => {
                    curves.push(ParityCurves {
                        algo: algo.clone(),
                        sides: Vec::new(),
                    });
                    curves.len() - 1
                }
            };
            let entry = &mut curves[index];
            entry.sides.push((side.clone(), seeds));
        }
    }
    if curves.is_empty() {
        bail!(
            "{}: no training curve, expected <side>/<algo>/seed<S>/episodes.csv, side `paper` or a \
             ctxrace setting such as `ctxrace` (deploy/paper_parity.sh writes them)",
            dir.display()
        );
    }
    Ok(curves)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A training curve of `n` episodes of 50 steps whose progress rises by `slope` per
    /// episode; every third episode ends in a collision.
    fn curve(n: u64, slope: f64) -> String {
        let mut csv = String::from(
            "env_steps,grad_steps,actor,episode,context_speed,context_steer,progress,overtakes,\
             a2a,wall_crash,episode_return,steps\n",
        );
        for k in 0..n {
            let crash = k % 3 == 0;
            csv += &format!(
                "{},{},0,{k},0.1,-0.1,{},0,{crash},false,{},50\n",
                50 * (k + 1),
                25 * k,
                (slope * k as f64).min(1.0),
                k as f64 * slope * 10.0
            );
        }
        csv
    }

    fn put(dir: &Path, side: &str, algo: &str, seed: &str, text: &str) {
        let d = dir.join(side).join(algo).join(seed);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join(TRAINING_EPISODES), text).unwrap();
    }

    #[test]
    fn every_side_loads_per_algorithm_the_papers_last_and_draws_one_figure_each() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for seed in 0..3 {
            let s = format!("seed{seed}");
            put(
                d,
                "ctxrace",
                "cmask",
                &s,
                &curve(40, 0.02 + 0.002 * seed as f64),
            );
            put(d, "paper", "cmask", &s, &curve(30, 0.01));
            put(d, "variant", "cmask", &s, &curve(25, 0.015));
            put(d, "ctxrace", "dreamerv3", &s, &curve(20, 0.03));
        }
        // a run still starting and a folder that is not a seed are left out
        std::fs::create_dir_all(d.join("paper/cmask/seed3")).unwrap();
        std::fs::create_dir_all(d.join("paper/cmask/logs")).unwrap();
        let curves = load(d).unwrap();
        let names: Vec<&str> = curves.iter().map(|c| c.algo.as_str()).collect();
        assert_eq!(names, ["cmask", "dreamerv3"]);
        let cmask = &curves[0];
        let sides: Vec<(&str, usize)> = cmask
            .sides
            .iter()
            .map(|(side, seeds)| (side.as_str(), seeds.len()))
            .collect();
        assert_eq!(sides, [("ctxrace", 3), ("variant", 3), ("paper", 3)]);
        assert_eq!(cmask.sides[2].1[2].1.len(), 30);
        assert!(cmask.sides[2].1[0].1[0].a2a);
        assert_eq!(curves[1].sides.len(), 1);

        let out = d.join("report");
        std::fs::create_dir_all(&out).unwrap();
        let files = crate::figures::write_parity(&curves, &out).unwrap();
        assert_eq!(files.len(), 4, "{files:?}");
        for f in &files {
            assert!(
                std::fs::metadata(f).unwrap().len() > 1000,
                "{}",
                f.display()
            );
        }
        assert!(out.join("parity_cmask.png").is_file());
        assert!(out.join("parity_dreamerv3.svg").is_file());
    }

    #[test]
    fn a_bad_curve_is_named_and_an_empty_folder_says_what_it_expects() {
        let dir = tempfile::tempdir().unwrap();
        let err = format!("{:#}", load(dir.path()).unwrap_err());
        assert!(
            err.contains("no training curve") && err.contains("paper_parity.sh"),
            "{err}"
        );
        let mut text = curve(3, 0.1);
        text += "oops,0,0,3,0,0,0.5,0,false,false,1,50\n";
        put(dir.path(), "paper", "cmask", "seed0", &text);
        let err = format!("{:#}", load(dir.path()).unwrap_err());
        assert!(
            err.contains("paper/cmask/seed0/episodes.csv row 5"),
            "{err}"
        );
        let err = format!("{:#}", load(&dir.path().join("none")).unwrap_err());
        assert!(err.contains("no such folder"), "{err}");
    }
}
