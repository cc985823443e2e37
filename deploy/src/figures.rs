//! The report's figures, each as PNG and SVG: per-context heatmaps of PG and A2A, training curves,
//! the rivals' speed profiles and race lines under different contexts (paper Figs. 3–4), and the
//! evaluation's episode pictures copied over.

use crate::groups::{sections, Group, Metric, Run};
use crate::paper::bootstrap_ci;
use crate::parity::ParityCurves;
use crate::TrackArgs;
use anyhow::{Context as _, Result};
use ctxrace_config::{Context, RaceConfig};
use ctxrace_render::figure::Result as DrawResult;
use ctxrace_render::figure::{plot_err, register_font, save_png_and_svg, Figure};
use ctxrace_render::race::{bounds, draw_track, track_picture_size, TrackChart};
use ctxrace_run::results::TrainingEpisode;
use ctxrace_sim::evaluation::A2A_PER_LAPS;
use ctxrace_sim::masks::{ContextMasks, PROGRESS_BINS};
use ctxrace_sim::rival::{drive_solo_lap, SoloLap};
use ctxrace_tracks::Track;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::{Path, PathBuf};

/// Writes every figure for `groups` into `out`; returns the files written. The rival figures of a
/// track that does not load are skipped with a warning.
pub fn write_all(
    groups: &[Group],
    out: &Path,
    tracks: &TrackArgs,
    cfg: &RaceConfig,
) -> Result<Vec<PathBuf>> {
    register_font()?;
    let mut files = Vec::new();
    for g in groups {
        let stem = format!("heatmap_{}", group_stem(g));
        files.extend(save_png_and_svg(&Heatmap { group: g }, out, &stem)?);
        if g.runs.iter().any(|r| r.masks.is_some()) {
            let stem = group_stem(g);
            let heatmap = MaskHeatmap { group: g };
            files.extend(save_png_and_svg(
                &heatmap,
                out,
                &format!("mask_heatmap_{stem}"),
            )?);
            let along = MaskAlongLap { group: g };
            files.extend(save_png_and_svg(
                &along,
                out,
                &format!("mask_along_{stem}"),
            )?);
        }
    }
    for section in sections(groups) {
        let trained: Vec<&Group> = section
            .iter()
            .filter(|g| g.runs.iter().any(|r| !r.training.is_empty()))
            .collect();
        if let Some(first) = trained.first() {
            let stem = format!("training_{}_{}r", slug(&first.track), first.rivals);
            let series = trained
                .iter()
                .map(|g| CurveSeries {
                    label: g.display_name(),
                    runs: g
                        .runs
                        .iter()
                        .filter(|r| !r.training.is_empty())
                        .map(|r| r.training.as_slice())
                        .collect(),
                })
                .collect();
            let curves = TrainingCurves {
                title: format!("Training on {}", first.section()),
                series,
                band: Band::MinMax,
                panels: &CURVE_PANELS,
            };
            files.extend(save_png_and_svg(&curves, out, &stem)?);
        }
    }
    let mut names: Vec<&str> = groups.iter().map(|g| g.track.as_str()).collect();
    names.dedup();
    for name in names {
        match tracks.load(name, cfg) {
            Ok(track) => {
                files.extend(rival_figures(&track, cfg, out)?);
                for g in groups.iter().filter(|g| g.track == name) {
                    if let Some(figure) = MaskOnTrack::of(g, &track) {
                        let stem = format!("mask_track_{}", group_stem(g));
                        files.extend(save_png_and_svg(&figure, out, &stem)?);
                    }
                }
            }
            Err(e) => tracing::warn!("skipping the rival figures of track '{name}': {e:#}"),
        }
    }
    for g in groups {
        for run in &g.runs {
            for ext in ["png", "svg"] {
                let src = run.dir.join(format!("episode.{ext}"));
                if src.is_file() {
                    let stem = group_stem(g);
                    let dst = out.join(format!("episode_{stem}_seed{}.{ext}", run.meta.train_seed));
                    std::fs::copy(&src, &dst).with_context(|| {
                        format!("copying {} to {}", src.display(), dst.display())
                    })?;
                    files.push(dst);
                }
            }
        }
    }
    Ok(files)
}

