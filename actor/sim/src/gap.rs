//! Follow-the-gap (Sezer & Gokasan 2012, in the form the F1TENTH course teaches): a reactive
//! driver that needs no raceline, planning every decision from an exact LiDAR scan of its own
//! pose ([`Lidar`], noise-free) that sees the walls and every other car. The steps, their maths
//! and their parameters are those of [`FollowTheGapConfig`]: clip and smooth the ranges, blank
//! a safety bubble around the closest point, find the largest gap of free beams, steer at its
//! best point, and pick the speed from the steering angle and the braking distance to what lies
//! on the way. The context scales it as it scales the pure-pursuit rival: the speed by
//! `1 + λ_v c_v`, the steering gain by `1 / (1 + λ_θ c_θ)` (a lookahead `1 + λ_θ c_θ` times
//! longer).

use crate::collision::CarBox;
use crate::lidar::{Lidar, NearbyWalls};
use crate::vehicle::{idx, State};
use ctxrace_config::{Context, ContextGains, FollowTheGapConfig, GapAim, LidarConfig};
use ctxrace_tracks::Walls;
use nalgebra::Point2;
use std::f64::consts::FRAC_PI_2;

/// A follow-the-gap driver with its scan buffers.
#[derive(Clone, Debug)]
pub struct FollowTheGap {
    cfg: FollowTheGapConfig,
    lidar: Lidar,
    nearby: NearbyWalls,
    /// Beam angles `α_k` from the heading (rad, left positive).
    angles: Vec<f64>,
    /// The raw scan (m, capped at `range_clip`).
    scan: Vec<f32>,
    /// The smoothed, bubbled ranges.
    work: Vec<f64>,
    /// Prefix sums of the clipped ranges (the moving average).
    sums: Vec<f64>,
    /// `1 / (1 + λ_θ c_θ)`.
    steer_scale: f64,
    /// `1 + λ_v c_v`.
    speed_scale: f64,
    /// Cap on the commanded speed (m/s).
    speed_cap: f64,
    /// Largest steering command (rad).
    max_steer: f64,
    /// Half the car's width: the corridor ahead checked for braking (m).
    half_width: f64,
}

/// The plan of one decision: what the driver saw and chose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GapPlan {
    /// First and last beam of the largest gap, if any beam was free.
    pub gap: Option<(usize, usize)>,
    /// Angle of the best point from the heading (rad, left positive).
    pub aim: f64,
    /// Steering command (rad, left positive).
    pub steer: f64,
    /// Speed command (m/s).
    pub speed: f64,
}

impl FollowTheGap {
    /// A rival driver in `ctx`: the context scales speed and steering gain (see the module
    /// docs); `max_steer` bounds the steering and `width` is the car's width (m).
    pub fn rival(
        cfg: &FollowTheGapConfig,
        gains: ContextGains,
        ctx: Context,
        max_steer: f64,
        width: f64,
    ) -> Self {
        Self {
            steer_scale: 1.0 / (1.0 + gains.lambda_theta * ctx.steer),
            speed_scale: 1.0 + gains.lambda_v * ctx.speed,
            ..Self::reference(cfg, f64::INFINITY, max_steer, width)
        }
    }

    /// The context-free driver, its speed capped at `speed_cap` (the reference ego).
    pub fn reference(cfg: &FollowTheGapConfig, speed_cap: f64, max_steer: f64, width: f64) -> Self {
        let lidar = Lidar::new(&LidarConfig {
            beams: cfg.beams,
            fov_deg: cfg.fov_deg,
            max_range: cfg.max_range,
            noise_sd: 0.0,
        });
        let fov = cfg.fov_deg.to_radians();
        let n = cfg.beams;
        let angles = (0..n)
            .map(|k| {
                if n == 1 {
                    0.0
                } else {
                    -fov / 2.0 + fov * k as f64 / (n - 1) as f64
                }
            })
            .collect();
        Self {
            cfg: cfg.clone(),
            lidar,
            nearby: NearbyWalls::default(),
            angles,
            scan: vec![0.0; n],
            work: vec![0.0; n],
            sums: Vec::with_capacity(n + 1),
            steer_scale: 1.0,
            speed_scale: 1.0,
            speed_cap,
            max_steer,
            half_width: width / 2.0,
        }
    }

