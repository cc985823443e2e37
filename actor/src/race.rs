//! A head-to-head race (paper §III–IV): the ego against 0–7 rivals for one lap.
//!
//! All cars start in a line on the centreline, ego last at arc length 0 (the start/finish line),
//! rival `i` at `i · gap · L` ahead. Every decision (10 physics steps of 0.01 s) the ego acts with
//! `a ∈ [-1, 1]²` — steering `δ = −a₀ θ_max` (negative `a₀` turns left, as the paper states) and speed
//! `v = v_min + (a₁ + 1)/2 · (v_max − v_min)` — and each rival plans with pure pursuit.
//!
//! Reward (Jaritz et al.): `r = v / v_max · cos φ − d_c`, `φ` the heading error to the centreline and
//! `d_c` the distance to it; plus `−1` on a crash, `+1` on completing the lap, and per decision the
//! change of the ego's rank by track progress (`+1` per rival passed, `−1` per time passed).
//! The episode ends when the ego completes the lap, hits a wall, or collides with a rival
//! (terminated), or at the time limit (truncated). A rival that crashes stops and stays as an
//! obstacle.
//!
//! Metrics: PG, the largest fraction of the lap the ego completed; OT, the sum of the rank changes;
//! A2A, whether the episode ended in an ego–rival collision.

use crate::collision::CarBox;
use crate::lidar::{Lidar, NearbyWalls};
use crate::rival::PurePursuit;
use crate::vehicle::{State, Vehicle, VehicleParams, DT};
use ctxrace_common::{Context, RaceConfig};
use ctxrace_tracks::{Projection, Track};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::sync::Arc;

/// Errors of the race environment.
#[derive(Debug, thiserror::Error)]
pub enum RaceError {
    /// The race config is invalid.
    #[error("race config: {0}")]
    Config(String),
    /// An action element is NaN or infinite.
    #[error("action {0:?} is not finite; policies must output numbers in [-1, 1]")]
    BadAction([f64; 2]),
    /// `step` was called before `reset` or after the episode ended.
    #[error("step called on a finished episode; call reset first")]
    Finished,
}

/// One car of the race and its progress along the centreline.
#[derive(Clone, Debug)]
pub struct Car {
    /// The vehicle.
    pub vehicle: Vehicle,
    /// Whether it crashed (it then stays where it stopped).
    pub crashed: bool,
    /// Arc length travelled along the centreline from the start/finish line (m), unwrapped:
    /// rivals start ahead with positive values.
    pub travelled: f64,
    /// Centreline arc length at the last update.
    s: f64,
    /// Centreline segment at the last update.
    hint: usize,
}

/// What happened in one decision step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StepInfo {
    /// Ego progress this episode so far, `[0, 1]`.
    pub progress: f64,
    /// Change in the ego's rank this step (+ passes, − being passed).
    pub overtakes: i32,
    /// The ego hit a wall.
    pub wall_crash: bool,
    /// The ego collided with a rival.
    pub a2a: bool,
    /// The ego completed the lap.
    pub lap_complete: bool,
    /// Episode time (s).
    pub time: f64,
}

/// The result of one decision step.
#[derive(Clone, Debug)]
pub struct Step {
    /// The ego's LiDAR observation, `beams` values in `[0, 1]`.
    pub obs: Vec<f32>,
    /// The reward.
    pub reward: f64,
    /// The episode ended (lap, crash or collision).
    pub terminated: bool,
    /// The episode hit the time limit.
    pub truncated: bool,
    /// Details.
    pub info: StepInfo,
}

/// Per-episode metrics.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct EpisodeMetrics {
    /// PG: largest fraction of the lap completed.
    pub progress: f64,
    /// OT: overtakes minus times overtaken.
    pub overtakes: i32,
    /// A2A: the episode ended in an ego–rival collision.
    pub a2a: bool,
    /// The episode ended with the ego hitting a wall.
    pub wall_crash: bool,
    /// Lap time when the lap was completed (s).
    pub lap_time: Option<f64>,
    /// Decisions taken.
    pub steps: usize,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Rivals that crashed during the episode.
    pub rivals_crashed: usize,
}

/// The race environment.
pub struct RaceEnv {
    track: Arc<Track>,
    cfg: RaceConfig,
    params: VehicleParams,
    lidar: Lidar,
    nearby: NearbyWalls,
    cars: Vec<Car>,
    drivers: Vec<PurePursuit>,
    rng: ChaCha8Rng,
    context: Context,
    steps: usize,
    max_steps: usize,
    rank: usize,
    boxes: Vec<CarBox>,
    metrics: EpisodeMetrics,
    finished: bool,
}