/// A name made safe for a file name: anything but letters, digits, `-` and `.` becomes `_`.
fn slug(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// `ALGO_TRACK_Nr`, the file stem of a group's figures.
fn group_stem(g: &Group) -> String {
    format!("{}_{}_{}r", slug(&g.algo), slug(&g.track), g.rivals)
}

/// A title font of `size` pixels.
fn font(size: u32) -> TextStyle<'static> {
    ("sans-serif", size).into_font().into()
}

/// Seed-averaged values per context of a group, from each run's `(c_v, c_θ, value)`:
/// `(c_v, c_θ, mean)`.
fn context_means(g: &Group, values: impl Fn(&Run) -> Vec<(f64, f64, f64)>) -> Vec<(f64, f64, f64)> {
    let mut cells: Vec<(f64, f64, Vec<f64>)> = Vec::new();
    for (cv, ct, v) in g.runs.iter().flat_map(values) {
        let same = |cell: &&mut (f64, f64, Vec<f64>)| {
            (cell.0 - cv).abs() < 1e-9 && (cell.1 - ct).abs() < 1e-9
        };
        match cells.iter_mut().find(same) {
            Some(cell) => cell.2.push(v),
            None => cells.push((cv, ct, vec![v])),
        }
    }
    cells
        .into_iter()
        .map(|(cv, ct, v)| (cv, ct, v.iter().sum::<f64>() / v.len() as f64))
        .collect()
}

/// Smallest spacing between distinct values, 0.1 when there is only one.
fn grid_step(values: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    v.windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 1e-9)
        .fold(None, |m: Option<f64>, d| Some(m.map_or(d, |m| m.min(d))))
        .unwrap_or(0.1)
}

/// The metrics of the heatmaps and the top of their colour scales.
const HEATMAP_METRICS: [(Metric, f64); 2] = [(Metric::Progress, 1.0), (Metric::A2a, A2A_PER_LAPS)];

/// Grids with at most this many values per axis get their cell values written in.
const MAX_LABELLED_GRID: usize = 9;

/// PG and A2A over the context grid of one group, with the training range outlined.
struct Heatmap<'a> {
    group: &'a Group,
}

impl Figure for Heatmap<'_> {
    fn size(&self) -> (u32, u32) {
        (1300, 620)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        let g = self.group;
        root.fill(&WHITE).map_err(plot_err)?;
        let title = format!(
            "{} on {} ({} seed(s); red box: training range)",
            g.display_name(),
            g.section(),
            g.runs.len()
        );
        let root = root.titled(&title, font(26)).map_err(plot_err)?;
        let train_range = g.runs.first().map_or(0.0, |r| r.meta.train_range);
        let panels = root.split_evenly((1, HEATMAP_METRICS.len()));
        for (area, (metric, top)) in panels.iter().zip(HEATMAP_METRICS) {
            let caption = format!("{} per context {}", metric.label(), arrow_note(metric));
            let decimals = if metric == Metric::A2a { 1 } else { 2 };
            let cells = context_means(g, |r| {
                r.contexts
                    .iter()
                    .map(|c| (c.context_speed, c.context_steer, metric.of(c)))
                    .collect()
            });
            heatmap_panel(area, &cells, &caption, decimals, top, train_range)?;
        }
        Ok(())
    }
}

