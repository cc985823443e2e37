//! Track geometry for ctxrace: the paper's maps and the F1TENTH racetracks dialect, walls from the
//! map image, the centreline as a closed arc-length curve, the min-curvature raceline with its speed
//! profile, a procedural track generator, and (feature `download`) fetching tracks from their
//! public repositories.

#[cfg(feature = "download")]
pub mod download;
pub mod error;
pub mod files;
pub mod generate;
pub mod map;
pub mod mincurv;
pub mod path;
pub mod track;
pub mod walls;

pub use error::{ImageError, Result, TrackError};
pub use generate::{generate_track, wall_polylines, GeneratorParams};
pub use map::OccupancyMap;
pub use mincurv::{min_curvature_raceline, velocity_profile, RacelineParams};
pub use path::{Centreline, ClosedCurve, Projection, Raceline};
pub use track::{RacelineSource, Track, TrackOptions, GENERATED_PREFIX};
pub use walls::Walls;
