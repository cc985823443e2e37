//! The single-track vehicle model of f1tenth_gym (CommonRoad ST), integrated with RK4.
//!
//! State `x = [s_x, s_y, δ, v, ψ, ψ̇, β]`, input `u = [δ̇, a]`. Below `|v| < 0.5` m/s the kinematic
//! model is used:
//! `ẋ = v cos ψ, ẏ = v sin ψ, δ̇ = u₀, v̇ = u₁, ψ̇ = v tan δ / L, ψ̈ = u₁ tan δ / L + v u₀ / (L cos² δ), β̇ = 0`.
//! Above it, with `F_f = g l_r − a h`, `F_r = g l_f + a h`:
//! - `ẋ = v cos(ψ+β)`, `ẏ = v sin(ψ+β)`, `δ̇ = u₀`, `v̇ = u₁`, `ψ̇ = ψ̇`
//! - `ψ̈ = μ m/(I L) [l_f C_Sf F_f δ + (l_r C_Sr F_r − l_f C_Sf F_f) β − (l_f² C_Sf F_f + l_r² C_Sr F_r) ψ̇ / v]`
//! - `β̇ = μ/(v L) [C_Sf F_f δ − (C_Sr F_r + C_Sf F_f) β + (C_Sr F_r l_r − C_Sf F_f l_f) ψ̇ / v] − ψ̇`
//!
//! The input constraints (steering-rate and steering-angle limits, the power-limited acceleration
//! `a ≤ a_max v_switch / v` above `v_switch`, speed limits) are applied at every RK4 stage, and the
//! desired `(δ, v)` command becomes `u` through f1tenth_gym's bang-bang steering and proportional
//! speed controller ([`command_to_input`]).

use ctxrace_config::Integrator;
use serde::{Deserialize, Serialize};

/// Gravity (m/s²).
const G: f64 = 9.81;
/// Below this speed the kinematic model is used (m/s).
const KINEMATIC_BELOW: f64 = 0.5;

/// Vehicle parameters; the defaults are f1tenth_gym's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VehicleParams {
    /// Friction coefficient.
    pub mu: f64,
    /// Front cornering stiffness coefficient (1/rad).
    pub c_sf: f64,
    /// Rear cornering stiffness coefficient (1/rad).
    pub c_sr: f64,
    /// Centre of gravity to front axle (m).
    pub lf: f64,
    /// Centre of gravity to rear axle (m).
    pub lr: f64,
    /// Height of the centre of gravity (m).
    pub h: f64,
    /// Mass (kg).
    pub m: f64,
    /// Yaw moment of inertia (kg m²).
    pub i: f64,
    /// Minimum steering angle (rad).
    pub s_min: f64,
    /// Maximum steering angle (rad).
    pub s_max: f64,
    /// Minimum steering velocity (rad/s).
    pub sv_min: f64,
    /// Maximum steering velocity (rad/s).
    pub sv_max: f64,
    /// Speed above which acceleration is power limited (m/s).
    pub v_switch: f64,
    /// Maximum acceleration (m/s²).
    pub a_max: f64,
    /// Minimum speed (m/s).
    pub v_min: f64,
    /// Maximum speed (m/s).
    pub v_max: f64,
    /// Car width (m).
    pub width: f64,
    /// Car length (m).
    pub length: f64,
}

impl Default for VehicleParams {
    fn default() -> Self {
        Self {
            mu: 1.0489,
            c_sf: 4.718,
            c_sr: 5.4562,
            lf: 0.15875,
            lr: 0.17145,
            h: 0.074,
            m: 3.74,
            i: 0.04712,
            s_min: -0.4189,
            s_max: 0.4189,
            sv_min: -3.2,
            sv_max: 3.2,
            v_switch: 7.319,
            a_max: 9.51,
            v_min: -5.0,
            v_max: 20.0,
            width: 0.31,
            length: 0.58,
        }
    }
}

impl VehicleParams {
    /// Wheelbase `L = l_f + l_r`.
    pub fn wheelbase(&self) -> f64 {
        self.lf + self.lr
    }
}

/// The 7-element state `[s_x, s_y, δ, v, ψ, ψ̇, β]`.
pub type State = [f64; 7];

/// Index of each state element.
pub mod idx {
    /// x position.
    pub const X: usize = 0;
    /// y position.
    pub const Y: usize = 1;
    /// Steering angle δ.
    pub const STEER: usize = 2;
    /// Speed v.
    pub const V: usize = 3;
    /// Yaw ψ.
    pub const YAW: usize = 4;
    /// Yaw rate ψ̇.
    pub const YAW_RATE: usize = 5;
    /// Slip angle β.
    pub const BETA: usize = 6;
}

/// Steering-rate constraint: zero at the angle limits, else clipped to the rate limits.
#[inline]
fn steering_constraint(delta: f64, sv: f64, p: &VehicleParams) -> f64 {
    if (delta <= p.s_min && sv <= 0.0) || (delta >= p.s_max && sv >= 0.0) {
        0.0
    } else {
        sv.clamp(p.sv_min, p.sv_max)
    }
}

