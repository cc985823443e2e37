//! Follow-the-gap on the paper's maps (read from ../shared/tracks): as a rival alone, from each
//! of the three rivals' grid places, it laps f1_esp and f1_gbr without touching a wall in every
//! one of the 49 evaluation contexts (the zero context checked on its own first); as the
//! reference ego alone it laps f1_esp; in a race its rivals see the other cars and drive off.

use ctxrace_config::{Context, RaceConfig, RivalDriverKind};
use ctxrace_sim::baseline::BaselineKind;
use ctxrace_sim::driver::{BaselineEgo, Ego};
use ctxrace_sim::rival::drive_solo_lap;
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::files::shared_reference;
use ctxrace_tracks::{Track, TrackOptions};
use std::sync::Arc;

fn paper_track(name: &str) -> Track {
    let dir = shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
    let opts = TrackOptions {
        tracks_dir: dir,
        ..Default::default()
    };
    Track::load(name, &opts).unwrap()
}

fn gap_config() -> RaceConfig {
    let mut cfg = RaceConfig::default();
    cfg.rival.driver = RivalDriverKind::FollowTheGap;
    cfg
}

/// Every (context, grid place) whose solo lap of `track` did not complete, with where it hit
/// the wall; prints the slowest and fastest lap.
fn failures(track: &Track, contexts: &[Context]) -> Vec<(Context, usize, Option<f64>)> {
    let cfg = gap_config();
    let (mut slowest, mut fastest) = (0.0f64, f64::INFINITY);
    let mut failed = Vec::new();
    for &context in contexts {
        for place in 1..=3 {
            let start = place as f64 * cfg.grid_spacing(&track.name, track.length());
            let lap = drive_solo_lap(track, &cfg, context, start).unwrap();
            if lap.completed {
                slowest = slowest.max(lap.time);
                fastest = fastest.min(lap.time);
            } else {
                failed.push((context, place, lap.wall_hit_at));
            }
        }
    }
    eprintln!(
        "{}: laps of {fastest:.1} to {slowest:.1} s, {} failed",
        track.name,
        failed.len()
    );
    failed
}

#[test]
fn follow_the_gap_rivals_lap_f1_esp_alone_at_the_zero_context() {
    let failed = failures(&paper_track("f1_esp"), &[Context::default()]);
    assert!(failed.is_empty(), "laps that hit a wall: {failed:?}");
}

#[test]
fn follow_the_gap_rivals_lap_both_paper_tracks_in_all_49_contexts() {
    for name in ["f1_esp", "f1_gbr"] {
        let failed = failures(&paper_track(name), &Context::grid(7, 0.3));
        assert!(
            failed.is_empty(),
            "{name}: laps that hit a wall: {failed:?}"
        );
    }
}

#[test]
fn the_follow_the_gap_ego_laps_f1_esp_alone() {
    let cfg = RaceConfig {
        rivals: 0,
        ..RaceConfig::default()
    };
    let mut env = RaceEnv::new(Arc::new(paper_track("f1_esp")), cfg).unwrap();
    let mut ego = BaselineEgo::new(BaselineKind::FollowTheGap, &env);
    let info = ego.drive_episode(&mut env, Context::default(), 0).unwrap();
    let m = env.metrics();
    eprintln!("follow-the-gap ego on f1_esp: {m:?}");
    assert!(info.lap_complete && !m.wall_crash, "{m:?}");
}

/// Follow-the-gap rivals behind a standing ego: each scans from its own pose (a rival that saw
/// its own box would find no gap and not drive off), and none has hit anything 10 s in.
#[test]
fn follow_the_gap_rivals_drive_off_in_a_race() {
    let cfg = RaceConfig {
        rivals: 3,
        max_time: 10.0,
        ..gap_config()
    };
    let mut env = RaceEnv::new(Arc::new(paper_track("f1_esp")), cfg).unwrap();
    let mut ego = BaselineEgo::new(BaselineKind::Still, &env);
    let start: Vec<f64> = {
        env.reset(0, Context::default());
        env.cars().iter().map(|c| c.travelled).collect()
    };
    ego.drive_episode(&mut env, Context::default(), 0).unwrap();
    for (i, car) in env.cars().iter().enumerate().skip(1) {
        assert!(!car.crashed, "rival {i} crashed");
        assert!(
            car.travelled - start[i] > 30.0,
            "rival {i} drove {:.1} m",
            car.travelled - start[i]
        );
    }
}
