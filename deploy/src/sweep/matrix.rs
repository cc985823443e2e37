//! A sweep's matrix file: its axes, the tables laid over the base experiment, how its runs
//! are trained, evaluated and ablated, and the runs it expands to (filtered by `--only`).

use anyhow::{bail, Context as _, Result};
use clap::ValueEnum as _;
use ctxrace_config::config_file::read_config_text;
use ctxrace_config::validate::toml_message;
use ctxrace_config::{AlgoKind, ContextMode, ExperimentConfig};
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::evaluation::ToldContext;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A matrix file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatrixFile {
    /// The experiment config every run starts from, relative to the matrix file.
    pub base: PathBuf,
    /// The algorithms.
    pub algos: Vec<AlgoKind>,
    /// The tracks.
    pub tracks: Vec<String>,
    /// The rival counts.
    pub rivals: Vec<usize>,
    /// The training seeds.
    pub seeds: Vec<u64>,
    /// An experiment-config fragment laid over the base for every run (before `algo`'s).
    #[serde(default)]
    pub experiment: toml::Table,
    /// Per algorithm (by name), an experiment-config fragment laid over the base.
    #[serde(default)]
    pub algo: BTreeMap<String, toml::Table>,
    /// How the runs are trained.
    #[serde(default)]
    pub train: SweepTrain,
    /// How the runs are evaluated.
    #[serde(default)]
    pub eval: SweepEval,
    /// The context ablation after each context-aware run's evaluation (none by default).
    #[serde(default)]
    pub ablation: Option<SweepAblation>,
}

/// The context ablation of a sweep (H6 of docs/table2/README.md): every cRSSM and cMask run
/// evaluated again under `[eval]`'s protocol with `laps` laps a context, told each context of
/// `told`, and every cMask run with its mask fixed at each of `masks`; each in
/// `<run>/ablation/<condition>`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepAblation {
    /// Laps per context (the main evaluation's first laps share their episode seeds).
    pub laps: usize,
    /// What cRSSM and cMask are told instead of the context: `zeros`, `other`.
    #[serde(default)]
    pub told: Vec<ToldContext>,
    /// The masks cMask is fixed at, `[m_v, m_θ]` in [0, 1].
    #[serde(default)]
    pub masks: Vec<[f32; 2]>,
}

/// One evaluation of a run: the protocol's, or one condition of the context ablation.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct EvalPass {
    /// Its output folder.
    pub(super) dir: PathBuf,
    /// Laps per context.
    pub(super) laps: usize,
    /// What the agent is told.
    pub(super) told: ToldContext,
    /// cMask's fixed mask.
    pub(super) mask: Option<[f32; 2]>,
}

/// How a sweep trains its runs.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepTrain {
    /// Actor processes per run; 0 trains inline (one process, continued exactly from its
    /// resume point if interrupted).
    pub actors: usize,
}

impl Default for SweepTrain {
    fn default() -> Self {
        Self { actors: 1 }
    }
}

/// How a sweep evaluates its runs (the paper's protocol by default).
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepEval {
    /// Grid points per context dimension.
    pub grid: usize,
    /// Half-width of the context grid.
    pub range: f64,
    /// Laps per context.
    pub laps: usize,
    /// Checkpoint evaluated: best, latest or step-N.
    pub checkpoint: String,
    /// How the agent acts.
    pub act: ActMode,
    /// Seed of the evaluation episodes.
    pub seed: u64,
    /// Race only these contexts of the grid, as `ctxrace eval --contexts` takes them (e.g.
    /// `"17-48"`, the paper's code's test contexts) [default: all].
    pub contexts: Option<String>,
}

impl Default for SweepEval {
    fn default() -> Self {
        use ctxrace_sim::eval_dir::{GRID, LAPS, RANGE};
        Self {
            grid: GRID,
            range: RANGE,
            laps: LAPS,
            checkpoint: ctxrace_run::trained::CheckpointChoice::default().to_string(),
            act: ActMode::default(),
            seed: 0,
            contexts: None,
        }
    }
}

impl SweepEval {
    /// The grid indices its `contexts` selects (none: the whole grid).
    pub(super) fn chosen(&self) -> Result<Option<Vec<usize>>> {
        Ok(self
            .contexts
            .as_deref()
            .map(|spec| ctxrace_sim::eval_dir::parse_contexts(spec, self.grid * self.grid))
            .transpose()?)
    }
}

/// One run of a matrix.
#[derive(Clone, Debug)]
pub struct MatrixRun {
    /// Its name and directory name.
    pub name: String,
    /// Its resolved experiment.
    pub config: ExperimentConfig,
}

