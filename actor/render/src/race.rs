//! Pictures of a race: walls, centreline and raceline, every car's path coloured by speed
//! (viridis: dark blue slow, yellow fast) and the cars' footprints (ego red, rivals blue, a
//! crashed car filled), under a title naming the track, the egos, the context and the outcome
//! and above a legend. As a `.gif`, the same race as an animation: the cars move, each trailing
//! its last seconds of path; one moment of it as an RGB picture ([`moment_rgb`]).

use crate::figure::{plot_err, register_font, save, Figure, RenderError, Result};
use ctxrace_config::RivalDriverKind;
use ctxrace_sim::driver::{DriveError, Ego};
use ctxrace_sim::vehicle::{idx, State, VehicleParams};
use ctxrace_sim::{RaceEnv, StepInfo};
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

/// Runs one episode of `env` under `context` from `seed` with `ego`, recording a frame after
/// the reset and after every decision into `frames`; returns the last step's details.
pub fn drive_recorded<E: Ego>(
    ego: &mut E,
    env: &mut RaceEnv,
    context: ctxrace_config::Context,
    seed: u64,
    frames: &mut Vec<Frame>,
) -> std::result::Result<StepInfo, DriveError<E::Error>> {
    ego.drive_observed(env, context, seed, |env, d| {
        frames.push(Frame::capture(env, d.action, d.reward, d.obs))
    })
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

/// Width in pixels of a still picture.
const WIDTH_PX: u32 = 1600;
/// Width in pixels of an animation (a 50-s race stays under 1 MB).
const GIF_WIDTH_PX: u32 = 1000;
/// Animation frames per second of race time (played in real time).
const GIF_FPS: f64 = 20.0;
/// Seconds of path each car trails in an animation.
const TRAIL_S: f64 = 3.0;
/// How long an animation holds its last frame (s).
const GIF_HOLD_S: f64 = 2.0;
/// Height of the title band of a still, in pixels (scaled with the width).
const TITLE_PX: u32 = 44;
/// Height of the legend band of a still, in pixels (scaled with the width).
const LEGEND_PX: u32 = 44;
/// The ego's colour.
const EGO: RGBColor = RGBColor(220, 30, 30);
/// The rivals' colour.
const RIVAL: RGBColor = RGBColor(30, 80, 220);
/// The raceline's colour.
const RACELINE: RGBColor = RGBColor(150, 190, 150);
/// The centreline's colour.
const CENTRELINE: RGBColor = RGBColor(200, 200, 200);

/// The title of a picture of `env`'s episode (the last one, or the one under way) driven by
/// `ego` on `track`: the cars, the rivals' context and the outcome (or the progress so far).
pub fn race_title(track: &str, ego: &str, env: &RaceEnv) -> String {
    let m = env.metrics();
    let c = env.context();
    let outcome = match m.lap_time {
        Some(t) => format!("lap complete in {t:.1} s"),
        None if !env.is_finished() => format!("racing, progress {:.2}", m.progress),
        None => format!("{} at progress {:.2}", m.ended_by(), m.progress),
    };
    // the paper's driver goes unnamed
    let driver = match env.config().rival.driver {
        d if d == RivalDriverKind::default() => String::new(),
        d => format!(" {d}"),
    };
    format!(
        "{track} · ego {ego} vs {}{driver} rival(s) at context c_v {:+.2}, c_t {:+.2} · {outcome}",
        env.config().rivals,
        c.speed,
        c.steer
    )
}

/// Draws the race under `title` into a PNG or SVG still, or a GIF animation, chosen by the
/// file extension.
pub fn render_race(path: &Path, track: &Track, frames: &[Frame], title: &str) -> Result<()> {
    check_render_path(path)?;
    if frames.is_empty() {
        return Err(RenderError::Refused(format!(
            "cannot draw {}: the race has no frames",
            path.display()
        )));
    }
    if is_animation(path) {
        write_gif(path, &RaceScene::new(track, frames, title, GIF_WIDTH_PX))
    } else {
        save(&RaceScene::new(track, frames, title, WIDTH_PX), path)
    }
}

/// Whether `path` names an animation (`.gif`) rather than a still.
fn is_animation(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()) == Some("gif")
}