/// One heatmap with its colour bar on the right: `cells` `(c_v, c_θ, value)` on a `[0, top]`
/// scale, values written in with `decimals` places on grids of at most [`MAX_LABELLED_GRID`]
/// values per axis.
fn heatmap_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    cells: &[(f64, f64, f64)],
    caption: &str,
    decimals: usize,
    top: f64,
    train_range: f64,
) -> DrawResult<()>
where
    DB::ErrorType: 'static,
{
    let (plot, bar) = area.split_horizontally(area.dim_in_pixel().0.saturating_sub(110));
    let half = grid_step(cells.iter().flat_map(|c| [c.0, c.1])) / 2.0;
    let extent = cells
        .iter()
        .flat_map(|c| [c.0.abs(), c.1.abs()])
        .fold(train_range, f64::max)
        + half;
    let mut chart = ChartBuilder::on(&plot)
        .caption(caption, font(22))
        .margin(10)
        .x_label_area_size(50)
        .y_label_area_size(70)
        .build_cartesian_2d(-extent..extent, -extent..extent)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("c_θ (rival steering)")
        .y_desc("c_v (rival speed)")
        .x_label_formatter(&context_label)
        .y_label_formatter(&context_label)
        .label_style(font(15))
        .axis_desc_style(font(17))
        .draw()
        .map_err(plot_err)?;
    let colour =
        |v: f64| ViridisRGB::get_color_normalized(v.clamp(0.0, top) as f32, 0.0, top as f32);
    chart
        .draw_series(cells.iter().map(|&(cv, ct, v)| {
            Rectangle::new(
                [(ct - half, cv - half), (ct + half, cv + half)],
                colour(v).filled(),
            )
        }))
        .map_err(plot_err)?;
    let mut columns: Vec<f64> = cells.iter().map(|c| c.1).collect();
    columns.sort_by(f64::total_cmp);
    columns.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    if columns.len() <= MAX_LABELLED_GRID {
        chart
            .draw_series(cells.iter().map(|&(cv, ct, v)| {
                let ink = if v / top < 0.5 { &WHITE } else { &BLACK };
                let style = font(13)
                    .color(ink)
                    .pos(Pos::new(HPos::Center, VPos::Center));
                Text::new(format!("{v:.decimals$}"), (ct, cv), style)
            }))
            .map_err(plot_err)?;
    }
    let r = train_range;
    chart
        .draw_series(std::iter::once(PathElement::new(
            vec![(-r, -r), (r, -r), (r, r), (-r, r), (-r, -r)],
            RED.stroke_width(3),
        )))
        .map_err(plot_err)?;

    let mut scale = ChartBuilder::on(&bar)
        .margin_top(50)
        .margin_bottom(60)
        .margin_right(10)
        .set_label_area_size(LabelAreaPosition::Right, 55)
        .build_cartesian_2d(0.0..1.0, 0.0..top)
        .map_err(plot_err)?;
    scale
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .label_style(font(14))
        .draw()
        .map_err(plot_err)?;
    let slices = 100;
    scale
        .draw_series((0..slices).map(|i| {
            let (a, b) = (
                i as f64 / slices as f64 * top,
                (i + 1) as f64 / slices as f64 * top,
            );
            Rectangle::new([(0.0, a), (1.0, b)], colour((a + b) / 2.0).filled())
        }))
        .map_err(plot_err)?;
    Ok(())
}

/// The mask components: their index in a mask and name.
const MASK_COMPONENTS: [(usize, &str); 2] = [(0, "c_v (rival speed)"), (1, "c_θ (rival steering)")];

/// The mean of each cMask mask component over the context grid of one group (seeds averaged),
/// with the training range outlined.
struct MaskHeatmap<'a> {
    group: &'a Group,
}

impl Figure for MaskHeatmap<'_> {
    fn size(&self) -> (u32, u32) {
        (1300, 620)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        let g = self.group;
        root.fill(&WHITE).map_err(plot_err)?;
        let seeds = g.runs.iter().filter(|r| r.masks.is_some()).count();
        let title = format!(
            "{} on {}: mean context mask per context over every decision ({seeds} seed(s); red box: training range)",
            g.display_name(),
            g.section(),
        );
        let root = root.titled(&title, font(22)).map_err(plot_err)?;
        let train_range = g.runs.first().map_or(0.0, |r| r.meta.train_range);
        let panels = root.split_evenly((1, MASK_COMPONENTS.len()));
        for (area, (k, name)) in panels.iter().zip(MASK_COMPONENTS) {
            let cells = context_means(g, |r| {
                r.masks
                    .iter()
                    .flat_map(|m| &m.contexts)
                    .map(|c| (c.context_speed, c.context_steer, c.mean(k)))
                    .collect()
            });
            let caption = format!("mask on {name}");
            heatmap_panel(area, &cells, &caption, 2, 1.0, train_range)?;
        }
        Ok(())
    }
}

/// How many contexts the mask-along-the-lap figure shows.
const ALONG_CONTEXTS: usize = 3;

