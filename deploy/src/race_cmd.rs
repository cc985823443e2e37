//! `ctxrace race`: one episode with a reference ego policy, its metrics, picture and trace.

use crate::ego::EgoSpec;
use crate::TrackArgs;
use anyhow::{Context as _, Result};
use clap::Args;
use ctxrace_config::Context;
use ctxrace_render::race::{check_render_path, drive_recorded, race_title, render_race, Frame};
use ctxrace_run::trained::CheckpointChoice;
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::ActMode;
use ctxrace_sim::vehicle::idx;
use ctxrace_sim::RaceEnv;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Arguments of `ctxrace race`.
#[derive(Args)]
pub struct RaceArgs {
    /// Track name, path to a map yaml, or generated:SEED.
    track: String,
    /// Number of rivals, 0 to 7 [default: the config's, 1].
    #[arg(long)]
    rivals: Option<usize>,
    /// Rival context CV,CT (speed and steering coefficients).
    #[arg(long, default_value = "0,0", allow_hyphen_values = true)]
    context: Context,
    /// Ego policy: pure-pursuit (raceline at full speed), follow-the-gap (reactive, on its own
    /// scan, with the parameters of [rival.follow_the_gap]), random, or still.
    #[arg(long, default_value = "pure-pursuit")]
    ego: BaselineKind,
    /// Drive the ego with a trained agent instead: a checkpoint or run directory (in the run's
    /// race scenario unless --config is given), or a policy trained elsewhere as an MLP file
    /// (`*.safetensors`, written by Python's ctxrace.save_mlp_policy).
    #[arg(long)]
    policy: Option<PathBuf>,
    /// Which checkpoint of a run directory: best, latest or step-N.
    #[arg(long, default_value_t = CheckpointChoice::default())]
    checkpoint: CheckpointChoice,
    /// How a trained agent acts: sample (seeded by --seed) or mode.
    #[arg(long, value_enum, default_value_t = ActMode::default())]
    act: ActMode,
    /// Episode seed (LiDAR noise, random policy).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Race config TOML (see configs/); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Draw the track and every car's path coloured by speed: a still (.png or .svg) or an
    /// animation of the cars on the track (.gif).
    #[arg(long)]
    render: Option<PathBuf>,
    /// Write per-step poses, speeds, actions and the ego scan as CSV.
    #[arg(long)]
    trace: Option<PathBuf>,
    /// Print the metrics as JSON.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    tracks: TrackArgs,
}

#[derive(Serialize)]
struct RaceReport<'a> {
    track: &'a str,
    rivals: usize,
    context: [f64; 2],
    ego: String,
    seed: u64,
    #[serde(flatten)]
    metrics: &'a ctxrace_sim::EpisodeMetrics,
    ended_by: &'static str,
}

/// Runs one episode.
pub fn run(args: RaceArgs) -> Result<()> {
    if let Some(path) = &args.render {
        check_render_path(path)?;
    }
    let spec = match &args.policy {
        Some(path) => EgoSpec::load(path, args.checkpoint)?,
        None => EgoSpec::Baseline(args.ego),
    };
    let mut cfg = match (&spec, &args.config) {
        (EgoSpec::Trained(t), None) => t.race(),
        (_, config) => crate::load_race_config(config.as_ref())?,
    };
    if let Some(n) = args.rivals {
        cfg.rivals = n;
    }
    let track = Arc::new(args.tracks.load(&args.track, &cfg)?);
    let mut env = RaceEnv::new(track.clone(), cfg)?;
    let mut policy = spec.driver(&env, args.act)?;
    let mut frames = Vec::new();
    drive_recorded(&mut policy, &mut env, args.context, args.seed, &mut frames)?;
    let m = env.metrics();
    let ended_by = m.ended_by();
    if args.json {
        let report = RaceReport {
            track: &track.name,
            rivals: env.config().rivals,
            context: args.context.to_array(),
            ego: spec.name(),
            seed: args.seed,
            metrics: m,
            ended_by,
        };
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "track {} · {} rivals · context {:+.2},{:+.2} · ego {} · seed {}",
            track.name,
            env.config().rivals,
            args.context.speed,
            args.context.steer,
            spec.name(),
            args.seed
        );
        println!("ended by        {ended_by} after {} decisions", m.steps);
        println!("progress (PG)   {:.4}", m.progress);
        println!("overtakes (OT)  {}", m.overtakes);
        println!("rival collision {}", m.a2a);
        println!("wall crash      {}", m.wall_crash);
        match m.lap_time {
            Some(t) => println!("lap time        {t:.2} s"),
            None => println!("lap time        -"),
        }
        println!("return          {:.3}", m.episode_return);
        println!("rivals crashed  {}", m.rivals_crashed);
    }
    if let Some(path) = &args.render {
        let title = race_title(&track.name, &spec.name(), &env);
        render_race(path, &track, &frames, &title)?;
        eprintln!("rendered {}", path.display());
    }
    if let Some(path) = &args.trace {
        write_trace(path, &frames).with_context(|| format!("writing trace {}", path.display()))?;
        eprintln!("wrote trace {}", path.display());
    }
    Ok(())
}

/// Writes the trace CSV to `path`, atomically and without following a link there.
fn write_trace(path: &Path, frames: &[Frame]) -> Result<()> {
    ctxrace_run::run_dir::write_atomic_with(path, |_, file| trace_csv(file, frames))
}

/// The trace of `frames` as CSV into `file`: a row per step, the cars' states and the scan.
fn trace_csv(file: &mut std::fs::File, frames: &[Frame]) -> Result<()> {
    let mut w = std::io::BufWriter::new(file);
    let cars = frames.first().map_or(0, |f| f.cars.len());
    let beams = frames.first().map_or(0, |f| f.scan.len());
    let mut header = vec![
        "step".to_string(),
        "time".into(),
        "action_steer".into(),
        "action_speed".into(),
        "reward".into(),
    ];
    for c in 0..cars {
        let name = if c == 0 {
            "ego".to_string()
        } else {
            format!("rival{c}")
        };
        for f in ["x", "y", "yaw", "speed", "steer", "crashed"] {
            header.push(format!("{name}_{f}"));
        }
    }
    header.extend((0..beams).map(|b| format!("scan{b}")));
    writeln!(w, "{}", header.join(","))?;
    for (k, f) in frames.iter().enumerate() {
        // actions in full (the shortest text that reads back as the same number), so that
        // replaying them (in Python's env, say) drives the same race
        let mut row = vec![
            k.to_string(),
            format!("{:.2}", f.time),
            f.action[0].to_string(),
            f.action[1].to_string(),
            format!("{:.6}", f.reward),
        ];
        for c in &f.cars {
            row.extend(
                [
                    c.state[idx::X],
                    c.state[idx::Y],
                    c.state[idx::YAW],
                    c.state[idx::V],
                    c.state[idx::STEER],
                ]
                .iter()
                .map(|v| format!("{v:.6}")),
            );
            row.push((c.crashed as u8).to_string());
        }
        row.extend(f.scan.iter().map(|v| format!("{v:.5}")));
        writeln!(w, "{}", row.join(","))?;
    }
    w.flush()?;
    Ok(())
}
