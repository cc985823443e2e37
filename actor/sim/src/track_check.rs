//! Whether a map is raceable (`ctxrace track check`, and `train`'s gate on its training contexts). The pure-pursuit reference ego must lap
//! alone; rivals in each context of the evaluation grid must drive from each of the first grid
//! places round to the start line with the ego standing still on it; the track must be wide
//! enough for a car with a margin each side; the raceline's curvature must lie within the car's
//! steering limit. Each failure says where on the track it happened.

use crate::baseline::{Baseline, BaselineKind};
use crate::driver::{BaselineEgo, DriveError, Ego as _};
use crate::race::{RaceEnv, RaceError};
use crate::vehicle::{idx, VehicleParams};
use ctxrace_config::{Context, RaceConfig};
use ctxrace_tracks::Track;
use serde::Serialize;
use std::sync::Arc;

/// Free space a car needs beside it on each side (m), on top of its width.
const SIDE_MARGIN_M: f64 = 0.3;

/// What `track check` measures.
#[derive(Clone, Copy, Debug)]
pub struct CheckPlan {
    /// The contexts' grid: `grid × grid` over `[−range, range]²`.
    pub grid: usize,
    /// Half-width of the contexts' grid.
    pub range: f64,
    /// Grid places behind which rivals are checked: 1 (just ahead of the ego) to this.
    pub places: usize,
}

impl Default for CheckPlan {
    /// The evaluation protocol's 7 × 7 contexts over `[−0.3, 0.3]²`, grid places 1 to 3.
    fn default() -> Self {
        Self {
            grid: 7,
            range: 0.3,
            places: 3,
        }
    }
}

/// One check's result.
#[derive(Clone, Debug, Serialize)]
pub struct Finding {
    /// Which check.
    pub check: &'static str,
    /// Whether it passed.
    pub passed: bool,
    /// What was measured, and where it failed.
    pub detail: String,
}

/// Every check's result on one track.
#[derive(Clone, Debug, Serialize)]
pub struct CheckReport {
    /// The track's name.
    pub track: String,
    /// The checks, in order: width, curvature, ego, rivals (one line per failing race).
    pub findings: Vec<Finding>,
}

impl CheckReport {
    /// Whether every check passed.
    pub fn raceable(&self) -> bool {
        self.findings.iter().all(|f| f.passed)
    }

    /// Whether some rival failed to drive (crashed on its own, or never reached the line).
    pub fn rivals_fail(&self) -> bool {
        self.failures().any(|f| f.check == RIVALS_DRIVE)
    }

    /// The failing findings.
    pub fn failures(&self) -> impl Iterator<Item = &Finding> {
        self.findings.iter().filter(|f| !f.passed)
    }

    /// The report as lines of text: each check (only the failing ones if `failures_only`)
    /// marked ok or FAIL, then the verdict.
    pub fn to_text(&self, failures_only: bool) -> String {
        let mut text = String::new();
        for f in &self.findings {
            if !(failures_only && f.passed) {
                let mark = if f.passed { "ok  " } else { "FAIL" };
                text += &format!("{mark} {:<26} {}\n", f.check, f.detail);
            }
        }
        let verdict = if self.raceable() {
            "raceable"
        } else {
            "not raceable"
        };
        text + &format!("{} is {verdict}", self.track)
    }
}

/// The name of the rivals' check.
const RIVALS_DRIVE: &str = "rivals drive";

/// Runs every check of `plan` on `track` in the race `race` describes. The cars get at least
/// the default race's time for their lap: the checks ask whether they drive, not whether they
/// finish within a short episode's time limit.
pub fn check_track(
    track: Arc<Track>,
    race: &RaceConfig,
    plan: CheckPlan,
) -> Result<CheckReport, RaceError> {
    let race = &RaceConfig {
        max_time: race.max_time.max(RaceConfig::default().max_time),
        ..race.clone()
    };
    let mut findings = vec![width(&track), curvature(&track, race)];
    findings.push(ego_laps(&track, race)?);
    findings.extend(rivals_drive(&track, race, plan)?);
    Ok(CheckReport {
        track: track.name.clone(),
        findings,
    })
}