    /// The command `(steering angle, speed)` for a car in state `x` among `walls` and the other
    /// cars `others` (its own box excluded).
    pub fn command(&mut self, walls: &Walls, others: &[CarBox], x: &State) -> (f64, f64) {
        let origin = Point2::new(x[idx::X], x[idx::Y]);
        let mut scan = std::mem::take(&mut self.scan);
        self.lidar.ranges(
            origin,
            x[idx::YAW],
            &mut self.nearby,
            walls,
            others,
            &mut scan,
        );
        let plan = self.plan(&scan);
        self.scan = scan;
        (plan.steer, plan.speed)
    }

    /// Plans from a scan `ranges` (m, one per beam, right to left).
    pub fn plan(&mut self, ranges: &[f32]) -> GapPlan {
        let cfg = &self.cfg;
        let clip = cfg.range_clip;
        let n = ranges.len().min(self.angles.len());
        let raw = |k: usize| (ranges[k] as f64).clamp(0.0, clip);
        // 1. clip and smooth: the centred window k − ⌊w/2⌋ .. k − ⌊w/2⌋ + w − 1, cut at the ends
        let w = cfg.smoothing.max(1);
        let sums = &mut self.sums;
        sums.clear();
        sums.push(0.0);
        let mut prefix = 0.0;
        for k in 0..n {
            prefix += raw(k);
            sums.push(prefix);
        }
        let work = &mut self.work;
        work.resize(n, 0.0);
        for (k, slot) in work.iter_mut().enumerate() {
            let lo = k.saturating_sub(w / 2);
            let hi = (lo + w).min(n);
            *slot = (sums[hi] - sums[lo]) / (hi - lo) as f64;
        }
        // 2. the safety bubble: beams crossing the line through the closest point, square to
        // its beam, within R of it (|α_k − α*| ≤ atan(R / r*))
        let closest = (0..n)
            .min_by(|&a, &b| work[a].total_cmp(&work[b]))
            .unwrap_or(0);
        let r_min = work.get(closest).copied().unwrap_or(0.0);
        let half = if r_min > 0.0 {
            (cfg.bubble_radius / r_min).atan()
        } else {
            FRAC_PI_2
        };
        let a_min = self.angles.get(closest).copied().unwrap_or(0.0);
        for (slot, a) in work.iter_mut().zip(&self.angles) {
            if (a - a_min).abs() <= half {
                *slot = 0.0;
            }
        }
        // 3. the largest gap of free beams; 4. its best point
        let angles = &self.angles;
        let gap = longest_run(
            n,
            |k| work[k] > cfg.free_range,
            |a, b| (angles[a] + angles[b]).abs(),
        );
        let aim = match gap {
            Some((a, b)) => match cfg.aim {
                GapAim::Middle => (angles[a] + angles[b]) / 2.0,
                GapAim::Farthest => {
                    let far = work[a..=b].iter().copied().fold(0.0, f64::max);
                    let (p, q) = longest_run(
                        n,
                        |k| k >= a && k <= b && work[k] >= far - 1e-9,
                        |p, q| (angles[p] + angles[q]).abs(),
                    )
                    .unwrap_or((a, b));
                    (angles[p] + angles[q]) / 2.0
                }
            },
            // nothing free: the farthest beam of the bubbled scan, straight on if all are blank
            None => (0..n)
                .filter(|&k| work[k] > 0.0)
                .max_by(|&a, &b| work[a].total_cmp(&work[b]))
                .map_or(0.0, |k| angles[k]),
        };
        // 5. steering, the context scaling the gain
        let steer0 = (cfg.steer_gain * aim).clamp(-self.max_steer, self.max_steer);
        let steer =
            (cfg.steer_gain * aim * self.steer_scale).clamp(-self.max_steer, self.max_steer);
        // 6. speed from the context-free steering, capped by the braking distance on the way to
        // the best point, scaled by the context
        let turn = (steer0.abs() / cfg.corner_steer).min(1.0);
        let mut speed = cfg.straight_speed - (cfg.straight_speed - cfg.corner_speed) * turn;
        if cfg.brake_decel > 0.0 {
            let ahead = (0..n)
                .filter_map(|k| {
                    let (s, c) = (angles[k] - aim).sin_cos();
                    let r = ranges[k] as f64;
                    (c > 0.0 && (r * s).abs() <= self.half_width).then_some(r * c)
                })
                .fold(cfg.max_range, f64::min);
            speed = speed.min((2.0 * cfg.brake_decel * (ahead - cfg.stop_margin).max(0.0)).sqrt());
        }
        GapPlan {
            gap,
            aim,
            steer,
            speed: (speed * self.speed_scale).min(self.speed_cap).max(0.0),
        }
    }
}

