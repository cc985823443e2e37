//! The starting grid: where a car stands at its grid place.

use ctxrace_config::GridLine;
use ctxrace_tracks::Track;
use nalgebra::Point2;

/// The pose `(position, heading)` of a car at centreline arc length `s` of `track`: on the
/// centreline, or on the raceline at the point nearest the centreline's (`grid_line`), facing
/// along that line.
pub fn grid_pose(track: &Track, grid_line: GridLine, s: f64) -> (Point2<f64>, f64) {
    let centre = &track.centreline.curve;
    match grid_line {
        GridLine::Centreline => (centre.point_at(s), centre.heading_at(s)),
        GridLine::Raceline => {
            let line = &track.raceline.curve;
            let on_line = line.project(&centre.point_at(s)).s;
            (line.point_at(on_line), line.heading_at(on_line))
        }
    }
}