/// Acceleration constraint: power limited above `v_switch`, zero at the speed limits.
#[inline]
fn accel_constraint(v: f64, a: f64, p: &VehicleParams) -> f64 {
    let pos_limit = if v > p.v_switch {
        p.a_max * p.v_switch / v
    } else {
        p.a_max
    };
    if (v <= p.v_min && a <= 0.0) || (v >= p.v_max && a >= 0.0) {
        0.0
    } else {
        a.clamp(-p.a_max, pos_limit)
    }
}

/// The state derivative `f(x, u)` with the input constraints applied.
pub fn dynamics(x: &State, u: [f64; 2], p: &VehicleParams) -> State {
    let [_, _, delta, v, yaw, yaw_rate, beta] = *x;
    let sv = steering_constraint(delta, u[0], p);
    let a = accel_constraint(v, u[1], p);
    let l = p.wheelbase();
    if v.abs() < KINEMATIC_BELOW {
        let (s, c) = yaw.sin_cos();
        let tan_d = delta.tan();
        let cos_d = delta.cos();
        return [
            v * c,
            v * s,
            sv,
            a,
            v / l * tan_d,
            a / l * tan_d + v / (l * cos_d * cos_d) * sv,
            0.0,
        ];
    }
    let ff = G * p.lr - a * p.h;
    let fr = G * p.lf + a * p.h;
    let (s, c) = (yaw + beta).sin_cos();
    let yaw_acc = p.mu * p.m / (p.i * l)
        * (p.lf * p.c_sf * ff * delta + (p.lr * p.c_sr * fr - p.lf * p.c_sf * ff) * beta
            - (p.lf * p.lf * p.c_sf * ff + p.lr * p.lr * p.c_sr * fr) * yaw_rate / v);
    let beta_dot = p.mu / (v * l)
        * (p.c_sf * ff * delta - (p.c_sr * fr + p.c_sf * ff) * beta
            + (p.c_sr * fr * p.lr - p.c_sf * ff * p.lf) * yaw_rate / v)
        - yaw_rate;
    [v * c, v * s, sv, a, yaw_rate, yaw_acc, beta_dot]
}

/// f1tenth_gym's controller from a desired steering angle and speed to `u = [δ̇, a]`: bang-bang
/// steering at the rate limit, and `a = k_p (v_des − v)` with a gain that depends on the direction.
pub fn command_to_input(steer: f64, speed: f64, x: &State, p: &VehicleParams) -> [f64; 2] {
    let steer_diff = steer - x[idx::STEER];
    let sv = if steer_diff.abs() > 1e-4 {
        steer_diff.signum() * p.sv_max
    } else {
        0.0
    };
    let v = x[idx::V];
    let vel_diff = speed - v;
    let scale = if v > 0.0 { 10.0 } else { 2.0 };
    let kp = if vel_diff > 0.0 {
        scale * p.a_max / p.v_max
    } else {
        scale * p.a_max / (-p.v_min)
    };
    [sv, kp * vel_diff]
}

/// One classical RK4 step of length `dt` with a constant input.
pub fn rk4(x: &State, u: [f64; 2], dt: f64, p: &VehicleParams) -> State {
    let add = |a: &State, k: &State, h: f64| -> State { std::array::from_fn(|i| a[i] + h * k[i]) };
    let k1 = dynamics(x, u, p);
    let k2 = dynamics(&add(x, &k1, dt / 2.0), u, p);
    let k3 = dynamics(&add(x, &k2, dt / 2.0), u, p);
    let k4 = dynamics(&add(x, &k3, dt), u, p);
    std::array::from_fn(|i| x[i] + dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]))
}

/// One explicit Euler step of length `dt` with a constant input, `x + f(x, u) dt` (the
/// f1tenth_gym copy in the paper's code integrates so).
pub fn euler(x: &State, u: [f64; 2], dt: f64, p: &VehicleParams) -> State {
    let f = dynamics(x, u, p);
    std::array::from_fn(|i| x[i] + dt * f[i])
}

/// A car: its state, parameters and steering-delay line.
#[derive(Clone, Debug)]
pub struct Vehicle {
    /// The current state.
    pub state: State,
    /// The parameters.
    pub params: VehicleParams,
    /// How a physics step is integrated.
    pub integrator: Integrator,
    /// Delayed steering commands, oldest first (capacity = the delay in steps).
    steer_queue: std::collections::VecDeque<f64>,
    delay: usize,
}

/// Physics time step (s).
pub const DT: f64 = ctxrace_config::config::PHYSICS_DT;

impl Vehicle {
    /// A car at rest at `(x, y)` facing `yaw`, whose steering commands take effect `delay` steps late
    /// (the car steers straight until the first command arrives, as in f1tenth_gym).
    pub fn new(params: VehicleParams, x: f64, y: f64, yaw: f64, delay: usize) -> Self {
        let mut state = [0.0; 7];
        state[idx::X] = x;
        state[idx::Y] = y;
        state[idx::YAW] = yaw;
        Self {
            state,
            params,
            integrator: Integrator::Rk4,
            steer_queue: std::collections::VecDeque::with_capacity(delay + 1),
            delay,
        }
    }

