//! cMask's masks: per-context heatmaps of each component, the mask along the lap, and the mask
//! drawn on the track.

use super::*;

/// The mask components: their index in a mask and name.
const MASK_COMPONENTS: [(usize, &str); 2] = [(0, "c_v (rival speed)"), (1, "c_θ (rival steering)")];

/// The mean of each cMask mask component over the context grid of one group (seeds averaged),
/// with the training range outlined.
pub(super) struct MaskHeatmap<'a> {
    /// The runs drawn.
    pub(super) group: &'a Group,
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
pub(super) struct MaskAlongLap<'a> {
    /// The runs drawn.
    pub(super) group: &'a Group,
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
pub(super) struct MaskOnTrack<'a> {
    group: &'a Group,
    track: &'a Track,
    seed: u64,
    lap: &'a ContextMasks,
}

impl<'a> MaskOnTrack<'a> {
    /// The figure of `g` on `track`, if it has masks.
    pub(super) fn of(g: &'a Group, track: &'a Track) -> Option<Self> {
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