/// The contexts of a group's masks nearest the grid's low corner, centre and high corner
/// (`(−r, −r)`, `(0, 0)`, `(r, r)`), each with its decisions summed over the seeds.
fn along_contexts(g: &Group) -> Vec<ContextMasks> {
    let all: Vec<&ContextMasks> = g
        .runs
        .iter()
        .flat_map(|r| r.masks.iter())
        .flat_map(|m| &m.contexts)
        .collect();
    let r = all
        .iter()
        .map(|c| c.context_speed.abs().max(c.context_steer.abs()))
        .fold(0.0, f64::max);
    let mut chosen: Vec<ContextMasks> = Vec::new();
    for target in [-r, 0.0, r] {
        let distance =
            |c: &ContextMasks| (c.context_speed - target).hypot(c.context_steer - target);
        let Some(nearest) = all
            .iter()
            .min_by(|a, b| distance(a).total_cmp(&distance(b)))
        else {
            continue;
        };
        if chosen.iter().any(|c| c.context() == nearest.context()) {
            continue;
        }
        let mut sum = ContextMasks {
            context_speed: nearest.context_speed,
            context_steer: nearest.context_steer,
            along: vec![([0.0; 2], 0); PROGRESS_BINS],
            ..ContextMasks::default()
        };
        for c in all.iter().filter(|c| c.context() == nearest.context()) {
            sum.count += c.count;
            for (total, (m, n)) in sum.along.iter_mut().zip(&c.along) {
                total.0[0] += m[0];
                total.0[1] += m[1];
                total.1 += n;
            }
        }
        chosen.push(sum);
    }
    chosen.truncate(ALONG_CONTEXTS);
    chosen
}

/// Each mask component along the lap (mean per bin of lap progress over every lap and seed)
/// for a few contexts of one group, as the paper's `plot_masks.py` draws one lap's.
struct MaskAlongLap<'a> {
    group: &'a Group,
}

impl Figure for MaskAlongLap<'_> {
    fn size(&self) -> (u32, u32) {
        (1400, 560)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        let g = self.group;
        root.fill(&WHITE).map_err(plot_err)?;
        let title = format!(
            "{} on {}: context mask along the lap (mean over laps and seeds)",
            g.display_name(),
            g.section()
        );
        let root = root.titled(&title, font(24)).map_err(plot_err)?;
        let contexts = along_contexts(g);
        let panels = root.split_evenly((1, MASK_COMPONENTS.len()));
        for (area, (k, name)) in panels.iter().zip(MASK_COMPONENTS) {
            let mut chart = ChartBuilder::on(area)
                .caption(format!("mask on {name}"), font(20))
                .margin(15)
                .x_label_area_size(50)
                .y_label_area_size(60)
                .build_cartesian_2d(0.0..1.0, 0.0..1.0)
                .map_err(plot_err)?;
            chart
                .configure_mesh()
                .x_desc("lap progress")
                .y_desc("mask")
                .label_style(font(14))
                .axis_desc_style(font(16))
                .draw()
                .map_err(plot_err)?;
            for (i, c) in contexts.iter().enumerate() {
                let colour = Palette99::pick(i).to_rgba();
                let points = c
                    .along
                    .iter()
                    .enumerate()
                    .filter(|(_, (_, n))| *n > 0)
                    .map(|(b, (m, n))| ((b as f64 + 0.5) / PROGRESS_BINS as f64, m[k] / *n as f64));
                chart
                    .draw_series(LineSeries::new(points, colour.stroke_width(2)))
                    .map_err(plot_err)?
                    .label(format!(
                        "c_v = {:+.2}, c_θ = {:+.2} ({} decisions)",
                        c.context_speed, c.context_steer, c.count
                    ))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                    });
            }
            legend(&mut chart, SeriesLabelPosition::LowerRight)?;
        }
        Ok(())
    }
}

/// Each mask component as the colour of the path of one lap on the track (as the paper's
/// `plot_masks_map.py`): the longest lap in the context nearest `(0, 0)` of the group's first
/// seed with masks.
struct MaskOnTrack<'a> {
    group: &'a Group,
    track: &'a Track,
    seed: u64,
    lap: &'a ContextMasks,
}

impl<'a> MaskOnTrack<'a> {
    /// The figure of `g` on `track`, if it has masks.
    fn of(g: &'a Group, track: &'a Track) -> Option<Self> {
        let run = g.runs.iter().find(|r| r.masks.is_some())?;
        let centre = |c: &&ContextMasks| c.context_speed.hypot(c.context_steer);
        let lap = run
            .masks
            .as_ref()?
            .contexts
            .iter()
            .min_by(|a, b| centre(a).total_cmp(&centre(b)))?;
        Some(Self {
            group: g,
            track,
            seed: run.meta.train_seed,
            lap,
        })
    }
}

