//! Per-context heatmaps of PG and A2A, seed-averaged, one panel per metric.

use super::*;

/// The metrics of the heatmaps and the top of their colour scales.
const HEATMAP_METRICS: [(Metric, f64); 2] = [(Metric::Progress, 1.0), (Metric::A2a, A2A_PER_LAPS)];

/// Grids with at most this many values per axis get their cell values written in.
const MAX_LABELLED_GRID: usize = 9;

/// PG and A2A over the context grid of one group, with the training range outlined.
pub(super) struct Heatmap<'a> {
    /// The runs drawn.
    pub(super) group: &'a Group,
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
pub(super) fn heatmap_panel<DB: DrawingBackend>(
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