/// Checks that [`render_race`] can draw to `path` (before a race is run for it).
pub fn check_render_path(path: &Path) -> Result<()> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("png" | "svg" | "gif") => Ok(()),
        _ => Err(RenderError::Refused(format!(
            "cannot draw to {}: the file name must end in .png or .svg (a still) or .gif (an \
             animation)",
            path.display()
        ))),
    }
}

/// Width in pixels of [`moment_rgb`]'s picture when none is asked for: an animation's.
pub const MOMENT_WIDTH_PX: u32 = GIF_WIDTH_PX;

/// An RGB picture: `height` rows of `width` pixels, three bytes each (red, green, blue).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbPicture {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// The pixels, row by row from the top.
    pub rgb: Vec<u8>,
}

/// The race at its last frame as an animation draws it, `width` pixels wide (at least 100):
/// each car filled and ringed at its place, trailing its last seconds of path coloured by
/// speed (the colour bar's top is the fastest of `frames`), the title with the moment's time.
pub fn moment_rgb(track: &Track, frames: &[Frame], title: &str, width: u32) -> Result<RgbPicture> {
    if frames.is_empty() {
        return Err(RenderError::Refused(
            "cannot draw the race: it has no frames (reset it first)".into(),
        ));
    }
    if width < 100 {
        return Err(RenderError::Refused(format!(
            "cannot draw the race {width} pixels wide: give at least 100"
        )));
    }
    let scene = RaceScene::new(track, frames, title, width).at(frames.len() - 1);
    let (width, height) = scene.size();
    let mut rgb = vec![0u8; width as usize * height as usize * 3];
    scene.draw_rgb(&mut rgb)?;
    Ok(RgbPicture { width, height, rgb })
}

/// A race picture: the whole race as a still, or (with `upto` and a trail) one moment of it.
#[derive(Clone)]
struct RaceScene<'a> {
    track: &'a Track,
    frames: &'a [Frame],
    title: &'a str,
    /// The frame whose footprints are drawn (and where the paths end).
    upto: usize,
    /// Seconds of path drawn behind each car; the whole race when `None`.
    trail_s: Option<f64>,
    /// The speed of the colour bar's top (the race's fastest), m/s.
    v_max: f64,
    /// Picture width in pixels.
    width: u32,
}

impl<'a> RaceScene<'a> {
    /// The whole race, `width` pixels wide (`frames` not empty).
    fn new(track: &'a Track, frames: &'a [Frame], title: &'a str, width: u32) -> Self {
        let v_max = frames
            .iter()
            .flat_map(|f| f.cars.iter().map(|c| c.state[idx::V]))
            .fold(0.1, f64::max);
        Self {
            track,
            frames,
            title,
            upto: frames.len() - 1,
            trail_s: None,
            v_max,
            width,
        }
    }

    /// Pixels per pixel of a [`WIDTH_PX`]-wide picture, for text and bands.
    fn scale(&self) -> f64 {
        f64::from(self.width) / f64::from(WIDTH_PX)
    }

    /// A band's height in this picture's pixels.
    fn band(&self, px: u32) -> u32 {
        (f64::from(px) * self.scale()).round() as u32
    }

    /// The moment `upto` of the race as an animation shows it, trailing [`TRAIL_S`] of path.
    fn at(&self, upto: usize) -> Self {
        Self {
            upto,
            trail_s: Some(TRAIL_S),
            ..self.clone()
        }
    }

    /// Draws the picture into `rgb`, [`Figure::size`]'s pixels of three bytes.
    fn draw_rgb(&self, rgb: &mut [u8]) -> Result<()> {
        let root = BitMapBackend::with_buffer(rgb, self.size()).into_drawing_area();
        self.draw(&root)?;
        root.present().map_err(plot_err)
    }

    /// The title, with the moment's time in an animation.
    fn title_text(&self) -> String {
        match self.trail_s {
            Some(_) => format!("{} · t = {:.1} s", self.title, self.frames[self.upto].time),
            None => self.title.to_string(),
        }
    }
}

