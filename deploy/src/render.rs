//! Pictures of a race: walls, centreline and raceline, and every car's path coloured by speed
//! (viridis: dark blue slow, yellow fast), with the cars' final footprints (ego red, rivals blue, a
//! crashed car filled).

use crate::plot::{plot_err, save, Figure};
use anyhow::Result;
use ctxrace_actor::vehicle::{idx, State, VehicleParams};
use ctxrace_actor::RaceEnv;
use ctxrace_tracks::Track;
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use std::path::Path;

/// A chart in track coordinates (metres).
pub type TrackChart<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// A car at one decision.
#[derive(Clone, Debug)]
pub struct CarSnapshot {
    /// Its state.
    pub state: State,
    /// Whether it has crashed.
    pub crashed: bool,
}

/// The race at one decision.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Episode time (s).
    pub time: f64,
    /// The ego action that led here.
    pub action: [f64; 2],
    /// The reward received.
    pub reward: f64,
    /// The ego observation.
    pub scan: Vec<f32>,
    /// Every car, ego first.
    pub cars: Vec<CarSnapshot>,
}

impl Frame {
    /// Records the environment's current state.
    pub fn capture(env: &RaceEnv, action: [f64; 2], reward: f64, scan: &[f32]) -> Self {
        let steps = env.metrics().steps as f64;
        Self {
            time: steps * env.config().physics_steps_per_action as f64 * 0.01,
            action,
            reward,
            scan: scan.to_vec(),
            cars: env
                .cars()
                .iter()
                .map(|c| CarSnapshot {
                    state: c.vehicle.state,
                    crashed: c.crashed,
                })
                .collect(),
        }
    }
}

/// Pixels per metre of the picture's longer side target.
const WIDTH_PX: u32 = 1600;

/// Draws the race into a PNG or SVG chosen by the file extension.
pub fn render_race(path: &Path, track: &Track, frames: &[Frame]) -> Result<()> {
    save(&RacePicture { track, frames }, path)
}

/// The race picture of [`render_race`].
struct RacePicture<'a> {
    track: &'a Track,
    frames: &'a [Frame],
}

impl Figure for RacePicture<'_> {
    fn size(&self) -> (u32, u32) {
        track_picture_size(self.track)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        let (lo, hi) = bounds(self.track);
        root.fill(&WHITE).map_err(plot_err)?;
        let mut chart = ChartBuilder::on(root)
            .margin(10)
            .build_cartesian_2d(lo.0..hi.0, lo.1..hi.1)
            .map_err(plot_err)?;
        draw_track(&mut chart, self.track)?;
        draw_cars(&mut chart, self.frames)
    }
}

/// Pixel size of a picture of the whole track: [`WIDTH_PX`] wide, the track's aspect ratio.
pub fn track_picture_size(track: &Track) -> (u32, u32) {
    let (lo, hi) = bounds(track);
    let aspect = (hi.1 - lo.1) / (hi.0 - lo.0);
    (
        WIDTH_PX,
        ((WIDTH_PX as f64) * aspect).round().max(200.0) as u32,
    )
}

/// The track's bounding box with a metre of margin: `(min, max)` corners.
pub fn bounds(track: &Track) -> ((f64, f64), (f64, f64)) {
    let mut lo = (f64::INFINITY, f64::INFINITY);
    let mut hi = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    let pts = track
        .walls
        .loops()
        .iter()
        .flatten()
        .chain(track.centreline.curve.points());
    for p in pts {
        lo = (lo.0.min(p.x), lo.1.min(p.y));
        hi = (hi.0.max(p.x), hi.1.max(p.y));
    }
    let pad = 1.0;
    ((lo.0 - pad, lo.1 - pad), (hi.0 + pad, hi.1 + pad))
}

/// Closes a loop of points for drawing.
fn closed(pts: &[nalgebra::Point2<f64>]) -> Vec<(f64, f64)> {
    pts.iter().chain(pts.first()).map(|p| (p.x, p.y)).collect()
}

/// Draws the walls, the centreline (grey), the raceline (pale green) and the start/finish line.
pub fn draw_track<DB: DrawingBackend>(chart: &mut TrackChart<DB>, track: &Track) -> Result<()>
where
    DB::ErrorType: 'static,
{
    for wall in track.walls.loops() {
        chart
            .draw_series(std::iter::once(PathElement::new(
                closed(wall),
                BLACK.stroke_width(2),
            )))
            .map_err(plot_err)?;
    }
    let grey = RGBColor(200, 200, 200);
    chart
        .draw_series(std::iter::once(PathElement::new(
            closed(track.centreline.curve.points()),
            grey.stroke_width(1),
        )))
        .map_err(plot_err)?;
    chart
        .draw_series(std::iter::once(PathElement::new(
            closed(track.raceline.curve.points()),
            RGBColor(150, 190, 150).stroke_width(1),
        )))
        .map_err(plot_err)?;
    // start/finish line across the track at s = 0
    let c = &track.centreline;
    let p0 = c.curve.points()[0];
    let d = c.curve.segment_vector(0).normalize();
    let (wr, wl) = c.widths_at(0.0);
    chart
        .draw_series(std::iter::once(PathElement::new(
            vec![
                (p0.x + d.y * wr, p0.y - d.x * wr),
                (p0.x - d.y * wl, p0.y + d.x * wl),
            ],
            BLACK.stroke_width(3),
        )))
        .map_err(plot_err)?;
    Ok(())
}

/// Draws every car's path coloured by speed and its final footprint.
fn draw_cars<DB: DrawingBackend>(chart: &mut TrackChart<DB>, frames: &[Frame]) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let n_cars = frames.first().map_or(0, |f| f.cars.len());
    let v_max = frames
        .iter()
        .flat_map(|f| f.cars.iter().map(|c| c.state[idx::V]))
        .fold(0.1, f64::max);
    for car in (0..n_cars).rev() {
        let width = if car == 0 { 4 } else { 2 };
        let segments = frames.windows(2).map(|w| {
            let (a, b) = (&w[0].cars[car].state, &w[1].cars[car].state);
            let colour = ViridisRGB::get_color_normalized(b[idx::V] as f32, 0.0, v_max as f32);
            PathElement::new(
                vec![(a[idx::X], a[idx::Y]), (b[idx::X], b[idx::Y])],
                colour.stroke_width(width),
            )
        });
        chart.draw_series(segments).map_err(plot_err)?;
        if let Some(last) = frames.last() {
            let snap = &last.cars[car];
            let colour = if car == 0 { RED } else { BLUE };
            let style = if snap.crashed {
                colour.filled()
            } else {
                colour.stroke_width(2)
            };
            chart
                .draw_series(std::iter::once(Polygon::new(footprint(&snap.state), style)))
                .map_err(plot_err)?;
        }
    }
    Ok(())
}

/// Corners of a car's rectangle.
fn footprint(s: &State) -> Vec<(f64, f64)> {
    let p = VehicleParams::default();
    let (l, w) = (p.length / 2.0, p.width / 2.0);
    let (sin, cos) = s[idx::YAW].sin_cos();
    [(l, w), (-l, w), (-l, -w), (l, -w)]
        .iter()
        .map(|(a, b)| (s[idx::X] + a * cos - b * sin, s[idx::Y] + a * sin + b * cos))
        .collect()
}
