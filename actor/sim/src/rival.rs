//! The rivals' drivers ([`RivalDriver`], chosen by `[rival] driver`): pure pursuit on the
//! raceline, its speed and lookahead scaled by the context (below), follow-the-gap on the
//! rival's own scan ([`crate::gap`]), or a trained agent on it ([`crate::policy_rival`]).
//!
//! Each decision the driver searches the target point `g`: the first raceline point, going
//! forward from the car's foot point, at distance `r = d_0 + k v` from the car (`d_0 = 1` m,
//! `k = 0.1` s, the paper's code). It steers with the pure-pursuit law `δ = atan(2 L y / L_d²)`,
//! where `y` is the lateral offset of `g` in the car frame and `L` the wheelbase. The speed
//! command is the raceline speed read at [`SpeedPoint`], capped at `v_cap`, times
//! `f (1 + λ_v c_v)` with the speed factor `f` (0.85 in the code that produced the paper's tables).
//!
//! **ctxrace's driver (the default).** `L_d = r`, and the context scales the whole lookahead:
//! `r = (d_0 + k v)(1 + λ_θ c_θ)`. The speed is the slowest raceline speed between the car and
//! `g`, so the rival brakes for a corner as early as when reading it at `g` (the paper's text)
//! and does not accelerate before the corner's exit. It always steers. A rival told to drive
//! faster than its line (`f (1 + λ_v c_v) > 1`: `c_v ≥ 0.2` at `f = 0.85`) that has run more than
//! `lift_off_line` (0.15 m) wide lifts to the line's speed until it is back on it, as a driver
//! lifts off the throttle: pure pursuit's path error grows with speed, and at `c_v = +0.3` the
//! rivals ran 0.25 to 0.35 m off the line on every map (0.12 m at `c_v = 0`), more than the
//! raceline's 0.25 m wall margin leaves on the corner exits of f1_mco, Monza, Oschersleben and
//! Spielberg, where 1 to 5 of 147 fast races hit the wall; with the lift none do, and rivals at
//! `c_v ≤ 0.1` and the reference ego (never faster than the line) drive exactly as before.
//!
//! **The paper's code** (Planners/PurePursuit.py; `preset = "paper-code"`) searched `g` at the
//! unscaled `1 + 0.1 v` but steered as if it were a fixed `L_d = 1.5 (1 + λ_θ c_θ)` away
//! (`steer_lookahead`), snapped `g` back to the raceline vertex starting the segment it lies on
//! (`target_at_vertex`), read the speed at the nearest vertex (`speed_point = "nearest"`), and
//! below 1 m/s drove straight at 4 m/s (`launch_below`, `launch_speed`).
//!
//! Why ctxrace departs: at the paper's text speed (f = 0.3, ≈1.5 m/s) the code's law understeers
//! by `(1.15 / 1.5)² ≈ 0.6` and put rivals into the walls of f1_gbr in every context; at f = 0.8
//! the two distances nearly agree on the straights but not in slow corners. Reading the speed
//! at `g` makes fast rivals with long lookahead (`c_v, c_θ ≥ 0.2`) accelerate out of corners
//! they have not left and run wide into the wall; the slowest speed ahead keeps all 49
//! evaluation contexts on the track on f1_esp and f1_gbr (tested).

use crate::collision::CarBox;
use crate::gap::FollowTheGap;
use crate::policy_rival::{PolicyRival, RivalAgent, RivalAgentError};
use crate::vehicle::{idx, State, VehicleParams};
use ctxrace_config::{
    Context, ContextGains, RivalConfig, RivalContacts, RivalDriverKind, SpeedPoint,
};
use ctxrace_tracks::{Raceline, Track};
use nalgebra::Point2;
use std::path::Path;

/// A rival's driver, of the kind `[rival] driver` names; each plans from its own car's state.
#[derive(Debug)]
pub enum RivalDriver {
    /// Pure pursuit on the raceline ([`PurePursuit`]).
    PurePursuit(PurePursuit),
    /// Follow-the-gap on the car's own scan ([`FollowTheGap`]).
    FollowTheGap(Box<FollowTheGap>),
    /// A trained agent on the car's own scan ([`PolicyRival`]).
    Policy(Box<PolicyRival>),
}