impl Figure for RaceScene<'_> {
    fn size(&self) -> (u32, u32) {
        let (w, h) = track_picture_size(self.track);
        let track_h = (f64::from(h) * f64::from(self.width) / f64::from(w)).round() as u32;
        (
            self.width,
            track_h + self.band(TITLE_PX) + self.band(LEGEND_PX),
        )
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        register_font()?;
        root.fill(&WHITE).map_err(plot_err)?;
        let (_, h) = root.dim_in_pixel();
        let (title, rest) = root.split_vertically(self.band(TITLE_PX));
        let (body, legend) = rest.split_vertically(h - self.band(TITLE_PX) - self.band(LEGEND_PX));
        let text_px = (20.0 * self.scale()).max(14.0);
        title
            .draw(&Text::new(
                self.title_text(),
                (self.band(10) as i32, self.band(10) as i32),
                ("sans-serif", text_px).into_font().color(&BLACK),
            ))
            .map_err(plot_err)?;
        let (lo, hi) = bounds(self.track);
        let mut chart = ChartBuilder::on(&body)
            .margin(self.band(10))
            .build_cartesian_2d(lo.0..hi.0, lo.1..hi.1)
            .map_err(plot_err)?;
        draw_track(&mut chart, self.track)?;
        self.draw_cars(&mut chart)?;
        self.draw_legend(&legend, text_px * 0.85)
    }
}