impl Figure for MaskOnTrack<'_> {
    fn size(&self) -> (u32, u32) {
        let (w, h) = track_picture_size(self.track);
        (w, 2 * h + 60)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(plot_err)?;
        let c = self.lap;
        let title = format!(
            "{} on {}: context mask along its longest lap at c_v = {:+.2}, c_θ = {:+.2} \
             (seed {}, {} decisions)",
            self.group.display_name(),
            self.group.section(),
            c.context_speed,
            c.context_steer,
            self.seed,
            c.longest_lap.len()
        );
        let root = root.titled(&title, font(24)).map_err(plot_err)?;
        let (lo, hi) = bounds(self.track);
        for (area, (k, name)) in root.split_evenly((2, 1)).iter().zip(MASK_COMPONENTS) {
            let mut chart = ChartBuilder::on(area)
                .caption(
                    format!("mask on {name}: colour 0 (dark blue) to 1 (yellow)"),
                    font(20),
                )
                .margin(10)
                .build_cartesian_2d(lo.0..hi.0, lo.1..hi.1)
                .map_err(plot_err)?;
            draw_track(&mut chart, self.track)?;
            chart
                .draw_series(c.longest_lap.windows(2).map(|w| {
                    let colour = ViridisRGB::get_color_normalized(w[0].2[k] as f32, 0.0, 1.0);
                    PathElement::new(
                        vec![(w[0].0, w[0].1), (w[1].0, w[1].1)],
                        colour.stroke_width(5),
                    )
                }))
                .map_err(plot_err)?;
        }
        Ok(())
    }
}

/// A context value on an axis, one decimal, without a sign on 0.
fn context_label(v: &f64) -> String {
    format!("{:.1}", (v * 10.0).round() / 10.0 + 0.0)
}

/// "(higher is better)" or "(lower is better)".
fn arrow_note(metric: Metric) -> &'static str {
    if metric.higher_is_better() {
        "(higher is better)"
    } else {
        "(lower is better)"
    }
}

/// Bins of environment steps the report's training curves are averaged over.
const CURVE_BINS: usize = 40;

/// A training curve point: bin centre (env steps), mean over seeds, and the band's low and
/// high ends.
pub type CurvePoint = (f64, f64, f64, f64);

/// The band drawn around a training curve's mean over seeds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Band {
    /// The seeds' smallest and largest value.
    MinMax,
    /// The 95% bootstrap interval of the mean over the seeds ([`bootstrap_ci`]).
    Bootstrap95,
}

impl Band {
    /// The band's ends for per-seed `values` (not empty).
    fn ends(self, values: &[f64]) -> (f64, f64) {
        match self {
            Band::MinMax => (
                values.iter().copied().fold(f64::INFINITY, f64::min),
                values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ),
            // no interval from no values: the band is then empty, as min-max's
            Band::Bootstrap95 => bootstrap_ci(values).unwrap_or_else(|| Band::MinMax.ends(values)),
        }
    }

    /// How a title names it.
    fn label(self) -> &'static str {
        match self {
            Band::MinMax => "band min–max",
            Band::Bootstrap95 => "band 95% bootstrap interval over seeds",
        }
    }
}

/// Per-bin means of `value` for each seed's episodes in `runs` over `bins` bins of `width`
/// environment steps (the last takes every later episode), then their mean and `band` over the
/// seeds that have episodes in the bin; bins without any are left out.
pub fn binned_curve(
    runs: &[&[TrainingEpisode]],
    value: fn(&TrainingEpisode) -> f64,
    (bins, width): (usize, f64),
    band: Band,
) -> Vec<CurvePoint> {
    let bin = |e: &TrainingEpisode| ((e.env_steps as f64 / width) as usize).min(bins - 1);
    let per_run: Vec<Vec<Option<f64>>> = runs
        .iter()
        .map(|episodes| {
            let mut sums = vec![(0.0, 0usize); bins];
            for e in episodes.iter() {
                let s = &mut sums[bin(e)];
                *s = (s.0 + value(e), s.1 + 1);
            }
            sums.into_iter()
                .map(|(sum, n)| (n > 0).then(|| sum / n as f64))
                .collect()
        })
        .collect();
    (0..bins)
        .filter_map(|b| {
            let v: Vec<f64> = per_run.iter().filter_map(|r| r[b]).collect();
            (!v.is_empty()).then(|| {
                let mean = v.iter().sum::<f64>() / v.len() as f64;
                let (lo, hi) = band.ends(&v);
                ((b as f64 + 0.5) * width, mean, lo, hi)
            })
        })
        .collect()
}