/// Where on `track` the point `(x, y)` is: metres along the centreline and the point.
fn place(track: &Track, x: f64, y: f64) -> String {
    let s = track
        .centreline
        .curve
        .project(&nalgebra::Point2::new(x, y))
        .s;
    format!("at {s:.1} m of {:.1} m ({x:.1}, {y:.1})", track.length())
}

/// The narrowest wall-to-wall width across the centreline against the car's width and margins.
fn width(track: &Track) -> Finding {
    let need = VehicleParams::default().width + 2.0 * SIDE_MARGIN_M;
    let widths = track.drawn_widths();
    let (i, narrowest) = widths
        .iter()
        .copied()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0, f64::INFINITY));
    let p = track.centreline.curve.points()[i];
    Finding {
        check: "width",
        passed: narrowest >= need,
        detail: format!(
            "narrowest {narrowest:.2} m {} (a car needs {need:.2} m)",
            place(track, p.x, p.y)
        ),
    }
}

/// The raceline's sharpest curvature against the tightest turn the car's steering allows.
fn curvature(track: &Track, race: &RaceConfig) -> Finding {
    let p = VehicleParams::default();
    let limit = p.s_max.min(race.max_steer).tan() / p.wheelbase();
    let r = &track.raceline;
    let (i, sharpest) = r
        .kappa
        .iter()
        .map(|k| k.abs())
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0, 0.0));
    let pt = r.curve.points()[i];
    Finding {
        check: "raceline curvature",
        passed: sharpest <= limit,
        detail: format!(
            "sharpest {sharpest:.3} 1/m {} (the car turns at most {limit:.3} 1/m)",
            place(track, pt.x, pt.y)
        ),
    }
}

/// The pure-pursuit reference ego alone on the track.
fn ego_laps(track: &Track, race: &RaceConfig) -> Result<Finding, RaceError> {
    let cfg = RaceConfig {
        rivals: 0,
        ..race.clone()
    };
    let mut env = RaceEnv::new(Arc::new(track.clone()), cfg)?;
    BaselineEgo::new(BaselineKind::PurePursuit, &env)
        .drive_episode(&mut env, Context::default(), 0)
        .map_err(|e| match e {
            DriveError::Race(e) => e,
            DriveError::Ego(never) => match never {},
        })?;
    let m = env.metrics();
    let detail = match m.lap_time {
        Some(t) => format!("lap in {t:.1} s"),
        None => {
            let s = env.ego_state();
            format!("{} {}", m.ended_by(), place(track, s[idx::X], s[idx::Y]))
        }
    };
    Ok(Finding {
        check: "reference ego laps alone",
        passed: m.lap_time.is_some(),
        detail,
    })
}