impl MatrixFile {
    /// Reads a matrix file; errors name the file and the key.
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_config_text(path).context("reading the matrix")?;
        let m: Self = toml::from_str(&text).map_err(|e| {
            anyhow::anyhow!("parsing matrix {}: {}", path.display(), toml_message(&e))
        })?;
        for (axis, empty) in [
            ("algos", m.algos.is_empty()),
            ("tracks", m.tracks.is_empty()),
            ("rivals", m.rivals.is_empty()),
            ("seeds", m.seeds.is_empty()),
        ] {
            if empty {
                bail!("matrix {}: {axis} lists no value", path.display());
            }
        }
        for name in m.algo.keys() {
            if name.parse::<AlgoKind>().is_err() {
                bail!(
                    "matrix {}: [algo.{name}] names no algorithm (sac, dreamerv3, crssm, cmask)",
                    path.display()
                );
            }
        }
        m.eval
            .checkpoint
            .parse::<ctxrace_run::trained::CheckpointChoice>()
            .map_err(|e| anyhow::anyhow!("matrix {}: [eval] checkpoint: {e}", path.display()))?;
        m.eval
            .chosen()
            .with_context(|| format!("matrix {}: [eval] contexts", path.display()))?;
        if let Some(a) = &m.ablation {
            if a.laps == 0 || a.laps > m.eval.laps {
                bail!(
                    "matrix {}: [ablation] laps = {} must lie in 1..={} ([eval] laps: its \
                     baseline is the main evaluation's first laps)",
                    path.display(),
                    a.laps,
                    m.eval.laps
                );
            }
            if a.told.contains(&ToldContext::True) {
                bail!(
                    "matrix {}: [ablation] told lists \"true\", the main evaluation; use \
                     \"zeros\" or \"other\"",
                    path.display()
                );
            }
            if let Some(m) = a
                .masks
                .iter()
                .find(|m| !m.iter().all(|v| (0.0..=1.0).contains(v)))
            {
                bail!(
                    "matrix {}: [ablation] masks holds {m:?}; each value must lie in [0, 1]",
                    path.display()
                );
            }
        }
        Ok(m)
    }

    /// The evaluations of `run` (its folder `dir`): the protocol's in `dir/eval`, then for a
    /// context-aware agent each condition of the ablation in `dir/ablation/<condition>`.
    pub(super) fn passes(&self, run: &MatrixRun, dir: &Path) -> Vec<EvalPass> {
        let mut passes = vec![EvalPass {
            dir: dir.join("eval"),
            laps: self.eval.laps,
            told: ToldContext::True,
            mask: None,
        }];
        let mode = run.config.agent.algo.context_mode();
        if let (Some(a), true) = (&self.ablation, mode != ContextMode::None) {
            let condition = |name: String| dir.join("ablation").join(name);
            for &told in &a.told {
                let name = told.to_possible_value().map(|v| v.get_name().to_string());
                passes.push(EvalPass {
                    dir: condition(name.unwrap_or_default()),
                    laps: a.laps,
                    told,
                    mask: None,
                });
            }
            if mode == ContextMode::Cmask {
                for &[v, t] in &a.masks {
                    passes.push(EvalPass {
                        dir: condition(format!("mask-{v}-{t}")),
                        laps: a.laps,
                        told: ToldContext::True,
                        mask: Some([v, t]),
                    });
                }
            }
        }
        passes
    }

    /// Whether every evaluation of `run` (in `dir`) is complete.
    pub(super) fn is_evaluated(&self, run: &MatrixRun, dir: &Path) -> bool {
        self.passes(run, dir)
            .iter()
            .all(|pass| is_evaluated(pass, &self.eval))
    }

    /// Every run, algorithm-major (`algos` × `tracks` × `rivals` × the first `seeds` seeds),
    /// keeping those that `only` admits. `dir` is the matrix file's folder (for `base`).
    pub fn runs(&self, dir: &Path, seeds: Option<usize>, only: &Only) -> Result<Vec<MatrixRun>> {
        let base_path = dir.join(&self.base);
        let base_text = read_config_text(&base_path).context("reading the matrix's base")?;
        let base: toml::Table = toml::from_str(&base_text).map_err(|e| {
            anyhow::anyhow!("parsing {}: {}", base_path.display(), toml_message(&e))
        })?;
        let seeds = &self.seeds[..seeds.unwrap_or(self.seeds.len()).min(self.seeds.len())];
        let mut runs = Vec::new();
        let base = ctxrace_config::preset::merge_tables(base, self.experiment.clone());
        for &algo in &self.algos {
            let mut table = base.clone();
            if let Some(over) = self.algo.get(algo.name()) {
                table = ctxrace_config::preset::merge_tables(table, over.clone());
            }
            for track in &self.tracks {
                for &rivals in &self.rivals {
                    for &seed in seeds {
                        let axes = [
                            ("algo", algo.name().to_string()),
                            ("track", track.clone()),
                            ("rivals", rivals.to_string()),
                            ("seed", seed.to_string()),
                        ];
                        if !only.admits(&axes) {
                            continue;
                        }
                        let config = resolve(&table, algo, track, rivals, seed)
                            .with_context(|| format!("the run {algo} {track} {rivals}r s{seed}"))?;
                        runs.push(MatrixRun {
                            name: ctxrace_run::run_dir::run_name(&config),
                            config,
                        });
                    }
                }
            }
        }
        Ok(runs)
    }
}

