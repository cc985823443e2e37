//! Training curves: episodes binned by env steps, each run averaged per bin, then the runs
//! (mean and band); the parity figures of the paper's code beside ctxrace.

use super::*;

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

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_run::results::TrainingEpisode;

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