impl RaceEnv {
    /// An environment on `track`; call [`RaceEnv::reset`] before stepping.
    pub fn new(track: Arc<Track>, cfg: RaceConfig) -> Result<Self, RaceError> {
        cfg.validate().map_err(RaceError::Config)?;
        let params = VehicleParams::default();
        let steps_per_decision = cfg.physics_steps_per_action as f64 * DT;
        Ok(Self {
            lidar: Lidar::new(&cfg.lidar),
            nearby: NearbyWalls::default(),
            max_steps: (cfg.max_time / steps_per_decision).ceil() as usize,
            track,
            params,
            cars: Vec::new(),
            drivers: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(0),
            context: Context::default(),
            steps: 0,
            rank: 0,
            boxes: Vec::new(),
            metrics: EpisodeMetrics::default(),
            finished: true,
            cfg,
        })
    }

    /// Starts an episode: cars on the grid, rivals driving in `context`, noise seeded by `seed`.
    /// Returns the first observation.
    pub fn reset(&mut self, seed: u64, context: Context) -> Vec<f32> {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.context = context;
        let gains = self.cfg.rival.gains_for(&self.track.name);
        let centre = &self.track.centreline.curve;
        let length = centre.length();
        self.cars = (0..=self.cfg.rivals)
            .map(|i| {
                let s = i as f64 * self.cfg.start_gap * length;
                let p = centre.point_at(s);
                let (seg, _) = centre.locate(s);
                Car {
                    vehicle: Vehicle::new(
                        self.params.clone(),
                        p.x,
                        p.y,
                        centre.heading_at(s),
                        self.cfg.steer_delay,
                    ),
                    crashed: false,
                    travelled: s,
                    s,
                    hint: seg,
                }
            })
            .collect();
        let wheelbase = self.params.wheelbase();
        self.drivers = (0..self.cfg.rivals)
            .map(|_| {
                PurePursuit::rival(
                    &self.cfg.rival,
                    gains,
                    context,
                    wheelbase,
                    self.params.s_max,
                )
            })
            .collect();
        self.steps = 0;
        self.rank = self.ego_rank();
        self.metrics = EpisodeMetrics::default();
        self.finished = false;
        self.observe()
    }

    /// Advances one decision with the ego action `a ∈ [-1, 1]²` (clipped).
    pub fn step(&mut self, action: [f64; 2]) -> Result<Step, RaceError> {
        if self.finished {
            return Err(RaceError::Finished);
        }
        if !action.iter().all(|a| a.is_finite()) {
            return Err(RaceError::BadAction(action));
        }
        let (steer, speed) = self.action_to_command(action);
        let commands: Vec<(f64, f64)> = self
            .drivers
            .iter_mut()
            .zip(&self.cars[1..])
            .map(|(d, car)| {
                if car.crashed {
                    (0.0, 0.0)
                } else {
                    d.command(&self.track.raceline, &car.vehicle.state)
                }
            })
            .collect();
        let mut wall_crash = false;
        let mut a2a = false;
        for _ in 0..self.cfg.physics_steps_per_action {
            self.cars[0].vehicle.step(steer, speed);
            for (car, &(st, sp)) in self.cars[1..].iter_mut().zip(&commands) {
                if !car.crashed {
                    car.vehicle.step(st, sp);
                }
            }
            (wall_crash, a2a) = self.resolve_collisions();
            if wall_crash || a2a {
                break;
            }
        }
        self.steps += 1;
        let ego_proj = self.update_progress(0);
        for i in 1..self.cars.len() {
            self.update_progress(i);
        }
        let ego = &self.cars[0];
        let length = self.track.length();
        let lap_complete = ego.travelled >= length;
        let progress = (ego.travelled / length).clamp(0.0, 1.0);
        self.metrics.progress = self.metrics.progress.max(progress);
        let rank = self.ego_rank();
        let overtakes = self.rank as i32 - rank as i32;
        self.rank = rank;

        let heading_error = ego.vehicle.yaw() - ego_proj.heading;
        let mut reward = ego.vehicle.speed() / self.cfg.reward_speed * heading_error.cos()
            - ego_proj.lateral.abs()
            + overtakes as f64;
        if wall_crash || a2a {
            reward -= 1.0;
        }
        if lap_complete {
            reward += 1.0;
        }
        let time = self.steps as f64 * self.cfg.physics_steps_per_action as f64 * DT;
        let terminated = wall_crash || a2a || lap_complete;
        let truncated = !terminated && self.steps >= self.max_steps;
        self.finished = terminated || truncated;

        let m = &mut self.metrics;
        m.overtakes += overtakes;
        m.a2a |= a2a;
        m.wall_crash |= wall_crash;
        m.steps = self.steps;
        m.episode_return += reward;
        if lap_complete {
            m.progress = 1.0;
            m.lap_time = Some(time);
        }
        m.rivals_crashed = self.cars[1..].iter().filter(|c| c.crashed).count();
        Ok(Step {
            obs: self.observe(),
            reward,
            terminated,
            truncated,
            info: StepInfo {
                progress: self.metrics.progress,
                overtakes,
                wall_crash,
                a2a,
                lap_complete,
                time,
            },
        })
    }