impl RivalDriver {
    /// The scripted driver `cfg` names for a rival in context `ctx` (gains `gains`), on a car
    /// with parameters `params`: its steering law's wheelbase and its steering limit are
    /// `cfg`'s `wheelbase` and `max_steer` where set, else the car's. `None` for `policy`: a
    /// trained agent is read once per race and restarted each episode
    /// ([`RivalDriver::restart`]).
    pub fn scripted(
        cfg: &RivalConfig,
        gains: ContextGains,
        ctx: Context,
        params: &VehicleParams,
    ) -> Option<Self> {
        match cfg.driver {
            RivalDriverKind::PurePursuit => Some(Self::PurePursuit(PurePursuit::rival(
                cfg,
                gains,
                ctx,
                cfg.wheelbase.unwrap_or_else(|| params.wheelbase()),
                cfg.max_steer.unwrap_or(params.s_max),
            ))),
            RivalDriverKind::FollowTheGap => {
                Some(Self::FollowTheGap(Box::new(FollowTheGap::rival(
                    &cfg.follow_the_gap,
                    gains,
                    ctx,
                    cfg.max_steer.unwrap_or(params.s_max),
                    params.width,
                ))))
            }
            RivalDriverKind::Policy => None,
        }
    }

    /// Starts a new episode for a driver that keeps itself across episodes (a trained agent:
    /// see [`PolicyRival::restart`]); scripted drivers are built anew instead. Returns whether it
    /// did.
    pub fn restart(&mut self, gains: ContextGains, ctx: Context, seed: u64, index: usize) -> bool {
        match self {
            Self::Policy(p) => {
                p.restart(gains, ctx, seed, index);
                true
            }
            Self::PurePursuit(_) | Self::FollowTheGap(_) => false,
        }
    }

    /// Which driver it is.
    pub fn kind(&self) -> RivalDriverKind {
        match self {
            Self::PurePursuit(_) => RivalDriverKind::PurePursuit,
            Self::FollowTheGap(_) => RivalDriverKind::FollowTheGap,
            Self::Policy(_) => RivalDriverKind::Policy,
        }
    }

    /// Whether it looks at the other cars (then [`RivalDriver::command`] needs their boxes).
    pub fn sees_cars(&self) -> bool {
        self.kind().sees_cars()
    }

    /// The command `(steering angle, speed)` for a car in state `x` on `track` among the other
    /// cars `others` (its own box excluded; a pure-pursuit driver ignores them).
    pub fn command(&mut self, track: &Track, others: &[CarBox], x: &State) -> (f64, f64) {
        match self {
            Self::PurePursuit(pp) => pp.command(&track.raceline, x),
            Self::FollowTheGap(gap) => gap.command(&track.walls, others, x),
            Self::Policy(p) => p.command(&track.walls, others, x),
        }
    }

    /// A trained agent's error in a decision since the last call (its car stopped for it).
    pub fn take_error(&mut self) -> Option<RivalAgentError> {
        match self {
            Self::Policy(p) => p.take_error(),
            Self::PurePursuit(_) | Self::FollowTheGap(_) => None,
        }
    }
}

/// A pure-pursuit driver following a raceline.
#[derive(Clone, Debug)]
pub struct PurePursuit {
    /// Target search distance at standstill, context scale included unless `steer_distance`
    /// is set (m).
    base: f64,
    /// Growth of the search distance with speed, scaled like `base` (s).
    gain: f64,
    /// A fixed steering-law distance `L_d` (context scale included), else the search distance.
    steer_distance: Option<f64>,
    /// Snap the target back to the raceline vertex starting its segment.
    target_at_vertex: bool,
    /// Where the raceline speed is read.
    speed_point: SpeedPoint,
    /// Below `launch.0` m/s, drive straight at `launch.1` m/s.
    launch: Option<(f64, f64)>,
    /// Multiplier on the capped raceline speed.
    speed_scale: f64,
    /// With `speed_scale > 1`: farther off the line than this (m), drive at the line's speed;
    /// 0 never.
    lift_off_line: f64,
    /// Cap on the raceline speed before scaling.
    speed_cap: f64,
    wheelbase: f64,
    max_steer: f64,
    /// Raceline segment of the last projection.
    hint: Option<usize>,
}

