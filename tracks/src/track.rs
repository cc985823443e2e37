//! A track ready to race on: centreline, raceline, walls, and the map image when there is one.

use crate::error::{Result, TrackError};
use crate::files::{default_tracks_dir, load_centreline, load_raceline, TrackFiles};
use crate::generate::{generate_track, wall_polylines, GeneratorParams};
use crate::map::OccupancyMap;
use crate::mincurv::{min_curvature_raceline, RacelineParams};
use crate::path::{Centreline, Projection, Raceline};
use crate::walls::Walls;
use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Prefix of a track argument that asks for a procedural track: `generated:SEED`.
pub const GENERATED_PREFIX: &str = "generated:";

/// Which raceline the rivals drive.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RacelineSource {
    /// The min-curvature raceline computed from the centreline (default).
    #[default]
    Computed,
    /// The `NAME_raceline.csv` shipped with the track.
    File,
}

/// How to find and build a track.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackOptions {
    /// Folder searched for track names.
    pub tracks_dir: PathBuf,
    /// Which raceline the rivals drive.
    pub raceline_source: RacelineSource,
    /// Parameters of the computed raceline.
    pub raceline: RacelineParams,
    /// Parameters of procedural tracks.
    pub generator: GeneratorParams,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            tracks_dir: default_tracks_dir(),
            raceline_source: RacelineSource::default(),
            raceline: RacelineParams::default(),
            generator: GeneratorParams::default(),
        }
    }
}

impl TrackOptions {
    /// The options a race loads its track with: names looked up in `tracks_dir` (without one,
    /// the default folders), and the rivals' raceline the one shipped with the map where
    /// `shipped_raceline` (a race config's choice), else the computed one.
    pub fn for_race(tracks_dir: Option<PathBuf>, shipped_raceline: bool) -> Self {
        let mut o = Self::default();
        if let Some(dir) = tracks_dir {
            o.tracks_dir = dir;
        }
        if shipped_raceline {
            o.raceline_source = RacelineSource::File;
        }
        o
    }
}

/// A track ready to race on.
#[derive(Clone, Debug)]
pub struct Track {
    /// Its name (`generated:SEED` for procedural tracks).
    pub name: String,
    /// The centreline, along which progress is measured.
    pub centreline: Centreline,
    /// The line the rivals follow.
    pub raceline: Raceline,
    /// The walls.
    pub walls: Walls,
    /// The map image, for tracks loaded from files.
    pub map: Option<OccupancyMap>,
}

impl Track {
    /// Loads `spec`: a track name in `opts.tracks_dir`, a path to a map yaml, or `generated:SEED`.
    pub fn load(spec: &str, opts: &TrackOptions) -> Result<Self> {
        opts.raceline.validate()?;
        if let Some(seed) = spec.strip_prefix(GENERATED_PREFIX) {
            let seed: u64 = seed.parse().map_err(|_| TrackError::Invalid {
                what: format!("track '{spec}'"),
                message: "the seed after 'generated:' must be a whole number, e.g. generated:7"
                    .into(),
            })?;
            return Self::generated(seed, opts);
        }
        let files = TrackFiles::resolve(spec, &opts.tracks_dir)?;
        let mut centreline = load_centreline(&files.centreline)?;
        let map = OccupancyMap::load(&files.yaml)?;
        check_map_matches(&map, &centreline, &files)?;
        let walls = Walls::from_map(&map);
        fit_widths_to_walls(&mut centreline, &walls);
        let raceline = match opts.raceline_source {
            RacelineSource::Computed => min_curvature_raceline(&centreline, &opts.raceline)?,
            RacelineSource::File => load_raceline(&files.raceline)?,
        };
        Ok(Self {
            name: files.name,
            centreline,
            raceline,
            walls,
            map: Some(map),
        })
    }