    /// Maps an ego action to the command `(steering angle, speed)`.
    pub fn action_to_command(&self, action: [f64; 2]) -> (f64, f64) {
        let a0 = action[0].clamp(-1.0, 1.0);
        let a1 = action[1].clamp(-1.0, 1.0);
        let c = &self.cfg;
        (
            -a0 * c.max_steer,
            c.min_speed + (a1 + 1.0) / 2.0 * (c.max_speed - c.min_speed),
        )
    }

    /// Maps a command `(steering angle, speed)` back to the ego action (clipped to `[-1, 1]²`).
    pub fn command_to_action(&self, steer: f64, speed: f64) -> [f64; 2] {
        let c = &self.cfg;
        [
            (-steer / c.max_steer).clamp(-1.0, 1.0),
            (2.0 * (speed - c.min_speed) / (c.max_speed - c.min_speed) - 1.0).clamp(-1.0, 1.0),
        ]
    }

    /// Marks crashes for this physics step; returns (ego hit a wall, ego hit a rival).
    fn resolve_collisions(&mut self) -> (bool, bool) {
        self.boxes.clear();
        self.boxes.extend(
            self.cars
                .iter()
                .map(|c| CarBox::new(&c.vehicle.state, &self.params)),
        );
        let n = self.cars.len();
        let mut ego_wall = false;
        let mut ego_a2a = false;
        for i in 0..n {
            if self.cars[i].crashed {
                continue;
            }
            if self.boxes[i].hits_wall(&self.track.walls) {
                self.crash(i);
                ego_wall |= i == 0;
            }
        }
        for i in 0..n {
            for j in i + 1..n {
                if (self.cars[i].crashed && self.cars[j].crashed)
                    || !self.boxes[i].overlaps(&self.boxes[j])
                {
                    continue;
                }
                self.crash(i);
                self.crash(j);
                ego_a2a |= i == 0;
            }
        }
        (ego_wall, ego_a2a)
    }

    fn crash(&mut self, i: usize) {
        self.cars[i].crashed = true;
        self.cars[i].vehicle.stop();
    }

    /// Moves car `i`'s progress to its current position; returns its centreline projection.
    fn update_progress(&mut self, i: usize) -> Projection {
        let car = &mut self.cars[i];
        let proj = self.track.project(&car.vehicle.position(), Some(car.hint));
        let length = self.track.length();
        let mut ds = proj.s - car.s;
        if ds > length / 2.0 {
            ds -= length;
        } else if ds < -length / 2.0 {
            ds += length;
        }
        car.travelled += ds;
        car.s = proj.s;
        car.hint = proj.segment;
        proj
    }

    /// 1-based rank of the ego by distance travelled (ties favour the ego).
    fn ego_rank(&self) -> usize {
        let ego = self.cars[0].travelled;
        1 + self.cars[1..].iter().filter(|c| c.travelled > ego).count()
    }

    fn observe(&mut self) -> Vec<f32> {
        self.boxes.clear();
        self.boxes.extend(
            self.cars[1..]
                .iter()
                .map(|c| CarBox::new(&c.vehicle.state, &self.params)),
        );
        let ego = &self.cars[0].vehicle;
        let mut obs = vec![0.0f32; self.lidar.beams()];
        self.lidar.ranges(
            ego.position(),
            ego.yaw(),
            &mut self.nearby,
            &self.track.walls,
            &self.boxes,
            &mut obs,
        );
        self.lidar.normalise(&mut obs, &mut self.rng);
        obs
    }

    /// The cars, ego first.
    pub fn cars(&self) -> &[Car] {
        &self.cars
    }

    /// The ego's state.
    pub fn ego_state(&self) -> &State {
        &self.cars[0].vehicle.state
    }

    /// The track.
    pub fn track(&self) -> &Arc<Track> {
        &self.track
    }

    /// The config.
    pub fn config(&self) -> &RaceConfig {
        &self.cfg
    }

    /// The vehicle parameters of every car.
    pub fn vehicle_params(&self) -> &VehicleParams {
        &self.params
    }

    /// This episode's context.
    pub fn context(&self) -> Context {
        self.context
    }

    /// Metrics of the current (or just finished) episode.
    pub fn metrics(&self) -> &EpisodeMetrics {
        &self.metrics
    }

    /// Whether the episode has ended.
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Number of LiDAR beams in an observation.
    pub fn obs_dim(&self) -> usize {
        self.lidar.beams()
    }
}