/// The experiment of one run: `table` with the run's axis values set.
fn resolve(
    table: &toml::Table,
    algo: AlgoKind,
    track: &str,
    rivals: usize,
    seed: u64,
) -> Result<ExperimentConfig> {
    let text = toml::to_string(table)?;
    let mut cfg = ExperimentConfig::from_toml(&text, "the matrix's base")?;
    cfg.agent.algo = algo;
    cfg.track = track.to_string();
    cfg.race.rivals = rivals;
    cfg.train.seed = seed;
    cfg.agent.set_seed(seed);
    cfg.validate()?;
    Ok(cfg)
}

/// A `--only` filter: for each named axis, the values admitted.
#[derive(Clone, Debug, Default)]
pub struct Only(BTreeMap<String, Vec<String>>);

impl std::str::FromStr for Only {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let mut only = BTreeMap::<String, Vec<String>>::new();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let Some((key, value)) = part.split_once('=') else {
                return Err(format!(
                    "--only: '{part}' is not AXIS=VALUE, e.g. algo=cmask"
                ));
            };
            if !["algo", "track", "rivals", "seed"].contains(&key) {
                return Err(format!(
                    "--only: '{key}' is no axis; use algo, track, rivals or seed"
                ));
            }
            only.entry(key.into()).or_default().push(value.into());
        }
        Ok(Self(only))
    }
}

impl Only {
    /// Whether a run with these axis values passes.
    fn admits(&self, axes: &[(&str, String)]) -> bool {
        axes.iter()
            .all(|(k, v)| self.0.get(*k).is_none_or(|vals| vals.contains(v)))
    }
}