impl PurePursuit {
    /// A rival driver for the given context.
    pub fn rival(
        cfg: &RivalConfig,
        gains: ContextGains,
        ctx: Context,
        wheelbase: f64,
        max_steer: f64,
    ) -> Self {
        let scale = 1.0 + gains.lambda_theta * ctx.steer;
        let search_scale = if cfg.steer_lookahead.is_some() {
            1.0
        } else {
            scale
        };
        Self {
            base: cfg.lookahead * search_scale,
            gain: cfg.lookahead_gain * search_scale,
            steer_distance: cfg.steer_lookahead.map(|l| l * scale),
            speed_scale: cfg.speed_factor * (1.0 + gains.lambda_v * ctx.speed),
            ..Self::full_speed(cfg, cfg.max_speed, wheelbase, max_steer)
        }
    }

    /// A driver at the full raceline speed (capped at `speed_cap`) with context-free lookahead, the
    /// pure-pursuit reference policy for the ego.
    pub fn full_speed(cfg: &RivalConfig, speed_cap: f64, wheelbase: f64, max_steer: f64) -> Self {
        Self {
            base: cfg.lookahead,
            gain: cfg.lookahead_gain,
            steer_distance: cfg.steer_lookahead,
            target_at_vertex: cfg.target_at_vertex,
            speed_point: cfg.speed_point,
            launch: (cfg.launch_below > 0.0).then_some((cfg.launch_below, cfg.launch_speed)),
            speed_scale: 1.0,
            lift_off_line: cfg.lift_off_line,
            speed_cap,
            wheelbase,
            max_steer,
            hint: None,
        }
    }

    /// The command `(steering angle, speed)` for a car in state `x`.
    pub fn command(&mut self, raceline: &Raceline, x: &State) -> (f64, f64) {
        let v = x[idx::V];
        if let Some((below, speed)) = self.launch {
            if v < below {
                return (0.0, speed);
            }
        }
        let pos = Point2::new(x[idx::X], x[idx::Y]);
        let curve = &raceline.curve;
        let proj = match self.hint {
            Some(h) => curve.project_near(&pos, h),
            None => curve.project(&pos),
        };
        self.hint = Some(proj.segment);
        let radius = self.base + self.gain * v.max(0.0);
        let cut = first_point_at_distance(raceline, &pos, proj.segment, proj.s, radius);
        let target = if self.target_at_vertex {
            curve.points()[cut.segment]
        } else {
            cut.point
        };
        let (sin, cos) = x[idx::YAW].sin_cos();
        let d = target - pos;
        let y = -sin * d.x + cos * d.y;
        let ld = self.steer_distance.unwrap_or(radius);
        let steer = (2.0 * self.wheelbase * y / (ld * ld))
            .atan()
            .clamp(-self.max_steer, self.max_steer);
        let line_speed = match self.speed_point {
            SpeedPoint::Nearest => raceline.speed[proj.segment],
            SpeedPoint::Target => raceline.speed_at(cut.s),
            SpeedPoint::SlowestAhead => slowest_between(raceline, proj.s, cut.s),
        };
        let lifted = self.lift_off_line > 0.0 && proj.lateral.abs() > self.lift_off_line;
        let scale = if lifted {
            self.speed_scale.min(1.0)
        } else {
            self.speed_scale
        };
        (steer, line_speed.min(self.speed_cap) * scale)
    }
}

/// Where the search circle cuts the raceline.
struct Cut {
    point: Point2<f64>,
    /// Arc length of `point` along the raceline.
    s: f64,
    /// Segment holding `point`.
    segment: usize,
}