    /// A procedural track from a seed.
    pub fn generated(seed: u64, opts: &TrackOptions) -> Result<Self> {
        let centreline = generate_track(seed, &opts.generator)?;
        let walls = Walls::from_loops(wall_polylines(&centreline));
        let raceline = min_curvature_raceline(&centreline, &opts.raceline)?;
        Ok(Self {
            name: format!("{GENERATED_PREFIX}{seed}"),
            centreline,
            raceline,
            walls,
            map: None,
        })
    }

    /// Centreline length (m).
    pub fn length(&self) -> f64 {
        self.centreline.curve.length()
    }

    /// Wall-to-wall width across the centreline at each of its points (m, at most 40), as the
    /// walls are drawn on the map.
    pub fn drawn_widths(&self) -> Vec<f64> {
        let curve = &self.centreline.curve;
        let pts = curve.points();
        (0..pts.len())
            .map(|i| {
                let d = curve.segment_vector(i).normalize();
                let normal = Vector2::new(-d.y as f32, d.x as f32);
                let o = Point2::new(pts[i].x as f32, pts[i].y as f32);
                let side =
                    |dir: Vector2<f32>| self.walls.cast_ray(o, dir, 20.0).unwrap_or(20.0) as f64;
                side(normal) + side(-normal)
            })
            .collect()
    }

    /// Projects a point on the centreline, searching near `hint` when given.
    pub fn project(&self, p: &Point2<f64>, hint: Option<usize>) -> Projection {
        match hint {
            Some(h) => self.centreline.curve.project_near(p, h),
            None => self.centreline.curve.project(p),
        }
    }
}

/// Narrows the listed widths to the drawn corridor: the walls traced from the image are what is
/// raced on, and on the paper's maps they are up to ~0.1 m closer than the CSV widths say. Each
/// side's width becomes `min(listed, distance to the wall along the normal)`.
fn fit_widths_to_walls(centreline: &mut Centreline, walls: &Walls) {
    let curve = &centreline.curve;
    let n = curve.len();
    for i in 0..n {
        let tangent = (curve.segment_vector(i + n - 1).normalize()
            + curve.segment_vector(i).normalize())
        .normalize();
        let left = nalgebra::Vector2::new(-tangent.y as f32, tangent.x as f32);
        let p = curve.points()[i];
        let o = Point2::new(p.x as f32, p.y as f32);
        let reach = |dir, listed: f64| {
            walls
                .cast_ray(o, dir, listed as f32 + 1.0)
                .map_or(listed, |d| listed.min(d as f64))
        };
        centreline.w_left[i] = reach(left, centreline.w_left[i]);
        centreline.w_right[i] = reach(-left, centreline.w_right[i]);
    }
}

/// Checks that the centreline lies on the map image and starts on a drivable pixel, so that a map
/// and a centreline from different tracks (or a wrong origin/resolution) are caught early.
fn check_map_matches(
    map: &OccupancyMap,
    centreline: &Centreline,
    files: &TrackFiles,
) -> Result<()> {
    let mismatch = |message: String| TrackError::Map {
        path: files.yaml.clone(),
        message,
    };
    let outside = centreline
        .curve
        .points()
        .iter()
        .filter(|p| map.pixel_of(p).is_none())
        .count();
    if outside > 0 {
        let (lo, hi) = map.extent();
        return Err(mismatch(format!(
            "{outside} points of {} lie outside the image, which covers x {:.2}..{:.2}, y {:.2}..{:.2}; \
             check the yaml's origin and resolution, and that the image and centreline are of the same track",
            files.centreline.display(),
            lo.x,
            hi.x,
            lo.y,
            hi.y
        )));
    }
    let start = centreline.curve.points()[0];
    let (c, r) = map.pixel_of(&start).unwrap_or_default();
    if map.is_occupied(c as isize, r as isize) {
        return Err(mismatch(format!(
            "the centreline starts at ({:.2}, {:.2}), an occupied pixel of {}; check the yaml's origin \
             and resolution, and that the image and centreline are of the same track",
            start.x,
            start.y,
            map.image_path.display()
        )));
    }
    Ok(())
}