/// A training-curve panel: its title and the value it plots.
pub type CurvePanel = (&'static str, fn(&TrainingEpisode) -> f64);

/// The panels of the training curves.
pub const CURVE_PANELS: [CurvePanel; 2] = [
    ("track progress (PG)", |e| e.progress),
    ("episode return", |e| e.episode_return),
];

/// The panels of the parity figure: the training curves and the episodes ending in a collision.
const PARITY_PANELS: [CurvePanel; 3] = [
    CURVE_PANELS[0],
    CURVE_PANELS[1],
    ("episodes ending in a collision", |e| {
        f64::from(u8::from(e.a2a || e.wall_crash))
    }),
];

/// One curve of a training figure: its legend label and each seed's episodes.
pub struct CurveSeries<'a> {
    /// The legend label (the seeds are counted after it).
    pub label: String,
    /// The episodes of each seed (none empty).
    pub runs: Vec<&'a [TrainingEpisode]>,
}

/// Panels of training curves against environment steps: each series' mean over seeds with a
/// band (the report's, one series per algorithm of a section; the parity figure's, one per
/// side; and the one run's `learning_curve.png` that `ctxrace train` draws).
pub struct TrainingCurves<'a> {
    /// The picture's title (the band's kind is added to it).
    pub title: String,
    /// The lines.
    pub series: Vec<CurveSeries<'a>>,
    /// The band around each line.
    pub band: Band,
    /// What each panel plots.
    pub panels: &'static [CurvePanel],
}

impl Figure for TrainingCurves<'_> {
    fn size(&self) -> (u32, u32) {
        (700 * self.panels.len() as u32, 560)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(plot_err)?;
        let title = format!("{}: mean over seeds, {}", self.title, self.band.label());
        let root = root.titled(&title, font(26)).map_err(plot_err)?;
        let max_steps = self
            .series
            .iter()
            .flat_map(|s| &s.runs)
            .flat_map(|r| r.iter())
            .map(|e| e.env_steps)
            .max()
            .unwrap_or(0)
            .max(1) as f64;
        let width = max_steps / CURVE_BINS as f64;
        let panels = root.split_evenly((1, self.panels.len()));
        for (area, &(name, value)) in panels.iter().zip(self.panels) {
            let curves: Vec<Vec<CurvePoint>> = self
                .series
                .iter()
                .map(|s| binned_curve(&s.runs, value, (CURVE_BINS, width), self.band))
                .collect();
            let (lo, hi) = curves
                .iter()
                .flatten()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p.2), hi.max(p.3))
                });
            let pad = ((hi - lo) * 0.05).max(0.01);
            let mut chart = ChartBuilder::on(area)
                .caption(name, font(20))
                .margin(15)
                .x_label_area_size(50)
                .y_label_area_size(70)
                .build_cartesian_2d(0.0..max_steps, (lo - pad)..(hi + pad))
                .map_err(plot_err)?;
            chart
                .configure_mesh()
                .x_desc("environment steps")
                .x_label_formatter(&|v| format!("{v:.0}"))
                .y_desc(name)
                .label_style(font(14))
                .axis_desc_style(font(16))
                .draw()
                .map_err(plot_err)?;
            for (i, (series, curve)) in self.series.iter().zip(&curves).enumerate() {
                let colour = Palette99::pick(i).to_rgba();
                let band: Vec<(f64, f64)> = curve
                    .iter()
                    .map(|p| (p.0, p.3))
                    .chain(curve.iter().rev().map(|p| (p.0, p.2)))
                    .collect();
                chart
                    .draw_series(std::iter::once(Polygon::new(
                        band,
                        colour.mix(0.2).filled(),
                    )))
                    .map_err(plot_err)?;
                chart
                    .draw_series(LineSeries::new(
                        curve.iter().map(|p| (p.0, p.1)),
                        colour.stroke_width(2),
                    ))
                    .map_err(plot_err)?
                    .label(format!("{} ({} seed(s))", series.label, series.runs.len()))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                    });
            }
            legend(&mut chart, SeriesLabelPosition::LowerRight)?;
        }
        Ok(())
    }
}

