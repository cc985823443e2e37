//! The rivals' speed profiles and race lines under different contexts (paper Figs. 3-4), each
//! rival driving a lap alone.

use super::*;

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
pub(super) fn rival_figures(track: &Track, cfg: &RaceConfig, out: &Path) -> Result<Vec<PathBuf>> {
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
