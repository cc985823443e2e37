//! Every one of the 49 evaluation contexts is drivable: a rival alone, from each of the three
//! rivals' places on the grid, completes a lap of f1_esp and f1_gbr (read from ../shared/tracks)
//! without hitting a wall, at the tables' rival speed factor 0.85 and starting grid. Checked for
//! ctxrace's scenario (computed raceline, its pure pursuit, footprint contact); the paper code's
//! race (shipped raceline, its pure pursuit, centre-point contact) is reported.

use ctxrace_config::{Context, RacePreset};
use ctxrace_sim::rival::drive_solo_lap;
use ctxrace_tracks::files::shared_reference;
use ctxrace_tracks::{RacelineSource, Track, TrackOptions};

/// A lap that hit a wall.
#[derive(Debug)]
struct Failure {
    track: String,
    context: Context,
    place: usize,
    /// Centreline arc length of the hit (m).
    wall_at: f64,
    /// Time driven before the hit (s).
    time: f64,
}

/// Every failing (track, context, grid place) of `preset`, printing the slowest lap per track.
fn failures(preset: RacePreset) -> Vec<Failure> {
    let dir = shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
    let cfg = preset.config();
    let opts = TrackOptions {
        tracks_dir: dir,
        raceline_source: if cfg.shipped_raceline {
            RacelineSource::File
        } else {
            RacelineSource::Computed
        },
        ..Default::default()
    };
    let mut failures = Vec::new();
    for name in ["f1_esp", "f1_gbr"] {
        let track = Track::load(name, &opts).unwrap();
        let mut slowest: f64 = 0.0;
        for context in Context::grid(7, 0.3) {
            for place in 1..=3 {
                let start = place as f64 * cfg.grid_spacing(name, track.length());
                let lap = drive_solo_lap(&track, &cfg, context, start).unwrap();
                if lap.completed {
                    slowest = slowest.max(lap.time);
                } else {
                    failures.push(Failure {
                        track: name.to_string(),
                        context,
                        place,
                        wall_at: lap.wall_hit_at.unwrap_or(f64::NAN),
                        time: lap.time,
                    });
                }
            }
        }
        eprintln!("{preset:?} {name}: slowest lap {slowest:.1} s");
    }
    for f in &failures {
        eprintln!(
            "{preset:?} {} ({:+.1}, {:+.1}) from place {}: wall at s = {:.1} after {:.1} s",
            f.track, f.context.speed, f.context.steer, f.place, f.wall_at, f.time
        );
    }
    failures
}

/// At the tables' grid, place 3 on f1_esp is 16.5 m out, 0.45 m beside the raceline and 3.5 m
/// before a bend: a rival standing on the centreline there, joining the line while it
/// accelerates hard, overshot it into the wall in fast contexts (`c_v >= 0.2`) within its first
/// second. On the raceline (`grid_line = "raceline"`, the default) every context laps from every
/// place.
#[test]
fn rivals_lap_both_paper_tracks_in_all_49_contexts() {
    let failed = failures(RacePreset::Default);
    assert!(
        failed.is_empty(),
        "{} laps hit a wall: {failed:?}",
        failed.len()
    );
}

/// The paper's code drives some out-of-distribution rivals into a wall (f1_esp at
/// `c = (0.3, 0.3)`), as its own runs did; every training context must be drivable.
#[test]
fn paper_code_rivals_lap_both_paper_tracks_in_every_training_context() {
    let failed = failures(RacePreset::PaperCode);
    let inside: Vec<_> = failed.iter().filter(|f| f.context.within(0.15)).collect();
    assert!(inside.is_empty(), "in-distribution failures: {inside:?}");
    eprintln!(
        "paper-code: {} of {} laps hit a wall, all out of distribution",
        failed.len(),
        2 * 49 * 3
    );
}
