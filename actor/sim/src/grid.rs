//! The starting grid: where a car stands at its grid place.

use ctxrace_config::GridLine;
use ctxrace_tracks::Track;
use nalgebra::Point2;

/// The pose `(position, heading)` of a car at grid distance `s` of `track`: at centreline arc
/// length `s` on the centreline, or on the raceline at the point nearest the centreline's,
/// facing along that line, or at `(s, 0)` on the map's x axis facing +x (`grid_line`).
pub fn grid_pose(track: &Track, grid_line: GridLine, s: f64) -> (Point2<f64>, f64) {
    let centre = &track.centreline.curve;
    match grid_line {
        GridLine::Centreline => (centre.point_at(s), centre.heading_at(s)),
        GridLine::XAxis => (Point2::new(s, 0.0), 0.0),
        GridLine::Raceline => {
            let line = &track.raceline.curve;
            let on_line = line.project(&centre.point_at(s)).s;
            (line.point_at(on_line), line.heading_at(on_line))
        }
    }
}