/// Whether `pass` of the sweep's protocol `eval` is complete.
pub(super) fn is_evaluated(pass: &EvalPass, eval: &SweepEval) -> bool {
    let eval_dir = &pass.dir;
    let Ok(meta) = ctxrace_run::results::read_json::<ctxrace_sim::evaluation::EvalMeta>(
        &eval_dir.join("meta.json"),
    ) else {
        return false;
    };
    eval_dir.join("contexts.csv").is_file()
        && (meta.grid, meta.laps, meta.seed, meta.act)
            == (eval.grid, pass.laps, eval.seed, eval.act)
        && (meta.told, meta.mask) == (pass.told, pass.mask)
        && meta.range == eval.range
        && meta.checkpoint == eval.checkpoint
        && eval.chosen().is_ok_and(|chosen| chosen == meta.contexts)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A matrix of 2 algorithms x 2 tracks x 2 rival counts x 3 seeds in `dir`, over a base
    /// of its own.
    pub(in crate::sweep) fn matrix(dir: &Path) -> MatrixFile {
        std::fs::write(
            dir.join("base.toml"),
            "[race]\nrivals = 1\n[agent]\nalgo = \"sac\"\n[train]\nenv_steps = 500\nprefill = 100\n",
        )
        .unwrap();
        let text = r#"base = "base.toml"
algos = ["sac", "cmask"]
tracks = ["f1_esp", "generated:3"]
rivals = [1, 3]
seeds = [10000, 10010, 10020]
[algo.sac.train]
train_ratio = 2.0
"#;
        std::fs::write(dir.join("m.toml"), text).unwrap();
        MatrixFile::load(&dir.join("m.toml")).unwrap()
    }

    #[test]
    fn the_matrix_expands_to_named_runs_with_their_overrides() {
        let dir = tempfile::tempdir().unwrap();
        let m = matrix(dir.path());
        let runs = m.runs(dir.path(), None, &Only::default()).unwrap();
        assert_eq!(runs.len(), 2 * 2 * 2 * 3);
        assert_eq!(runs[0].name, "sac-f1_esp-1r-s10000");
        assert_eq!(runs.last().unwrap().name, "cmask-generated_3-3r-s10020");
        let names: std::collections::HashSet<_> = runs.iter().map(|r| &r.name).collect();
        assert_eq!(names.len(), runs.len(), "names are unique");
        for r in &runs {
            let want = match r.config.agent.algo {
                AlgoKind::Sac => 2.0,
                AlgoKind::Dreamerv3 | AlgoKind::Crssm | AlgoKind::Cmask => 1.0,
            };
            assert_eq!(r.config.train.train_ratio, want, "{}", r.name);
            assert_eq!(r.config.train.env_steps, 500);
            assert_eq!(r.config.agent.seed(), r.config.train.seed);
        }
        let only: Only = "algo=cmask,rivals=3,seed=10000,seed=10020".parse().unwrap();
        let some = m.runs(dir.path(), Some(2), &only).unwrap();
        let names: Vec<_> = some.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            ["cmask-f1_esp-3r-s10000", "cmask-generated_3-3r-s10000"]
        );
        assert!("algo".parse::<Only>().unwrap_err().contains("AXIS=VALUE"));
        assert!("colour=red"
            .parse::<Only>()
            .unwrap_err()
            .contains("no axis"));
    }

    #[test]
    fn the_ablation_evaluates_context_aware_runs_again_under_each_condition() {
        let dir = tempfile::tempdir().unwrap();
        let m = matrix(dir.path());
        let text = std::fs::read_to_string(dir.path().join("m.toml")).unwrap();
        let with = |extra: &str| {
            std::fs::write(dir.path().join("a.toml"), format!("{text}{extra}")).unwrap();
            MatrixFile::load(&dir.path().join("a.toml"))
        };
        let a = with(
            "[ablation]\nlaps = 20\ntold = [\"zeros\", \"other\"]\nmasks = [[1, 0], [0.5, 1]]\n",
        )
        .unwrap();
        let runs = a.runs(dir.path(), Some(1), &Only::default()).unwrap();
        let run_dir = Path::new("out/r");
        let sac = runs
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Sac)
            .unwrap();
        let cmask = runs
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Cmask)
            .unwrap();
        assert_eq!(a.passes(sac, run_dir), m.passes(sac, run_dir));
        let passes = a.passes(cmask, run_dir);
        let dirs: Vec<_> = passes.iter().map(|p| p.dir.to_str().unwrap()).collect();
        assert_eq!(
            dirs,
            [
                "out/r/eval",
                "out/r/ablation/zeros",
                "out/r/ablation/other",
                "out/r/ablation/mask-1-0",
                "out/r/ablation/mask-0.5-1"
            ]
        );
        assert_eq!((passes[0].laps, passes[1].laps), (50, 20));
        assert_eq!(passes[2].told, ToldContext::Other);
        assert_eq!(passes[4].mask, Some([0.5, 1.0]));
        for (extra, says) in [
            ("[ablation]\nlaps = 0\n", "laps = 0 must lie in 1..=50"),
            ("[ablation]\nlaps = 60\n", "laps = 60 must lie in 1..=50"),
            (
                "[ablation]\nlaps = 5\ntold = [\"true\"]\n",
                "use \"zeros\" or \"other\"",
            ),
            (
                "[ablation]\nlaps = 5\nmasks = [[2, 0]]\n",
                "must lie in [0, 1]",
            ),
            (
                "[ablation]\nlaps = 5\ntold = [\"none\"]\n",
                "unknown variant",
            ),
        ] {
            let err = format!("{:#}", with(extra).unwrap_err());
            assert!(err.contains(says), "{extra}: {err}");
        }
    }

    #[test]
    fn the_shipped_paper_matrix_holds_its_80_runs() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/matrix.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        assert_eq!(runs.len(), 80);
        let cmask = runs
            .iter()
            .find(|r| r.name == "cmask-f1_gbr-3r-s10040")
            .unwrap();
        assert_eq!(cmask.config.train.env_steps, 100_000);
        assert_eq!(cmask.config.train.train_ratio, 1.0);
        let sac = runs
            .iter()
            .find(|r| r.name == "sac-f1_esp-1r-s10000")
            .unwrap();
        assert_eq!(
            (
                sac.config.train.train_ratio,
                sac.config.agent.sac.batch_size
            ),
            (2.0, 100)
        );
        assert_eq!(
            (m.eval.grid, m.eval.laps, m.eval.act),
            (7, 50, ActMode::Sample)
        );
    }

    #[test]
    fn the_shipped_reduced_matrix_keeps_the_protocol() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/reduced.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        assert_eq!(runs.len(), 8);
        assert_eq!((m.eval.grid, m.eval.range, m.eval.laps), (7, 0.3, 50));
        assert!(runs.iter().all(|r| r.config.train.context_range == 0.15));
    }

    #[test]
    fn bad_matrices_name_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let write = |text: &str| {
            let p = dir.path().join("bad.toml");
            std::fs::write(&p, text).unwrap();
            format!("{:#}", MatrixFile::load(&p).unwrap_err())
        };
        let axes = "base = \"b.toml\"\nalgos = [\"sac\"]\ntracks = [\"f1_esp\"]\nrivals = [1]\n";
        assert!(write(&format!("{axes}seeds = []\n")).contains("seeds lists no value"));
        assert!(write(&format!("{axes}seeds = [0]\n[algo.sack]\n")).contains("[algo.sack]"));
        assert!(write(&format!("{axes}seeds = [0]\ncolour = 1\n")).contains("colour"));
        assert!(write(&format!(
            "{axes}seeds = [0]\n[eval]\ncheckpoint = \"top\"\n"
        ))
        .contains("checkpoint"));
        let err = write(&format!(
            "{axes}seeds = [0]\n[eval]\ncontexts = \"40-60\"\n"
        ));
        assert!(
            err.contains("[eval] contexts") && err.contains("outside the grid"),
            "{err}"
        );
    }

    #[test]
    fn the_table2_matrix_evaluates_the_papers_protocol() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/paper/table2.toml");
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        // 4 algorithms x 1 and 3 rivals x 5 seeds
        assert_eq!(runs.len(), 40);
        // all 49 contexts of the 7 x 7 grid, 50 laps each, as the paper's text and means
        assert_eq!(m.eval.chosen().unwrap(), None);
        assert_eq!((m.eval.grid, m.eval.laps), (7, 50));
        assert!(runs
            .iter()
            .all(|r| r.config.race.preset == ctxrace_config::RacePreset::PaperCode));
        // the same env-step budget for every algorithm
        assert!(runs
            .iter()
            .all(|r| r.config.train.env_steps == runs[0].config.train.env_steps));
    }

    /// The runs of a shipped matrix file of configs/paper.
    fn paper_matrix(name: &str) -> (MatrixFile, Vec<MatrixRun>) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../configs/paper")
            .join(name);
        let m = MatrixFile::load(&path).unwrap();
        let runs = m
            .runs(path.parent().unwrap(), None, &Only::default())
            .unwrap();
        (m, runs)
    }

    #[test]
    fn the_protocol_matrices_lay_their_arms_over_the_tables_experiment() {
        use ctxrace_config::agents::{ImaginationContext, MaskSpace};
        let (_, table) = paper_matrix("table2.toml");
        let table_cmask = &table
            .iter()
            .find(|r| r.config.agent.algo == AlgoKind::Cmask)
            .unwrap()
            .config;
        let (_, more) = paper_matrix("table2-more-seeds.toml");
        assert_eq!(more.len(), 15);
        assert!(more.iter().all(|r| r.config.race.rivals == 1
            && r.config.train.seed >= 10_050
            && r.config.train.env_steps == table_cmask.train.env_steps));
        for (file, runs, alpha) in [
            ("table2-paper-mask.toml", 20, 1.0),
            ("table2-paper-mask-alpha0.05.toml", 5, 0.05),
        ] {
            let (_, arm) = paper_matrix(file);
            assert_eq!(arm.len(), runs, "{file}");
            let base = &table_cmask.race;
            for r in &arm {
                let mask = &r.config.agent.dreamer.mask;
                assert_eq!(mask.mask_space, MaskSpace::PaperCode, "{file}");
                assert_eq!(mask.imagination_context, ImaginationContext::Raw);
                assert_eq!((mask.lr, mask.init_alpha), (3e-5, alpha));
                // the rest of the experiment is the table's
                assert_eq!(r.config.train.env_steps, table_cmask.train.env_steps);
                assert_eq!(r.config.race.preset, base.preset);
            }
        }
        // the long runs: the table's experiment at the code's schedule, the code's mask for cMask
        let (_, long) = paper_matrix("long.toml");
        assert_eq!(long.len(), 6);
        for r in &long {
            let t = &r.config.train;
            assert_eq!((t.env_steps, t.train_ratio), (100_000, 1.0));
            assert_eq!(t.keep_best_at, [25_000, 50_000, 75_000]);
            assert_eq!(r.config.race.rival, table_cmask.race.rival);
            let code_mask = r.config.agent.dreamer.mask.mask_space == MaskSpace::PaperCode;
            assert_eq!(code_mask, r.config.agent.algo == AlgoKind::Cmask);
        }
    }
}