    /// The same car integrated with `integrator`.
    pub fn with_integrator(self, integrator: Integrator) -> Self {
        Self { integrator, ..self }
    }

    /// Advances one physics step under the command (desired steering angle, desired speed).
    pub fn step(&mut self, steer: f64, speed: f64) {
        self.steer_queue.push_back(steer);
        let applied = if self.steer_queue.len() > self.delay {
            self.steer_queue.pop_front().unwrap_or(0.0)
        } else {
            0.0
        };
        let u = command_to_input(applied, speed, &self.state, &self.params);
        self.state = match self.integrator {
            Integrator::Rk4 => rk4(&self.state, u, DT, &self.params),
            Integrator::Euler => euler(&self.state, u, DT, &self.params),
        };
        // keep yaw in [0, 2π) as f1tenth_gym does
        let yaw = &mut self.state[idx::YAW];
        if *yaw > std::f64::consts::TAU {
            *yaw -= std::f64::consts::TAU;
        } else if *yaw < 0.0 {
            *yaw += std::f64::consts::TAU;
        }
    }

    /// Stops the car where it is (a crashed car stays as an obstacle).
    pub fn stop(&mut self) {
        for i in [idx::V, idx::YAW_RATE, idx::BETA] {
            self.state[i] = 0.0;
        }
    }

    /// Position `(x, y)`.
    pub fn position(&self) -> nalgebra::Point2<f64> {
        nalgebra::Point2::new(self.state[idx::X], self.state[idx::Y])
    }

    /// Yaw ψ.
    pub fn yaw(&self) -> f64 {
        self.state[idx::YAW]
    }

    /// Speed v.
    pub fn speed(&self) -> f64 {
        self.state[idx::V]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// CommonRoad full-size parameters of f1tenth_gym's DynamicsTest (REFERENCE §8).
    fn commonroad() -> VehicleParams {
        VehicleParams {
            mu: 1.0489,
            c_sf: 21.92 / 1.0489,
            c_sr: 21.92 / 1.0489,
            lf: 0.3048 * 3.793293,
            lr: 0.3048 * 4.667707,
            h: 0.3048 * 2.01355,
            m: 4.4482216152605 / 0.3048 * 74.91452,
            i: 4.4482216152605 * 0.3048 * 1321.416,
            s_min: -1.066,
            s_max: 1.066,
            sv_min: -0.4,
            sv_max: 0.4,
            v_switch: 7.319,
            a_max: 11.5,
            v_min: -13.6,
            v_max: 50.8,
            ..Default::default()
        }
    }

    #[test]
    #[allow(clippy::excessive_precision)] // the reference digits, verbatim
    fn derivative_matches_the_reference_vector() {
        let x = [
            2.0233348142065677,
            0.0041907137716636,
            0.0197545248559617,
            15.7216236334290116,
            0.0025857914776859,
            0.0529001056654038,
            0.0033012170610298,
        ];
        let expected = [
            15.7213512030862397,
            0.0925527979719355,
            0.15,
            5.3536773276413925,
            0.0529001056654038,
            0.6435589397748606,
            0.0313297971641291,
        ];
        let f = dynamics(&x, [0.15, 0.63 * 9.81], &commonroad());
        for i in 0..7 {
            assert!(
                (f[i] - expected[i]).abs() < 1e-9,
                "f[{i}] = {} vs {}",
                f[i],
                expected[i]
            );
        }
    }

    /// The reference was integrated with an adaptive solver; the full-size car is stiff at low
    /// speed, so RK4 needs a step well below 0.01 s to match it.
    #[test]
    fn one_second_from_rest_matches_the_reference() {
        let p = commonroad();
        let mut x = [0.0; 7];
        for _ in 0..10_000 {
            x = rk4(&x, [0.15, 0.63 * 9.81], 1e-4, &p);
        }
        let expected = [3.0732, 0.2870, 0.15, 6.1803, 0.1098, 0.3248, 0.0698];
        for i in 0..7 {
            assert!(
                (x[i] - expected[i]).abs() < 1.5e-4,
                "x = {x:?} vs {expected:?}"
            );
        }
    }

    #[test]
    fn steering_and_speed_limits_hold() {
        let p = VehicleParams::default();
        let mut car = Vehicle::new(p.clone(), 0.0, 0.0, 0.0, 0);
        for _ in 0..500 {
            car.step(1.0, 100.0);
            assert!(car.state[idx::STEER] <= p.s_max + 0.033);
            // the limit holds at every RK4 stage, so a step can end at most one stage past it
            assert!(car.state[idx::V] <= p.v_max + p.a_max * DT);
        }
    }

    #[test]
    fn steering_delay_holds_commands_back() {
        let p = VehicleParams::default();
        let mut car = Vehicle::new(p, 0.0, 0.0, 0.0, 2);
        car.step(0.3, 0.0);
        car.step(0.3, 0.0);
        assert_eq!(car.state[idx::STEER], 0.0);
        car.step(0.3, 0.0);
        assert!((car.state[idx::STEER] - 0.032).abs() < 1e-12);
    }
}