/// Rivals in every context of the grid, from each grid place up to `plan.places`, the ego
/// standing still on the start line: the rival furthest up the grid must reach the line
/// without crashing. One finding per failing race, then a summary.
fn rivals_drive(
    track: &Track,
    race: &RaceConfig,
    plan: CheckPlan,
) -> Result<Vec<Finding>, RaceError> {
    let mut findings = Vec::new();
    let contexts = Context::grid(plan.grid, plan.range);
    let mut failed = 0;
    for places in 1..=plan.places {
        // the ego stands still whatever the race's ego keys: the paper code's speed range from
        // 1 m/s would make it crawl into a wall, and its launch rule drive it off at 7 m/s
        let cfg = RaceConfig {
            rivals: places,
            min_speed: 0.0,
            ego_relaunch: false,
            ..race.clone()
        };
        let mut env = RaceEnv::new(Arc::new(track.clone()), cfg)?;
        let length = track.length();
        for &context in &contexts {
            env.reset(0, context);
            let mut still = Baseline::new(BaselineKind::Still, &env, 0);
            let outcome = loop {
                let step = env.step(still.act(&env))?;
                let cars = env.cars();
                let rival = &cars[places];
                // a rival that reaches the line may hit the ego standing on it
                if rival.travelled >= length || env.metrics().a2a {
                    break None;
                }
                if rival.crashed {
                    let [x, y] = [rival.vehicle.state[idx::X], rival.vehicle.state[idx::Y]];
                    let touching = cars[1..places].iter().any(|c| {
                        c.crashed
                            && (c.vehicle.state[idx::X] - x).hypot(c.vehicle.state[idx::Y] - y)
                                < 1.0
                    });
                    let what = if touching {
                        "collided with another rival"
                    } else {
                        "hit a wall"
                    };
                    break Some(format!("{what} {}", place(track, x, y)));
                }
                if step.terminated || step.truncated {
                    break Some(format!(
                        "did not reach the line: the race ended by {} after {:.1} s",
                        env.metrics().ended_by(),
                        step.info.time
                    ));
                }
            };
            if let Some(why) = outcome {
                failed += 1;
                findings.push(Finding {
                    check: RIVALS_DRIVE,
                    passed: false,
                    detail: format!(
                        "context c_v {:+.2}, c_t {:+.2}, rival from grid place {places}: {why}",
                        context.speed, context.steer
                    ),
                });
            }
        }
    }
    let races = contexts.len() * plan.places;
    findings.push(Finding {
        check: RIVALS_DRIVE,
        passed: failed == 0,
        detail: format!(
            "{} of {races} races ({} contexts x grid places 1..={}) reach the line",
            races - failed,
            contexts.len(),
            plan.places
        ),
    });
    Ok(findings)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_tracks::TrackOptions;

    fn load(spec: &str, opts: &TrackOptions) -> Arc<Track> {
        Arc::new(Track::load(spec, opts).unwrap_or_else(|e| panic!("{spec}: {e}")))
    }

    #[test]
    fn a_paper_map_passes_every_check() {
        let dir =
            ctxrace_tracks::files::shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
        let opts = TrackOptions {
            tracks_dir: dir,
            ..TrackOptions::default()
        };
        let plan = CheckPlan {
            grid: 3,
            range: 0.3,
            places: 2,
        };
        let report = check_track(load("f1_esp", &opts), &RaceConfig::default(), plan).unwrap();
        assert!(report.raceable(), "{:#?}", report.findings);
        let checks: Vec<_> = report.findings.iter().map(|f| f.check).collect();
        assert_eq!(
            checks,
            [
                "width",
                "raceline curvature",
                "reference ego laps alone",
                "rivals drive"
            ]
        );
        assert!(report.findings[3].detail.starts_with("18 of 18 races"));
        // under the paper code's race too, whose ego could not stand still (from 1 m/s it
        // crawled into a wall after 24.8 s, ending every race of the check)
        // (over the training contexts: at c_v = +0.3 the code's driver crashes 4 of 147 laps)
        let training = CheckPlan {
            range: 0.15,
            ..plan
        };
        let code = check_track(load("f1_esp", &opts), &RaceConfig::paper_code(), training);
        let code = code.unwrap();
        assert!(code.raceable(), "{:#?}", code.findings);
    }

    #[test]
    fn rivals_far_too_fast_fail_naming_the_context_the_grid_place_and_where() {
        let track = load("generated:3", &TrackOptions::default());
        // contexts ±0.9: rivals at 1.9 times their speed cannot take the corners
        let plan = CheckPlan {
            grid: 2,
            range: 0.9,
            places: 1,
        };
        let findings = rivals_drive(&track, &RaceConfig::default(), plan).unwrap();
        let (summary, failures) = findings.split_last().unwrap();
        assert!(!summary.passed);
        assert!(!failures.is_empty());
        assert!(
            summary
                .detail
                .starts_with(&format!("{} of 4 races", 4 - failures.len())),
            "{}",
            summary.detail
        );
        for f in failures {
            assert!(!f.passed);
            assert!(f.detail.contains("c_v +0.90"), "{}", f.detail);
            assert!(
                f.detail.contains("rival from grid place 1: "),
                "{}",
                f.detail
            );
            assert!(
                f.detail
                    .contains(&format!(" m of {:.1} m (", track.length())),
                "{}",
                f.detail
            );
        }
    }
}
