//! The simulator as a library: a hand-written ego (steer towards the longest LiDAR beam, slow
//! down as the way ahead shortens) races context-scaled rivals on a track over a small grid of
//! contexts, and prints PG, OT and A2A per context and in and out of the training range, as
//! `ctxrace eval` computes them.
//!
//! ```sh
//! cargo run --release -p ctxrace-sim --example custom_ego              # generated:0, 1 rival
//! cargo run --release -p ctxrace-sim --example custom_ego -- f1_esp 3  # a map of the tracks folder
//! ```

use ctxrace_config::{Context, RaceConfig};
use ctxrace_sim::driver::{Ego, EgoAction};
use ctxrace_sim::eval_dir::TRAIN_RANGE;
use ctxrace_sim::evaluation::{episode_seed, run_episode, summarise, SplitMeans};
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::{Track, TrackOptions};
use std::convert::Infallible;
use std::sync::Arc;

/// Steers towards the longest beam of the scan (the way the track opens up) and drives as fast
/// as the beam straight ahead allows.
struct LongestBeam;

impl Ego for LongestBeam {
    type Error = Infallible;

    fn reset(&mut self, _env: &RaceEnv, _seed: u64) {}

    fn act(&mut self, _env: &RaceEnv, obs: &[f32]) -> Result<EgoAction, Infallible> {
        let n = obs.len();
        let (longest, _) =
            obs.iter().enumerate().fold(
                (n / 2, 0.0),
                |best, (i, &r)| if r > best.1 { (i, r) } else { best },
            );
        // beams run from the car's right (0) to its left (n − 1); a positive a₀ steers right
        let steer = -((longest as f64 / (n - 1) as f64) * 2.0 - 1.0);
        let ahead = f64::from(obs[n / 2]);
        let speed = (ahead * 2.0 - 1.0).clamp(-0.8, 0.0);
        Ok(([steer.clamp(-1.0, 1.0), speed], None))
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let spec = args.next().unwrap_or_else(|| "generated:0".into());
    let rivals: usize = args.next().map_or(Ok(1), |r| r.parse())?;
    let track = Arc::new(Track::load(&spec, &TrackOptions::default())?);
    let race = RaceConfig {
        rivals,
        ..RaceConfig::default()
    };
    let mut env = RaceEnv::new(track, race)?;
    let (laps, grid) = (3, Context::grid(3, 0.3));
    let mut episodes = Vec::new();
    for (index, &context) in grid.iter().enumerate() {
        for lap in 0..laps {
            let seed = episode_seed(0, index, lap);
            episodes.push(run_episode(
                &mut env,
                &mut LongestBeam,
                context,
                seed,
                lap,
                |_, _| {},
            )?);
        }
    }
    println!("{spec}, {rivals} rival(s), {laps} laps a context:");
    for c in summarise(&episodes, TRAIN_RANGE) {
        println!(
            "  c = ({:+.1}, {:+.1}): PG {:.3}  OT {:+.2}  A2A {:5.1}/50",
            c.context_speed, c.context_steer, c.progress, c.overtakes, c.a2a
        );
    }
    let summary = summarise(&episodes, TRAIN_RANGE);
    for (label, inside) in [("in", true), ("out", false)] {
        if let Some(m) = SplitMeans::split(&summary, inside) {
            println!(
                "  {label:>3} ({} contexts): PG {:.3}  OT {:+.3}  A2A {:.1}/50",
                m.contexts, m.progress, m.overtakes, m.a2a
            );
        }
    }
    Ok(())
}
