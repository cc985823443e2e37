//! Checks on the paper's maps (read from ../shared/tracks; the tests fail when it is absent).

use ctxrace_tracks::files::{load_centreline, load_raceline, shared_reference, TrackFiles};
use ctxrace_tracks::{OccupancyMap, Walls};
use std::path::PathBuf;

fn shared_tracks() -> PathBuf {
    shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn walls_enclose_the_centreline_of_both_paper_maps() {
    let dir = shared_tracks();
    for name in ["f1_esp", "f1_gbr"] {
        let files = TrackFiles::resolve(name, &dir).unwrap();
        let t0 = std::time::Instant::now();
        let map = OccupancyMap::load(&files.yaml).unwrap();
        let walls = Walls::from_map(&map);
        let centre = load_centreline(&files.centreline).unwrap();
        eprintln!(
            "{name}: {} wall loops, {} segments, traced in {:?}, centreline {:.1} m",
            walls.loops().len(),
            walls.segment_count(),
            t0.elapsed(),
            centre.curve.length()
        );
        // the drawn corridor is what is raced on: every centreline point is clear of the walls
        let min_clear = centre
            .curve
            .points()
            .iter()
            .map(|p| walls.distance(p))
            .fold(f64::INFINITY, f64::min);
        assert!(
            min_clear > 0.4,
            "{name}: centreline comes within {min_clear} m of a wall"
        );
        let raceline = load_raceline(&files.raceline).unwrap();
        assert!(raceline.curve.length() > 100.0);
    }
}

/// `occupied_at` reads the pixel holding a point, as the paper's gym tested a car's centre: the
/// centreline is free, points outside the image count as occupied, and the pixel test and the
/// traced walls agree on each side of a wall up to the tracing's half-pixel simplification.
#[test]
fn occupied_at_reads_the_pixel_holding_a_point() {
    let files = TrackFiles::resolve("f1_esp", &shared_tracks()).unwrap();
    let map = OccupancyMap::load(&files.yaml).unwrap();
    let walls = Walls::from_map(&map);
    let centre = load_centreline(&files.centreline).unwrap();
    assert!(centre.curve.points().iter().all(|p| !map.occupied_at(p)));
    let (lo, hi) = map.extent();
    for p in [lo - nalgebra::Vector2::new(0.01, 0.0), hi] {
        assert!(map.occupied_at(&p), "{p:?} is outside the image");
    }
    // walking left from the start across the wall: free until the pixel test says occupied,
    // and the traced wall lies within a pixel of that point
    let step = map.resolution / 10.0;
    let first = (0..400)
        .map(|k| nalgebra::Point2::new(0.0, k as f64 * step))
        .find(|p| map.occupied_at(p))
        .expect("a wall within 2 m left of the start");
    let wall = walls.distance(&first);
    assert!(
        wall <= map.resolution,
        "{first:?} is {wall} m from the traced wall"
    );
}
