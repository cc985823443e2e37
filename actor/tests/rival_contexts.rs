//! Every one of the 49 evaluation contexts is drivable: a rival alone completes a lap of f1_esp and
//! f1_gbr (read from ../shared/tracks) on the computed raceline without touching a wall.

use ctxrace_actor::rival::drive_solo_lap;
use ctxrace_common::{Context, RaceConfig};
use ctxrace_tracks::{Track, TrackOptions};
use std::path::PathBuf;

fn shared_tracks() -> Option<PathBuf> {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/tracks");
    d.is_dir().then_some(d).or_else(|| {
        eprintln!("skipping: ../shared/tracks not found");
        None
    })
}

#[test]
fn rivals_lap_both_paper_tracks_in_all_49_contexts() {
    let Some(dir) = shared_tracks() else { return };
    let opts = TrackOptions {
        tracks_dir: dir,
        ..Default::default()
    };
    let cfg = RaceConfig::default();
    for name in ["f1_esp", "f1_gbr"] {
        let track = Track::load(name, &opts).unwrap();
        let mut failures = Vec::new();
        for ctx in Context::grid(7, 0.3) {
            let lap = drive_solo_lap(&track, &cfg, ctx, 0.0);
            if !lap.completed {
                failures.push(format!(
                    "{ctx:?}: wall at s = {:?} after {:.1} s",
                    lap.wall_hit_at, lap.time
                ));
            }
        }
        assert!(
            failures.is_empty(),
            "{name}: {} contexts fail:\n{}",
            failures.len(),
            failures.join("\n")
        );
    }
}