/// The longest run of consecutive indices in `0..n` where `keep` holds, as (first, last);
/// among equally long runs the one with the smallest `tie(first, last)`.
fn longest_run(
    n: usize,
    keep: impl Fn(usize) -> bool,
    tie: impl Fn(usize, usize) -> f64,
) -> Option<(usize, usize)> {
    let mut best: Option<(usize, usize)> = None;
    let mut k = 0;
    while k < n {
        if !keep(k) {
            k += 1;
            continue;
        }
        let start = k;
        while k < n && keep(k) {
            k += 1;
        }
        let run = (start, k - 1);
        best = match best {
            Some((a, b)) => {
                let (len, best_len) = (run.1 - run.0, b - a);
                if len > best_len || (len == best_len && tie(run.0, run.1) < tie(a, b)) {
                    Some(run)
                } else {
                    Some((a, b))
                }
            }
            None => Some(run),
        };
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_config::{RaceConfig, RivalDriverKind};
    use ctxrace_tracks::{Track, TrackOptions};

    const GAINS: ContextGains = ContextGains {
        lambda_v: 1.0,
        lambda_theta: 0.4,
    };

    fn driver(ctx: Context) -> FollowTheGap {
        FollowTheGap::rival(&FollowTheGapConfig::default(), GAINS, ctx, 0.4189, 0.31)
    }

    /// The scan of the default 108 beams over 180° given the range of each beam angle.
    fn scan(range: impl Fn(f64) -> f64) -> Vec<f32> {
        let d = driver(Context::default());
        d.angles.iter().map(|&a| range(a) as f32).collect()
    }

    /// Between two straight walls 0.9 m either side, open ahead.
    fn corridor(a: f64) -> f64 {
        (0.9 / a.sin().abs()).min(10.0)
    }

    #[test]
    fn a_straight_corridor_is_driven_straight_at_full_speed() {
        let plan = driver(Context::default()).plan(&scan(corridor));
        assert!(plan.gap.is_some());
        // the farthest points (clipped at 2.5 m) lie symmetrically about the heading
        assert!(plan.aim.abs() < 1e-9, "{plan:?}");
        assert!(plan.steer.abs() < 1e-9);
        assert_eq!(plan.speed, FollowTheGapConfig::default().straight_speed);
    }

    #[test]
    fn the_bubble_turns_the_car_away_from_the_closest_point_and_slows_it() {
        // open space, and a car 1.5 m ahead, a little to the left
        let ranges = scan(|a| if (0.0..0.2).contains(&a) { 1.5 } else { 10.0 });
        let plan = driver(Context::default()).plan(&ranges);
        let cfg = FollowTheGapConfig::default();
        // the bubble (atan(1 / 1.5) ≈ 34° about the car) leaves the larger gap on the right
        let (a, b) = plan.gap.unwrap();
        let d = driver(Context::default());
        assert!(d.angles[b] < 0.2 - (cfg.bubble_radius / 1.5).atan() + 0.03);
        assert_eq!(a, 0);
        assert!(plan.aim < -0.5, "{plan:?}");
        assert_eq!(plan.steer, -0.4189);
        assert_eq!(plan.speed, cfg.corner_speed);
    }

    #[test]
    fn what_lies_on_the_way_caps_the_speed_by_its_braking_distance() {
        let cfg = FollowTheGapConfig::default();
        // a wall square across the heading 3 m ahead, walls 0.9 m either side
        let ranges = scan(|a| corridor(a).min(3.0 / a.cos().max(1e-9)));
        let plan = driver(Context::default()).plan(&ranges);
        assert!(plan.aim.abs() < 1e-9, "{plan:?}");
        let cap = (2.0 * cfg.brake_decel * (3.0 - cfg.stop_margin)).sqrt();
        assert!((plan.speed - cap).abs() < 1e-6, "{} vs {cap}", plan.speed);
    }

    #[test]
    fn the_context_scales_speed_and_steering_gain_as_it_scales_pure_pursuit() {
        // a free window about +0.1 rad between walls 0.8 m away
        let ranges = scan(|a| if (a - 0.1).abs() <= 0.3 { 3.0 } else { 0.8 });
        let base = driver(Context::default()).plan(&ranges);
        assert!(base.aim > 0.05 && base.aim < 0.15, "{base:?}");
        let ctx = Context::new(0.3, 0.3).unwrap();
        let scaled = driver(ctx).plan(&ranges);
        assert_eq!(scaled.aim, base.aim);
        let steer_scale = 1.0 + GAINS.lambda_theta * ctx.steer;
        assert!((scaled.steer * steer_scale - base.steer).abs() < 1e-12);
        let speed_scale = 1.0 + GAINS.lambda_v * ctx.speed;
        assert!((scaled.speed - base.speed * speed_scale).abs() < 1e-12);
        // the speed follows the context-free steering: a slower context keeps the same schedule
        let slow = driver(Context::new(-0.3, -0.3).unwrap()).plan(&ranges);
        assert!((slow.speed - base.speed * 0.7).abs() < 1e-12);
    }

    #[test]
    fn the_middle_aim_steers_at_the_gap_centre() {
        let cfg = FollowTheGapConfig {
            aim: GapAim::Middle,
            ..FollowTheGapConfig::default()
        };
        let mut d = FollowTheGap::rival(&cfg, GAINS, Context::default(), 0.4189, 0.31);
        let ranges = scan(|a| if (a - 0.1).abs() <= 0.3 { 3.0 } else { 0.8 });
        let plan = d.plan(&ranges);
        let (a, b) = plan.gap.unwrap();
        assert_eq!(plan.aim, (d.angles[a] + d.angles[b]) / 2.0);
    }

    #[test]
    fn the_scan_sees_the_other_cars() {
        use crate::vehicle::VehicleParams;
        use nalgebra::Point2;
        // a corridor 1.8 m wide and 40 m long; the car at its start, facing along it
        let walls = Walls::from_loops(vec![vec![
            Point2::new(-1.0, -0.9),
            Point2::new(40.0, -0.9),
            Point2::new(40.0, 0.9),
            Point2::new(-1.0, 0.9),
        ]]);
        let x: State = [0.0; 7];
        let mut d = driver(Context::default());
        let (steer, speed) = d.command(&walls, &[], &x);
        assert!(steer.abs() < 1e-9 && speed == 5.0, "{steer} {speed}");
        // a car stopped 2 m ahead, a little right of the middle: pass it on the left, slower
        let mut other: State = [0.0; 7];
        other[idx::X] = 2.0;
        other[idx::Y] = -0.2;
        let car = CarBox::new(&other, &VehicleParams::default());
        let (steer, speed) = d.command(&walls, &[car], &x);
        assert!(steer > 0.05 && speed < 5.0, "{steer} {speed}");
    }

    #[test]
    fn a_follow_the_gap_rival_laps_a_generated_track_alone() {
        let track = Track::load("generated:0", &TrackOptions::default()).unwrap();
        let mut cfg = RaceConfig::default();
        cfg.rival.driver = RivalDriverKind::FollowTheGap;
        for context in [
            Context::default(),
            Context::new(0.3, -0.3).unwrap(),
            Context::new(-0.3, 0.3).unwrap(),
        ] {
            for place in 1..=3 {
                let start = place as f64 * cfg.grid_spacing(&track.name, track.length());
                let lap = crate::rival::drive_solo_lap(&track, &cfg, context, start).unwrap();
                assert!(
                    lap.completed,
                    "{context:?} from place {place}: wall at {:?} after {:.1} s",
                    lap.wall_hit_at, lap.time
                );
            }
        }
    }
}