/// Draws one figure per algorithm of a parity folder: each side's training curves (PG, return,
/// collisions) with the 95% bootstrap interval over its seeds; returns the files written.
pub fn write_parity(parity: &[ParityCurves], out: &Path) -> Result<Vec<PathBuf>> {
    register_font()?;
    let mut files = Vec::new();
    for algo in parity {
        let series = algo
            .sides
            .iter()
            .map(|(side, seeds)| CurveSeries {
                label: side.clone(),
                runs: seeds.iter().map(|(_, e)| e.as_slice()).collect(),
            })
            .collect();
        let figure = TrainingCurves {
            title: format!("{}: ctxrace and the paper's code", algo.algo),
            series,
            band: Band::Bootstrap95,
            panels: &PARITY_PANELS,
        };
        files.extend(save_png_and_svg(
            &figure,
            out,
            &format!("parity_{}", slug(&algo.algo)),
        )?);
    }
    Ok(files)
}

/// The context values of the rival figures (paper Figs. 3–4) and their colours: orange, green,
/// blue.
const PROFILE_CONTEXTS: [(f64, RGBColor); 3] = [
    (-0.3, RGBColor(240, 120, 30)),
    (0.0, RGBColor(40, 160, 60)),
    (0.3, RGBColor(30, 90, 210)),
];

/// The context dimension a rival figure varies (the other stays 0).
#[derive(Clone, Copy)]
enum Dimension {
    /// `c_v`.
    Speed,
    /// `c_θ`.
    Steer,
}

impl Dimension {
    /// The context with this dimension at `c`, the other at 0.
    fn context(self, c: f64) -> Context {
        match self {
            Dimension::Speed => Context {
                speed: c,
                steer: 0.0,
            },
            Dimension::Steer => Context {
                speed: 0.0,
                steer: c,
            },
        }
    }

    /// Its symbol.
    fn symbol(self) -> &'static str {
        match self {
            Dimension::Speed => "c_v",
            Dimension::Steer => "c_θ",
        }
    }
}

/// Solo laps of a rival under each of [`PROFILE_CONTEXTS`] in one context dimension.
struct RivalLaps {
    /// Track name.
    track: String,
    /// The dimension varied.
    dimension: Dimension,
    /// One lap per context value.
    laps: Vec<(f64, RGBColor, SoloLap)>,
}

impl RivalLaps {
    /// Drives the laps from the start line.
    fn drive(track: &Track, cfg: &RaceConfig, dimension: Dimension) -> Result<Self> {
        let laps = PROFILE_CONTEXTS
            .iter()
            .map(|&(c, colour)| {
                let lap = drive_solo_lap(track, cfg, dimension.context(c), 0.0)?;
                Ok((c, colour, lap))
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            track: track.name.clone(),
            dimension,
            laps,
        })
    }

    /// The legend entry of one lap, noting a wall hit.
    fn label(&self, c: f64, lap: &SoloLap) -> String {
        let mut s = format!("{} = {c:+.1}", self.dimension.symbol());
        if let Some(at) = lap.wall_hit_at {
            s += &format!(" (hit a wall at s = {at:.1} m)");
        }
        s
    }
}

/// Writes the rival speed-profile and race-line figures of `track`.
fn rival_figures(track: &Track, cfg: &RaceConfig, out: &Path) -> Result<Vec<PathBuf>> {
    let name = slug(&track.name);
    let speeds = SpeedProfiles(RivalLaps::drive(track, cfg, Dimension::Speed)?);
    let lines = RaceLines {
        track,
        laps: RivalLaps::drive(track, cfg, Dimension::Steer)?,
    };
    let mut files = save_png_and_svg(&speeds, out, &format!("rival_speed_{name}"))?;
    files.extend(save_png_and_svg(
        &lines,
        out,
        &format!("rival_lines_{name}"),
    )?);
    Ok(files)
}

/// Rival speed along the lap for several `c_v` (paper Fig. 3).
struct SpeedProfiles(RivalLaps);