/// The first point of the raceline, going forward from the foot point at arc length `s_foot` on
/// segment `seg`, that lies at distance `radius` from `pos`; falls back to the point `radius` ahead
/// along the line when the circle does not reach it.
fn first_point_at_distance(
    raceline: &Raceline,
    pos: &Point2<f64>,
    seg: usize,
    s_foot: f64,
    radius: f64,
) -> Cut {
    let curve = &raceline.curve;
    let n = curve.len();
    let pts = curve.points();
    let mut t_min = {
        let len = curve.segment_vector(seg).norm();
        ((s_foot - curve.s_at_vertex(seg)) / len).clamp(0.0, 1.0)
    };
    let mut walked = 0.0;
    // never more than a lap and a half: a wider circle meets the line nowhere further on
    let limit = (2.0 * radius + 2.0).min(1.5 * curve.length());
    let mut i = seg;
    while walked < limit {
        let a = pts[i];
        let d = curve.segment_vector(i);
        // |a + t d − p|² = r²  →  (d·d) t² + 2 d·(a − p) t + |a − p|² − r² = 0
        let f = a - pos;
        let qa = d.norm_squared();
        let qb = 2.0 * d.dot(&f);
        let qc = f.norm_squared() - radius * radius;
        let disc = qb * qb - 4.0 * qa * qc;
        if disc >= 0.0 {
            let sq = disc.sqrt();
            for t in [(-qb - sq) / (2.0 * qa), (-qb + sq) / (2.0 * qa)] {
                if t >= t_min && t <= 1.0 {
                    let s = curve.s_at_vertex(i) + t * qa.sqrt();
                    return Cut {
                        point: a + d * t,
                        s: curve.wrap_s(s),
                        segment: i,
                    };
                }
            }
        }
        walked += qa.sqrt() * (1.0 - t_min);
        t_min = 0.0;
        i = (i + 1) % n;
    }
    let s = curve.wrap_s(s_foot + radius);
    Cut {
        point: curve.point_at(s),
        s,
        segment: curve.locate(s).0,
    }
}

/// The slowest raceline speed over the arc from `from` forward to `to` (both ends interpolated).
fn slowest_between(raceline: &Raceline, from: f64, to: f64) -> f64 {
    let curve = &raceline.curve;
    let n = curve.len();
    let (mut i, _) = curve.locate(from);
    let (last, _) = curve.locate(to);
    let mut slowest = raceline.speed_at(from).min(raceline.speed_at(to));
    // the vertices strictly after `from`'s segment start, up to `to`'s segment start
    for _ in 0..n {
        if i == last {
            break;
        }
        i = (i + 1) % n;
        slowest = slowest.min(raceline.speed[i]);
    }
    slowest
}

/// One rival's solo lap: where it drove and how fast.
#[derive(Clone, Debug, Default)]
pub struct SoloLap {
    /// Whether it came back round to its start.
    pub completed: bool,
    /// Centreline arc length where it touched a wall, if it did.
    pub wall_hit_at: Option<f64>,
    /// Lap time, or time driven until the wall hit or the time limit (s).
    pub time: f64,
    /// Per decision: centreline arc length travelled since the start, position and speed.
    pub samples: Vec<SoloSample>,
}

/// One decision of a [`SoloLap`].
#[derive(Clone, Copy, Debug)]
pub struct SoloSample {
    /// Distance travelled along the centreline since the start (m).
    pub travelled: f64,
    /// Position.
    pub x: f64,
    /// Position.
    pub y: f64,
    /// Speed (m/s).
    pub speed: f64,
}