impl RaceScene<'_> {
    /// Draws every car's path up to `upto` (its last `trail_s`, if set) coloured by speed, and
    /// its footprint at `upto`.
    fn draw_cars<DB: DrawingBackend>(&self, chart: &mut TrackChart<DB>) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        let now = &self.frames[self.upto];
        let from = match self.trail_s {
            Some(s) => self.frames[..self.upto].partition_point(|f| f.time < now.time - s),
            None => 0,
        };
        let shown = &self.frames[from..=self.upto];
        let line = |px: f64| ((px * self.scale()).round() as u32).max(1);
        for car in (0..now.cars.len()).rev() {
            let width = if car == 0 { line(4.0) } else { line(2.5) };
            let segments = shown.windows(2).map(|w| {
                let (a, b) = (&w[0].cars[car].state, &w[1].cars[car].state);
                let colour =
                    ViridisRGB::get_color_normalized(b[idx::V] as f32, 0.0, self.v_max as f32);
                PathElement::new(
                    vec![(a[idx::X], a[idx::Y]), (b[idx::X], b[idx::Y])],
                    colour.stroke_width(width),
                )
            });
            chart.draw_series(segments).map_err(plot_err)?;
            let snap = &now.cars[car];
            let colour = if car == 0 { EGO } else { RIVAL };
            let style = if snap.crashed || self.trail_s.is_some() {
                colour.filled()
            } else {
                colour.stroke_width(line(2.0))
            };
            chart
                .draw_series(std::iter::once(Polygon::new(footprint(&snap.state), style)))
                .map_err(plot_err)?;
            if self.trail_s.is_some() {
                // a car is a few pixels long: a ring in its colour (black once crashed) shows
                // where it is
                let ring = if snap.crashed { BLACK } else { colour };
                chart
                    .draw_series(std::iter::once(Circle::new(
                        (snap.state[idx::X], snap.state[idx::Y]),
                        line(14.0),
                        ring.stroke_width(line(3.0)),
                    )))
                    .map_err(plot_err)?;
            }
        }
        Ok(())
    }

    /// Draws the legend band: the ego's and the rivals' footprints, a crashed car, the
    /// raceline, and the speed colour bar.
    fn draw_legend<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        text_px: f64,
    ) -> Result<()>
    where
        DB::ErrorType: 'static,
    {
        let s = self.scale();
        let px = |v: f64| (v * s).round() as i32;
        let font = ("sans-serif", text_px).into_font().color(&BLACK);
        let mid = px(22.0);
        let swatch = |x: i32| [(x, mid - px(7.0)), (x + px(26.0), mid + px(7.0))];
        let mut x = px(10.0);
        let label = |area: &DrawingArea<DB, Shift>, x: &mut i32, text: &str| -> Result<()> {
            area.draw(&Text::new(
                text.to_string(),
                (*x + px(32.0), mid - (text_px / 2.0) as i32),
                font.clone(),
            ))
            .map_err(plot_err)?;
            let (w, _) = area.estimate_text_size(text, &font).map_err(plot_err)?;
            *x += px(32.0) + w as i32 + px(24.0);
            Ok(())
        };
        // a still draws running cars outlined and crashed ones filled; an animation draws
        // them filled in a ring of their colour, black once crashed
        let animated = self.trail_s.is_some();
        let car = |c: RGBColor| {
            if animated {
                c.filled()
            } else {
                c.stroke_width(2)
            }
        };
        area.draw(&Rectangle::new(swatch(x), car(EGO)))
            .map_err(plot_err)?;
        label(area, &mut x, "ego")?;
        area.draw(&Rectangle::new(swatch(x), car(RIVAL)))
            .map_err(plot_err)?;
        label(area, &mut x, "rivals")?;
        let grey = RGBColor(136, 136, 136);
        area.draw(&Rectangle::new(swatch(x), grey.filled()))
            .map_err(plot_err)?;
        if animated {
            area.draw(&Circle::new(
                (x + px(13.0), mid),
                px(9.0),
                BLACK.stroke_width(px(3.0).max(1) as u32),
            ))
            .map_err(plot_err)?;
        }
        label(
            area,
            &mut x,
            if animated {
                "crashed (black ring)"
            } else {
                "crashed (filled)"
            },
        )?;
        area.draw(&PathElement::new(
            vec![(x, mid), (x + px(26.0), mid)],
            RACELINE.stroke_width(3),
        ))
        .map_err(plot_err)?;
        label(area, &mut x, "raceline")?;
        // the colour bar: trail colour = speed
        let caption = "trail colour = speed: 0";
        area.draw(&Text::new(
            caption,
            (x, mid - (text_px / 2.0) as i32),
            font.clone(),
        ))
        .map_err(plot_err)?;
        let (w, _) = area.estimate_text_size(caption, &font).map_err(plot_err)?;
        let bar_x = x + w as i32 + px(8.0);
        let bar_w = px(200.0).max(40);
        let steps = 40;
        for k in 0..steps {
            let colour = ViridisRGB::get_color_normalized(k as f32, 0.0, (steps - 1) as f32);
            let x0 = bar_x + bar_w * k / steps;
            let x1 = bar_x + bar_w * (k + 1) / steps;
            area.draw(&Rectangle::new(
                [(x0, mid - px(7.0)), (x1, mid + px(7.0))],
                colour.filled(),
            ))
            .map_err(plot_err)?;
        }
        area.draw(&Text::new(
            format!("{:.1} m/s", self.v_max),
            (bar_x + bar_w + px(8.0), mid - (text_px / 2.0) as i32),
            font,
        ))
        .map_err(plot_err)?;
        Ok(())
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
    chart
        .draw_series(std::iter::once(PathElement::new(
            closed(track.centreline.curve.points()),
            CENTRELINE.stroke_width(1),
        )))
        .map_err(plot_err)?;
    chart
        .draw_series(std::iter::once(PathElement::new(
            closed(track.raceline.curve.points()),
            RACELINE.stroke_width(2),
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

/// The animation's fixed colours: greys from black to white, the cars' and the raceline's
/// colours with their paler tints (the edges of filled shapes), and viridis steps; every
/// pixel takes the nearest. One more index marks a pixel unchanged since the last frame.
struct Palette {
    colours: Vec<[u8; 3]>,
    /// Nearest colour per 5-bit-per-channel RGB cell.
    nearest: Vec<u8>,
}

impl Palette {
    fn new() -> Self {
        let mut colours: Vec<[u8; 3]> = (0..16u8).map(|k| [k * 17; 3]).collect();
        for RGBColor(r, g, b) in [EGO, RIVAL, RACELINE] {
            for keep in [1.0, 0.6, 0.3] {
                let tint = |c: u8| (f64::from(c) * keep + 255.0 * (1.0 - keep)).round() as u8;
                colours.push([tint(r), tint(g), tint(b)]);
            }
        }
        colours.extend((0..32).map(|k| {
            let RGBColor(r, g, b) = ViridisRGB::get_color_normalized(k as f32, 0.0, 31.0);
            [r, g, b]
        }));
        let cell = |v: usize| ((v << 3) + 4) as i32;
        let nearest = (0..1 << 15)
            .map(|i| {
                let rgb = [cell(i >> 10), cell((i >> 5) & 31), cell(i & 31)];
                let dist = |c: &[u8; 3]| -> i32 {
                    (0..3).map(|k| (i32::from(c[k]) - rgb[k]).pow(2)).sum()
                };
                (0..colours.len())
                    .min_by_key(|&k| dist(&colours[k]))
                    .unwrap_or(0) as u8
            })
            .collect();
        Self { colours, nearest }
    }

    /// The index that marks an unchanged pixel.
    fn unchanged(&self) -> u8 {
        self.colours.len() as u8
    }

    /// The palette as the GIF's global colour table (with the unchanged index's entry).
    fn table(&self) -> Vec<u8> {
        self.colours
            .iter()
            .flatten()
            .copied()
            .chain([255, 0, 255])
            .collect()
    }

    /// Palette indices of an RGB picture.
    fn indices(&self, rgb: &[u8]) -> Vec<u8> {
        rgb.chunks_exact(3)
            .map(|p| {
                let cell = (usize::from(p[0] >> 3) << 10)
                    | (usize::from(p[1] >> 3) << 5)
                    | usize::from(p[2] >> 3);
                self.nearest[cell]
            })
            .collect()
    }
}

/// The frames an animation shows: one per 1/[`GIF_FPS`] s of race time, and the last.
fn animation_moments(frames: &[Frame]) -> Vec<usize> {
    let mut moments = Vec::new();
    let mut next = f64::NEG_INFINITY;
    for (i, f) in frames.iter().enumerate() {
        if f.time >= next {
            moments.push(i);
            next = f.time + 1.0 / GIF_FPS - 1e-9;
        }
    }
    if moments.last() != Some(&(frames.len() - 1)) {
        moments.push(frames.len() - 1);
    }
    moments
}

/// Writes `whole`'s race as a looping GIF: one picture per [`animation_moments`], each
/// stored as the rectangle that changed since the previous one.
fn write_gif(path: &Path, whole: &RaceScene) -> Result<()> {
    ctxrace_run::run_dir::write_atomic_with(path, |_, file| gif_into(file, path, whole))
}

/// Encodes `whole`'s race as a GIF into `file` (`path` names it in errors).
fn gif_into(file: &mut std::fs::File, path: &Path, whole: &RaceScene) -> Result<()> {
    let (w, h) = whole.size();
    let too_big = |_| {
        RenderError::Refused(format!(
            "{} would be {w} x {h} pixels, over GIF's 65535",
            path.display()
        ))
    };
    let (w16, h16) = (
        u16::try_from(w).map_err(too_big)?,
        u16::try_from(h).map_err(too_big)?,
    );
    let palette = Palette::new();
    let mut encoder = gif::Encoder::new(std::io::BufWriter::new(file), w16, h16, &palette.table())
        .map_err(|e| RenderError::write(path, e))?;
    encoder
        .set_repeat(gif::Repeat::Infinite)
        .map_err(|e| RenderError::write(path, e))?;
    let moments = animation_moments(whole.frames);
    let mut rgb = vec![0u8; w as usize * h as usize * 3];
    let mut previous: Option<Vec<u8>> = None;
    for (k, &upto) in moments.iter().enumerate() {
        whole.at(upto).draw_rgb(&mut rgb)?;
        let picture = palette.indices(&rgb);
        // shown until the next moment: the race plays in real time
        let seconds = match moments.get(k + 1) {
            Some(&next) => whole.frames[next].time - whole.frames[upto].time,
            None => GIF_HOLD_S,
        };
        let mut frame = changed_part(previous.as_deref(), &picture, w16, palette.unchanged());
        frame.delay = centiseconds(seconds);
        encoder
            .write_frame(&frame)
            .map_err(|e| RenderError::write(path, e))?;
        previous = Some(picture);
    }
    Ok(())
}

/// A GIF frame delay: `seconds` in hundredths, at least one.
fn centiseconds(seconds: f64) -> u16 {
    (seconds * 100.0).round().clamp(1.0, f64::from(u16::MAX)) as u16
}

/// The GIF frame that turns `previous` into `picture` (both palette indices, `width` wide):
/// the bounding rectangle of the changed pixels, the unchanged ones in it marked `unchanged`
/// (transparent); the whole picture when there is no previous one.
fn changed_part(
    previous: Option<&[u8]>,
    picture: &[u8],
    width: u16,
    unchanged: u8,
) -> gif::Frame<'static> {
    let w = usize::from(width);
    let h = picture.len() / w;
    let Some(previous) = previous else {
        return gif::Frame {
            width,
            height: h as u16,
            buffer: picture.to_vec().into(),
            ..gif::Frame::default()
        };
    };
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for (i, (a, b)) in previous.iter().zip(picture).enumerate() {
        if a != b {
            let (x, y) = (i % w, i / w);
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
    }
    if x0 > x1 {
        // nothing changed: one transparent pixel
        (x0, y0, x1, y1) = (0, 0, 0, 0);
    }
    let mut buffer = Vec::with_capacity((x1 - x0 + 1) * (y1 - y0 + 1));
    for y in y0..=y1 {
        for i in y * w + x0..=y * w + x1 {
            buffer.push(if previous[i] == picture[i] {
                unchanged
            } else {
                picture[i]
            });
        }
    }
    gif::Frame {
        left: x0 as u16,
        top: y0 as u16,
        width: (x1 - x0 + 1) as u16,
        height: (y1 - y0 + 1) as u16,
        transparent: Some(unchanged),
        dispose: gif::DisposalMethod::Keep,
        buffer: buffer.into(),
        ..gif::Frame::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_config::{Context, RaceConfig};
    use ctxrace_sim::baseline::BaselineKind;
    use ctxrace_sim::driver::BaselineEgo;
    use ctxrace_tracks::TrackOptions;
    use std::sync::Arc;

    /// A pure-pursuit race against two rivals on a generated track: the track, the frames and
    /// the race's title.
    fn race(context: Context) -> (Arc<Track>, Vec<Frame>, String) {
        let track = Arc::new(Track::load("generated:3", &TrackOptions::default()).unwrap());
        let cfg = RaceConfig {
            rivals: 2,
            ..RaceConfig::default()
        };
        let mut env = RaceEnv::new(track.clone(), cfg).unwrap();
        let mut ego = BaselineEgo::new(BaselineKind::PurePursuit, &env);
        let mut frames = Vec::new();
        drive_recorded(&mut ego, &mut env, context, 0, &mut frames).unwrap();
        let title = race_title(&track.name, BaselineKind::PurePursuit.name(), &env);
        (track, frames, title)
    }

    #[test]
    fn a_still_names_the_cars_the_trail_colours_the_context_and_the_outcome() {
        let (track, frames, title) = race(Context {
            speed: 0.1,
            steer: -0.2,
        });
        assert!(title.contains("ego pure-pursuit vs 2 rival(s)"), "{title}");
        assert!(title.contains("c_v +0.10, c_t -0.20"), "{title}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("race.svg");
        render_race(&path, &track, &frames, &title).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        let v_max = RaceScene::new(&track, &frames, &title, WIDTH_PX).v_max;
        // each text element's content stands on a line of its own
        for text in [
            title.as_str(),
            "ego",
            "rivals",
            "crashed (filled)",
            "raceline",
            "trail colour = speed: 0",
            &format!("{v_max:.1} m/s"),
        ] {
            assert!(svg.lines().any(|l| l == text), "the picture lacks {text:?}");
        }
    }

    #[test]
    fn an_animation_replays_each_moment_storing_only_what_changed() {
        let (track, frames, title) = race(Context::default());
        let frames = &frames[..frames.len().min(40)];
        let scene = RaceScene::new(&track, frames, &title, 300);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("race.gif");
        write_gif(&path, &scene).unwrap();

        let moments = animation_moments(frames);
        let step = 1.0 / GIF_FPS;
        for w in moments.windows(2) {
            let (a, b) = (frames[w[0]].time, frames[w[1]].time);
            assert!(b - a >= step - 1e-6 || w[1] == frames.len() - 1);
        }
        let duration = frames.last().unwrap().time;
        assert!(moments.len() as f64 <= duration * GIF_FPS + 2.0);

        let (w, h) = scene.size();
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::Indexed);
        let mut decoder = options
            .read_info(std::fs::File::open(&path).unwrap())
            .unwrap();
        assert_eq!((decoder.width(), decoder.height()), (w as u16, h as u16));
        let palette = Palette::new();
        let mut canvas = vec![0u8; (w * h) as usize];
        let mut rgb = vec![0u8; canvas.len() * 3];
        let (mut shown, mut stored, mut delay) = (0, 0, 0u32);
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            let upto = moments[shown];
            for y in 0..usize::from(frame.height) {
                for x in 0..usize::from(frame.width) {
                    let v = frame.buffer[y * usize::from(frame.width) + x];
                    if Some(v) != frame.transparent {
                        let at =
                            (usize::from(frame.top) + y) * w as usize + usize::from(frame.left) + x;
                        canvas[at] = v;
                    }
                }
            }
            stored += usize::from(frame.width) * usize::from(frame.height);
            delay += u32::from(frame.delay);
            scene.at(upto).draw_rgb(&mut rgb).unwrap();
            assert!(canvas == palette.indices(&rgb), "frame {shown} differs");
            shown += 1;
        }
        assert_eq!(shown, moments.len());
        // played in real time, to the rounding of each delay to 1/100 s
        let played = f64::from(delay) / 100.0 - GIF_HOLD_S;
        assert!((played - duration).abs() <= 0.005 * moments.len() as f64);
        // after the first picture only the cars' and the clock's rectangles are stored
        let whole = (w * h) as usize;
        assert!(
            stored < whole + (shown - 1) * whole / 4,
            "{stored} pixels stored for {shown} pictures of {whole}"
        );
    }

    /// Where the pixels of exactly `colour` lie on average in `picture`, and how many there are.
    fn centroid(picture: &RgbPicture, colour: RGBColor) -> ((f64, f64), usize) {
        let RGBColor(r, g, b) = colour;
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0);
        for (i, p) in picture.rgb.chunks_exact(3).enumerate() {
            if p == [r, g, b] {
                sx += (i % picture.width as usize) as f64;
                sy += (i / picture.width as usize) as f64;
                n += 1;
            }
        }
        ((sx / n as f64, sy / n as f64), n)
    }

    #[test]
    fn a_moment_is_the_animation_frame_of_the_race_so_far_and_follows_the_cars() {
        let (track, frames, title) = race(Context::default());
        let early = moment_rgb(&track, &frames[..5], &title, 400).unwrap();
        let later = moment_rgb(&track, &frames[..60], &title, 400).unwrap();
        let scene = RaceScene::new(&track, &frames[..60], &title, 400);
        assert_eq!((later.width, later.height), scene.size());
        assert_eq!(later.rgb.len(), (later.width * later.height * 3) as usize);
        let mut rgb = vec![0u8; later.rgb.len()];
        scene.at(59).draw_rgb(&mut rgb).unwrap();
        assert!(
            rgb == later.rgb,
            "the moment differs from the animation's frame"
        );
        // the ego (red, filled and ringed) has moved along the track
        let ((x0, y0), n0) = centroid(&early, EGO);
        let ((x1, y1), n1) = centroid(&later, EGO);
        assert!(n0 > 20 && n1 > 20, "{n0} and {n1} ego pixels");
        let moved = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
        assert!(
            moved > 5.0,
            "the ego moved {moved:.1} pixels in 55 decisions"
        );
        let mid_race = race_title(&track.name, "agent", &{
            let mut env = RaceEnv::new(track.clone(), RaceConfig::default()).unwrap();
            env.reset(0, Context::default());
            env
        });
        assert!(mid_race.contains("racing, progress 0.00"), "{mid_race}");
    }

    #[test]
    fn a_moment_needs_a_frame_and_a_hundred_pixels() {
        let (track, frames, title) = race(Context::default());
        let err = moment_rgb(&track, &[], &title, 400).unwrap_err();
        assert!(err.to_string().contains("no frames"), "{err}");
        let err = moment_rgb(&track, &frames, &title, 99).unwrap_err();
        assert!(err.to_string().contains("at least 100"), "{err}");
    }

    #[test]
    fn a_picture_of_another_kind_is_refused_before_the_race() {
        let err = check_render_path(Path::new("race.jpg")).unwrap_err();
        assert!(err.to_string().contains(".png or .svg (a still) or .gif"));
        check_render_path(Path::new("race.gif")).unwrap();
    }
}
