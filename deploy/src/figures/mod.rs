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

mod curves;
mod heatmaps;
mod masks;
mod rivals;

pub use curves::{binned_curve, write_parity, Band, CurveSeries, TrainingCurves, CURVE_PANELS};
use heatmaps::{heatmap_panel, Heatmap};
use masks::{MaskAlongLap, MaskHeatmap, MaskOnTrack};
use rivals::rival_figures;

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