/// Drives one rival alone for a lap from grid distance `start_s` in `context`, exactly as in a
/// race (10 Hz planning, 100 Hz physics, the configured steering delay), checking the walls as
/// a race checks a rival's: at every physics step, or with `rival_contacts = "decision-end"` at
/// each decision's last. For the drivability check of the evaluation contexts and the rival
/// speed-profile and race-line figures. A rival that is a trained agent (`driver = "policy"`)
/// is read first: the error says why it could not be.
pub fn drive_solo_lap(
    track: &ctxrace_tracks::Track,
    cfg: &ctxrace_config::RaceConfig,
    context: Context,
    start_s: f64,
) -> Result<SoloLap, RivalAgentError> {
    use crate::vehicle::{Vehicle, DT};
    let params = VehicleParams::default();
    let centre = &track.centreline.curve;
    let (p0, yaw) = crate::grid::grid_pose(track, cfg.grid_line, start_s);
    let mut car = Vehicle::new(params.clone(), p0.x, p0.y, yaw, cfg.steer_delay)
        .with_integrator(cfg.integrator);
    let gains = cfg.rival.gains_for(&track.name);
    let mut driver = match RivalDriver::scripted(&cfg.rival, gains, context, &params) {
        Some(scripted) => scripted,
        None => {
            let agent = RivalAgent::load(cfg.rival.policy.as_deref().unwrap_or(Path::new("")))?;
            let mut policy = RivalDriver::Policy(Box::new(PolicyRival::new(&agent, cfg)?));
            policy.restart(gains, context, 0, 0);
            policy
        }
    };
    let length = centre.length();
    let (mut s, mut hint, mut travelled) = (centre.wrap_s(start_s), centre.locate(start_s).0, 0.0);
    let mut lap = SoloLap::default();
    let decision_time = cfg.physics_steps_per_action as f64 * DT;
    let max_decisions = (cfg.max_time.max(4.0 * length) / decision_time).ceil() as usize;
    let steps = cfg.physics_steps_per_action;
    let every_step = cfg.rival_contacts == RivalContacts::PerStep;
    for k in 0..max_decisions {
        let (steer, speed) = driver.command(track, &[], &car.state);
        for j in 0..steps {
            let p = car.position();
            car.step(steer, speed);
            let from = nalgebra::Point2::new(p.x as f32, p.y as f32);
            let now = car.position();
            if (every_step || j + 1 == steps)
                && CarBox::new(&car.state, &params).hits_wall_by(
                    cfg.wall_contact,
                    from,
                    &now,
                    track,
                )
            {
                lap.wall_hit_at = Some(centre.project_near(&car.position(), hint).s);
                lap.time = (k + 1) as f64 * decision_time;
                return Ok(lap);
            }
        }
        let proj = centre.project_near(&car.position(), hint);
        let mut ds = proj.s - s;
        if ds > length / 2.0 {
            ds -= length;
        } else if ds < -length / 2.0 {
            ds += length;
        }
        travelled += ds;
        (s, hint) = (proj.s, proj.segment);
        lap.time = (k + 1) as f64 * decision_time;
        lap.samples.push(SoloSample {
            travelled,
            x: car.state[idx::X],
            y: car.state[idx::Y],
            speed: car.speed(),
        });
        if travelled >= length {
            lap.completed = true;
            return Ok(lap);
        }
    }
    Ok(lap)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_tracks::{Track, TrackOptions};

    /// The speed a rival in `context` commands standing `offset` m left of the raceline at arc
    /// length `s`, facing along it, at 5 m/s.
    fn speed_command(
        track: &Track,
        cfg: &RivalConfig,
        context: Context,
        s: f64,
        offset: f64,
    ) -> f64 {
        let line = &track.raceline.curve;
        let (p, heading) = (line.point_at(s), line.heading_at(s));
        let mut x: State = [0.0; 7];
        x[idx::X] = p.x - heading.sin() * offset;
        x[idx::Y] = p.y + heading.cos() * offset;
        x[idx::YAW] = heading;
        x[idx::V] = 5.0;
        PurePursuit::rival(cfg, cfg.gains, context, 0.33, 0.4189)
            .command(&track.raceline, &x)
            .1
    }

    #[test]
    fn a_rival_faster_than_its_line_lifts_to_the_line_speed_when_it_runs_wide() {
        let track = Track::load("generated:0", &TrackOptions::default()).unwrap();
        let lift = RivalConfig::default();
        assert_eq!(lift.lift_off_line, 0.15);
        let never = RivalConfig {
            lift_off_line: 0.0,
            ..RivalConfig::default()
        };
        let fast = Context {
            speed: 0.3,
            steer: 0.0,
        };
        let scale = lift.speed_factor * (1.0 + fast.speed);
        for s in [5.0, 20.0, 40.0, 60.0] {
            // 0.3 m wide: the lifted rival drives the line's speed, the other 1.105 times it
            let (lifted, pushed) = (
                speed_command(&track, &lift, fast, s, 0.3),
                speed_command(&track, &never, fast, s, 0.3),
            );
            assert!(
                (lifted * scale - pushed).abs() < 1e-9,
                "s {s}: {lifted} {pushed}"
            );
            // on the line, and at any offset for a rival no faster than its line, nothing changes
            for (context, offset) in [(fast, 0.1), (fast, -0.1), (Context::default(), 0.3)] {
                let a = speed_command(&track, &lift, context, s, offset);
                let b = speed_command(&track, &never, context, s, offset);
                assert_eq!(a, b, "s {s}, {context:?}, offset {offset}");
            }
        }
    }
}