impl Figure for SpeedProfiles {
    fn size(&self) -> (u32, u32) {
        (1400, 500)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        let laps = &self.0;
        root.fill(&WHITE).map_err(plot_err)?;
        let samples = || laps.laps.iter().flat_map(|l| &l.2.samples);
        let length = samples().map(|s| s.travelled).fold(1.0, f64::max);
        let top = samples().map(|s| s.speed).fold(0.1, f64::max) * 1.1;
        let mut chart = ChartBuilder::on(root)
            .caption(format!("Rival speed on {} (c_θ = 0)", laps.track), font(24))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..length, 0.0..top)
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .x_desc("distance along the centreline (m)")
            .y_desc("speed (m/s)")
            .label_style(font(14))
            .axis_desc_style(font(16))
            .draw()
            .map_err(plot_err)?;
        for (c, colour, lap) in &laps.laps {
            let colour = *colour;
            chart
                .draw_series(LineSeries::new(
                    lap.samples.iter().map(|s| (s.travelled, s.speed)),
                    colour.stroke_width(2),
                ))
                .map_err(plot_err)?
                .label(laps.label(*c, lap))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
        }
        legend(&mut chart, SeriesLabelPosition::LowerRight)
    }
}

/// Rival paths around the track for several `c_θ` (paper Fig. 4).
struct RaceLines<'a> {
    track: &'a Track,
    laps: RivalLaps,
}

impl Figure for RaceLines<'_> {
    fn size(&self) -> (u32, u32) {
        let (w, h) = track_picture_size(self.track);
        (w, h + 40)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult<()>
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(plot_err)?;
        let (lo, hi) = bounds(self.track);
        let mut chart = ChartBuilder::on(root)
            .caption(
                format!("Rival race lines on {} (c_v = 0)", self.laps.track),
                font(24),
            )
            .margin(10)
            .build_cartesian_2d(lo.0..hi.0, lo.1..hi.1)
            .map_err(plot_err)?;
        draw_track(&mut chart, self.track)?;
        // widest first, so that lines on top of each other all show
        let n = self.laps.laps.len() as u32;
        for (i, (c, colour, lap)) in self.laps.laps.iter().enumerate() {
            let colour = *colour;
            chart
                .draw_series(std::iter::once(PathElement::new(
                    lap.samples.iter().map(|s| (s.x, s.y)).collect::<Vec<_>>(),
                    colour.stroke_width(2 * (n - i as u32)),
                )))
                .map_err(plot_err)?
                .label(self.laps.label(*c, lap))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
        }
        legend(&mut chart, SeriesLabelPosition::UpperRight)
    }
}

/// Draws the series labels at `position`.
fn legend<'a, DB: DrawingBackend + 'a>(
    chart: &mut TrackChart<'a, DB>,
    position: SeriesLabelPosition,
) -> DrawResult<()>
where
    DB::ErrorType: 'static,
{
    chart
        .configure_series_labels()
        .label_font(font(16))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(position)
        .draw()
        .map_err(plot_err)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(env_steps: u64, progress: f64) -> TrainingEpisode {
        TrainingEpisode {
            env_steps,
            grad_steps: 0,
            actor: 0,
            episode: 0,
            context_speed: 0.0,
            context_steer: 0.0,
            progress,
            overtakes: 0,
            a2a: false,
            wall_crash: false,
            episode_return: 0.0,
            steps: 1,
        }
    }

    #[test]
    fn a_curve_averages_each_run_per_bin_then_over_the_runs() {
        let a = [episode(10, 0.1), episode(90, 0.3), episode(150, 0.8)];
        let b = [episode(50, 0.4), episode(250, 1.0)];
        let runs = [a.as_slice(), b.as_slice()];
        // bins of 100 env steps: [0, 100) holds a's 0.1 and 0.3 and b's 0.4; the last bin
        // takes every later episode (b's at 250)
        let curve = binned_curve(&runs, |e| e.progress, (2, 100.0), Band::MinMax);
        assert_eq!(curve.len(), 2);
        let (x, mean, lo, hi) = curve[0];
        assert_eq!(x, 50.0);
        assert!((mean - 0.3).abs() < 1e-12 && (lo - 0.2).abs() < 1e-12 && hi == 0.4);
        let (x, mean, lo, hi) = curve[1];
        assert_eq!((x, lo, hi), (150.0, 0.8, 1.0));
        assert!((mean - 0.9).abs() < 1e-12);
        // a bin no run has an episode in is left out
        let gap = binned_curve(&[&a[..1]], |e| e.progress, (3, 100.0), Band::MinMax);
        assert_eq!(gap.len(), 1);
    }
}
