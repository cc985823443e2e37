//! `ctxrace track info|raceline|check|download`.

use crate::TrackArgs;
use anyhow::{Context, Result};
use clap::Subcommand;
use ctxrace_config::RaceConfig;
use ctxrace_sim::track_check::{check_track, CheckPlan};
use ctxrace_tracks::files::write_raceline;
use ctxrace_tracks::Track;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::Arc;

/// Track subcommands.
#[derive(Subcommand)]
pub enum TrackCommand {
    /// Length, width statistics, raceline length and lap time.
    Info {
        /// Track name, path to a map yaml, or generated:SEED.
        track: String,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        tracks: TrackArgs,
    },
    /// Write the computed raceline in the paper's dialect (s,x,y,psi,kappa,vx,ax).
    Raceline {
        /// Track name, path to a map yaml, or generated:SEED.
        track: String,
        /// Output CSV file.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        tracks: TrackArgs,
    },
    /// Whether a map is raceable: the pure-pursuit ego laps alone, rivals in every evaluation
    /// context drive from each grid place round to the line with the ego standing on it, the
    /// track is wide enough and the raceline's curvature within the car's steering; if not,
    /// what fails where (and an error exit).
    Check {
        /// Track name, path to a map yaml, or generated:SEED.
        track: String,
        /// Contexts per axis of the grid (the evaluation protocol's: 7).
        #[arg(long, default_value_t = CheckPlan::default().grid)]
        grid: usize,
        /// Half-width of the contexts' grid.
        #[arg(long, default_value_t = CheckPlan::default().range)]
        range: f64,
        /// Check rivals from grid places 1 to this (each a race with that many rivals).
        #[arg(long, default_value_t = CheckPlan::default().places)]
        places: usize,
        /// Race config TOML (see configs/).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        tracks: TrackArgs,
    },
    /// Fetch tracks from their public repositories (the paper's for f1_*, the F1TENTH
    /// racetracks' for the others) into the per-user tracks folder, where names resolve too.
    Download {
        /// Track names, e.g. f1_esp f1_gbr Monza.
        #[arg(required = true)]
        names: Vec<String>,
        /// Fetch from this base URL instead (a mirror with the repositories' layout).
        #[arg(long)]
        from: Option<String>,
        /// Download into this folder [default: $CTXRACE_DATA_DIR/tracks, else
        /// $XDG_DATA_HOME/ctxrace/tracks, else ~/.local/share/ctxrace/tracks].
        #[arg(long)]
        into: Option<PathBuf>,
    },
}

/// Minimum, mean and maximum of a series.
#[derive(Serialize)]
struct Stats {
    min: f64,
    mean: f64,
    max: f64,
}

impl Stats {
    fn of(v: impl Iterator<Item = f64>) -> Self {
        let (mut min, mut max, mut sum, mut n) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0usize);
        for x in v {
            min = min.min(x);
            max = max.max(x);
            sum += x;
            n += 1;
        }
        Self {
            min,
            mean: sum / n.max(1) as f64,
            max,
        }
    }
}

#[derive(Serialize)]
struct TrackInfo {
    name: String,
    length_m: f64,
    centreline_points: usize,
    /// w_left + w_right from the centreline file (or generator).
    listed_width_m: Stats,
    /// Wall-to-wall width across the centreline, measured on the walls.
    drawn_width_m: Stats,
    wall_segments: usize,
    raceline_length_m: f64,
    raceline_lap_time_s: f64,
    raceline_max_speed_mps: f64,
}

fn info(track: &Track) -> TrackInfo {
    let c = &track.centreline;
    let pts = c.curve.points();
    let drawn = track.drawn_widths().into_iter();
    TrackInfo {
        name: track.name.clone(),
        length_m: track.length(),
        centreline_points: pts.len(),
        listed_width_m: Stats::of(c.w_left.iter().zip(&c.w_right).map(|(l, r)| l + r)),
        drawn_width_m: Stats::of(drawn),
        wall_segments: track.walls.segment_count(),
        raceline_length_m: track.raceline.curve.length(),
        raceline_lap_time_s: track.raceline.lap_time(),
        raceline_max_speed_mps: track.raceline.speed.iter().copied().fold(0.0, f64::max),
    }
}

/// Runs a track subcommand.
pub fn run(cmd: TrackCommand) -> Result<()> {
    match cmd {
        TrackCommand::Info {
            track,
            json,
            tracks,
        } => {
            let t = tracks.load(&track, &RaceConfig::default())?;
            let i = info(&t);
            if json {
                println!("{}", serde_json::to_string_pretty(&i)?);
            } else {
                let s = |s: &Stats| format!("{:.2} / {:.2} / {:.2}", s.min, s.mean, s.max);
                println!("track            {}", i.name);
                println!(
                    "length           {:.2} m ({} centreline points)",
                    i.length_m, i.centreline_points
                );
                println!(
                    "listed width     {} m (min / mean / max)",
                    s(&i.listed_width_m)
                );
                println!("drawn width      {} m (wall to wall)", s(&i.drawn_width_m));
                println!("walls            {} segments", i.wall_segments);
                println!(
                    "raceline         {:.2} m, lap {:.2} s at up to {:.2} m/s",
                    i.raceline_length_m, i.raceline_lap_time_s, i.raceline_max_speed_mps
                );
            }
        }
        TrackCommand::Check {
            track,
            grid,
            range,
            places,
            config,
            json,
            tracks,
        } => {
            if grid == 0 || places == 0 || !(0.0..=0.9).contains(&range) {
                anyhow::bail!(
                    "--grid {grid} and --places {places} must be positive and --range {range} \
                     in [0, 0.9]"
                );
            }
            let race = crate::load_race_config(config.as_ref())?;
            let t = Arc::new(tracks.load(&track, &race)?);
            let plan = CheckPlan {
                grid,
                range,
                places,
            };
            let report = check_track(t, &race, plan)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                println!("{}", report.to_text(false));
            }
            anyhow::ensure!(
                report.raceable(),
                "{} is not raceable: {} check(s) fail",
                report.track,
                report.findings.iter().filter(|f| !f.passed).count()
            );
        }
        TrackCommand::Download { names, from, into } => {
            crate::download::run(&names, from.as_deref(), into.as_deref())?
        }
        TrackCommand::Raceline { track, out, tracks } => {
            let t = tracks.load(&track, &RaceConfig::default())?;
            // atomically, without following a link at `out`
            ctxrace_run::run_dir::write_atomic_with(&out, |_, file| {
                let mut w = std::io::BufWriter::new(file);
                write_raceline(&t.raceline, &mut w).and_then(|_| std::io::Write::flush(&mut w))
            })
            .with_context(|| format!("writing {}", out.display()))?;
            println!(
                "wrote {} ({} points, {:.2} m, lap {:.2} s)",
                out.display(),
                t.raceline.curve.len(),
                t.raceline.curve.length(),
                t.raceline.lap_time()
            );
        }
    }
    Ok(())
}
