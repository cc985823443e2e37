//! What `ctxrace train` shows when a run is complete: its learning curve (a table here and
//! `learning_curve.png`), a short evaluation of the trained agent on a 3 × 3 grid of contexts
//! beside the random and pure-pursuit egos, a picture and an animation of one of its races, and
//! the commands that go further (the full protocol, the report, TensorBoard).

use crate::ego::EgoSpec;
use crate::figures::{binned_curve, Band, CurveSeries, TrainingCurves, CURVE_PANELS};
use crate::TrackArgs;
use anyhow::Result;
use ctxrace_config::{Context, ExperimentConfig};
use ctxrace_render::figure::{register_font, save};
use ctxrace_render::race::{drive_recorded, race_title, render_race, Frame};
use ctxrace_run::results::{read_csv, TrainingEpisode};
use ctxrace_run::run_dir::TRAINING_EPISODES;
use ctxrace_run::trained::{CheckpointChoice, TrainedAgent};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::driver::Ego as _;
use ctxrace_sim::RaceEnv;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Laps per context of the short evaluation.
const LAPS: usize = 2;

/// Rows of the learning curve's table (bins of environment steps).
const CURVE_ROWS: usize = 10;

/// Width in characters of the table's PG bar at PG = 1.
const BAR_WIDTH: f64 = 30.0;

/// The picture of the learning curve in a run directory.
pub const LEARNING_CURVE: &str = "learning_curve.png";

/// Prints the run's learning curve (its training episodes' mean PG and return per bin of
/// environment steps, PG also as a bar) and draws it, as the report does, into
/// `<dir>/learning_curve.png`; returns the picture's path.
fn learning_curve(cfg: &ExperimentConfig, dir: &Path) -> Result<PathBuf> {
    let episodes: Vec<TrainingEpisode> = read_csv(&dir.join(TRAINING_EPISODES))?;
    let max_steps = episodes
        .iter()
        .map(|e| e.env_steps)
        .max()
        .unwrap_or(0)
        .max(1);
    let width = max_steps as f64 / CURVE_ROWS as f64;
    let runs = [episodes.as_slice()];
    let [(_, progress), (_, episode_return)] = CURVE_PANELS;
    let pg = binned_curve(&runs, progress, (CURVE_ROWS, width), Band::MinMax);
    let ret = binned_curve(&runs, episode_return, (CURVE_ROWS, width), Band::MinMax);
    println!(
        "\nlearning curve: {} training episodes, mean per {:.0} env steps",
        episodes.len(),
        width
    );
    println!("  {:>9} {:>7} {:>8}", "env steps", "PG", "return");
    for (p, r) in pg.iter().zip(&ret) {
        let bar = "#".repeat((p.1.clamp(0.0, 1.0) * BAR_WIDTH).round() as usize);
        println!("  {:>9.0} {:>7.3} {:>8.1}  {bar}", p.0, p.1, r.1);
    }
    register_font()?;
    let path = dir.join(LEARNING_CURVE);
    let curves = TrainingCurves {
        title: format!(
            "{} on {} against {} rival(s): training episodes",
            cfg.agent.algo, cfg.track, cfg.race.rivals
        ),
        series: vec![CurveSeries {
            label: format!("{}, seed {}", cfg.agent.algo, cfg.train.seed),
            runs: runs.to_vec(),
        }],
        band: Band::MinMax,
        panels: &CURVE_PANELS,
    };
    save(&curves, &path)?;
    Ok(path)
}

/// The metrics of one ego over the short evaluation.
#[derive(Default)]
struct Tally {
    progress_in: Vec<f64>,
    progress_out: Vec<f64>,
    overtakes: f64,
    a2a: usize,
    walls: usize,
    episodes: usize,
}

/// Prints the learning curve and the short evaluation of the run in `dir`, and writes
/// `<dir>/learning_curve.png`, `<dir>/race.png` and `<dir>/race.gif`.
pub fn show(cfg: &ExperimentConfig, dir: &Path, tracks: &TrackArgs) -> Result<()> {
    let curve = learning_curve(cfg, dir)?;
    let track = Arc::new(tracks.load(&cfg.track, &cfg.race)?);
    let mut env = RaceEnv::new(track.clone(), cfg.race.clone())?;
    let choice = if ctxrace_run::checkpoint::best_checkpoint(dir).is_some() {
        CheckpointChoice::Best
    } else {
        CheckpointChoice::Latest
    };
    let agent = EgoSpec::Trained(Box::new(TrainedAgent::load(dir, choice)?));
    let contexts = Context::grid(3, 0.3);
    println!(
        "\n{} ({choice} checkpoint) against {} rival(s) on {}, {} contexts x {LAPS} laps:",
        agent.name(),
        cfg.race.rivals,
        cfg.track,
        contexts.len()
    );
    println!(
        "  {:<14} {:>9} {:>9} {:>7} {:>8} {:>6}",
        "ego", "PG in", "PG out", "OT", "A2A/50", "wall"
    );
    let egos = [
        agent.clone(),
        EgoSpec::Baseline(BaselineKind::PurePursuit),
        EgoSpec::Baseline(BaselineKind::Random),
    ];
    for ego in &egos {
        let mut driver = ego.driver(&env, ActMode::Sample)?;
        let mut t = Tally::default();
        for (i, &context) in contexts.iter().enumerate() {
            for lap in 0..LAPS {
                driver.drive_episode(&mut env, context, (i * LAPS + lap) as u64)?;
                let m = env.metrics();
                if context.within(cfg.train.context_range) {
                    t.progress_in.push(m.progress);
                } else {
                    t.progress_out.push(m.progress);
                }
                t.overtakes += f64::from(m.overtakes);
                t.a2a += usize::from(m.a2a);
                t.walls += usize::from(m.wall_crash);
                t.episodes += 1;
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let n = t.episodes as f64;
        println!(
            "  {:<14} {:>9.3} {:>9.3} {:>+7.2} {:>8.1} {:>5.0}%",
            ego.name(),
            mean(&t.progress_in),
            mean(&t.progress_out),
            t.overtakes / n,
            t.a2a as f64 / n * 50.0,
            100.0 * t.walls as f64 / n
        );
    }
    let mut driver = agent.driver(&env, ActMode::Sample)?;
    let mut frames: Vec<Frame> = Vec::new();
    drive_recorded(&mut driver, &mut env, Context::default(), 0, &mut frames)?;
    let title = race_title(&cfg.track, &agent.name(), &env);
    let picture = dir.join("race.png");
    let animation = dir.join("race.gif");
    render_race(&picture, &track, &frames, &title)?;
    render_race(&animation, &track, &frames, &title)?;
    let d = dir.display();
    println!(
        "\nrun: {d} (the learning curve: {}; a race at c = (0, 0): {} and, animated, {})\nnext:\n  \
         ctxrace eval {d}                 # the paper's protocol: 7 x 7 contexts, 50 laps each\n  \
         ctxrace report {d} --out {d}/report\n  \
         tensorboard --logdir {}           # training curves",
        curve.display(),
        picture.display(),
        animation.display(),
        dir.parent().unwrap_or(Path::new(".")).display()
    );
    Ok(())
}
