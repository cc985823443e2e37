//! A head-to-head race (paper §III–IV): the ego against 0–7 rivals for one lap.
//!
//! All cars start in a line, ego last at centreline arc length 0 (the start/finish line), rival
//! `i` at `i` grid spacings ahead (`start_grid`: a fixed distance, or a fraction of the lap), each
//! on the raceline beside its place (`grid_line`; the paper's code: on the map's x axis). Every
//! decision (10 physics steps of 0.01 s) the ego acts with
//! `a ∈ [-1, 1]²` — steering `δ = −a₀ θ_max` (negative `a₀` turns left, as the paper states) and speed
//! `v = v_min + (a₁ + 1)/2 · (v_max − v_min)` — and each rival plans from its own state with the
//! driver `[rival] driver` names ([`RivalDriver`]: pure pursuit, or follow-the-gap on its own
//! scan of the walls and the other cars).
//!
//! Reward: see [`reward`]. The episode ends when the ego completes the lap, hits a wall, collides
//! with a rival or (with `reverse_limit`) drives backwards (terminated), or at the time limit
//! (truncated, or terminated with `timeout_is_terminal`). A rival that crashes stops and stays as
//! an obstacle (with `crashed_rivals = "coast"` it brakes under a zero command instead); with
//! `rival_contacts = "decision-end"` only a rival's contacts at a decision's last physics step
//! crash it.
//!
//! Metrics: PG, the largest fraction of the lap the ego completed; OT, the sum of the rank changes;
//! A2A, whether the episode ended in an ego–rival collision. `crashed_rivals`,
//! `overtakes_last_step` and `progress_past_line` select the paper code's forms.

use crate::collision::CarBox;
use crate::grid::grid_pose;
use crate::lidar::{Lidar, NearbyWalls};
use crate::policy_rival::{PolicyRival, RivalAgent, RivalAgentError};
use crate::rival::RivalDriver;
use crate::vehicle::{State, Vehicle, VehicleParams, DT};
use ctxrace_config::{
    Context, CrashedRivals, RaceConfig, RaceConfigError, RivalContacts, RivalDriverKind,
};
use ctxrace_tracks::Track;
use nalgebra::Point2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::sync::Arc;

/// Errors of the race environment.
#[derive(Debug, thiserror::Error)]
pub enum RaceError {
    /// The race config is invalid.
    #[error("race config: {0}")]
    Config(RaceConfigError),
    /// An action element is NaN or infinite.
    #[error("action {0:?} is not finite; policies must output numbers in [-1, 1]")]
    BadAction([f64; 2]),
    /// `step` was called before `reset` or after the episode ended.
    #[error("step called on a finished episode; call reset first")]
    Finished,
    /// Actions for another number of cars than the race's agents.
    #[error(
        "{actions} action(s) for a race of {agents} agent(s): step takes the ego's action when \
         the ego is the only agent, step_agents one action per agent"
    )]
    Agents {
        /// The race's agents.
        agents: usize,
        /// The actions given.
        actions: usize,
    },
    /// More agents than cars, or none.
    #[error("agents = {agents} must be 1 to {cars} (the ego and its {rivals} rivals)", cars = .rivals + 1)]
    AgentCount {
        /// The agents asked for.
        agents: usize,
        /// The race's rivals.
        rivals: usize,
    },
    /// The rivals' trained agent (`[rival] driver = "policy"`) could not be read or could not
    /// act.
    #[error(transparent)]
    RivalAgent(Box<RivalAgentError>),
}

impl From<RivalAgentError> for RaceError {
    fn from(e: RivalAgentError) -> Self {
        Self::RivalAgent(Box::new(e))
    }
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
    /// The largest `travelled` reached.
    pub furthest: f64,
    /// It crashed into a wall.
    wall_hit: bool,
    /// It crashed into another car.
    car_hit: bool,
    /// An agent whose episode ended without a crash (it drove backwards or completed the lap).
    retired: bool,
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
    /// The ego drove backwards past `reverse_limit`.
    pub reversed: bool,
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
    /// The episode ended with the ego driving backwards (`reverse_limit`).
    pub reversed: bool,
    /// Lap time when the lap was completed (s).
    pub lap_time: Option<f64>,
    /// Decisions taken.
    pub steps: usize,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Rivals that crashed during the episode.
    pub rivals_crashed: usize,
    /// The car furthest along the track (by its unwrapped arc length from the start line) when
    /// the episode ended, ties to the lower index: 0 the ego, `k` the `k`-th rival from the back
    /// of the grid. The paper's repository recounts a lap's overtakes from it
    /// (`DataTools/ReviewTesting/redo_overtakes.py` at c0fd903: `cars − leader − 1`).
    pub leader: usize,
}

impl EpisodeMetrics {
    /// How the race ended, in words: lap complete, collision with a rival, wall crash, driving
    /// backwards, or the time limit.
    pub fn ended_by(&self) -> &'static str {
        if self.lap_time.is_some() {
            "lap complete"
        } else if self.a2a {
            "collision with a rival"
        } else if self.wall_crash {
            "wall crash"
        } else if self.reversed {
            "driving backwards"
        } else {
            "time limit"
        }
    }
}

/// The ego's reward for one decision (paper §III after Jaritz et al.; `cfg` selects how the
/// paper's code computed it): the step reward `r = v / v_max · cos φ − d_c`, with `v` the speed,
/// `v_max` = `reward_speed`, `φ` the heading error to the centreline and `d_c` the distance to it,
/// floored at `step_reward_floor` if set; `−1` for a crash and `+1` for the completed lap, added
/// to `r` or, with `terminal_rewards_replace_step`, instead of it; plus the change in the ego's
/// rank by track progress (`+1` per rival passed, `−1` per time passed).
pub fn reward(
    cfg: &RaceConfig,
    speed: f64,
    heading_error: f64,
    lateral: f64,
    crashed: bool,
    lap_complete: bool,
    overtakes: i32,
) -> f64 {
    let mut step = speed / cfg.reward_speed * heading_error.cos() - lateral.abs();
    if let Some(floor) = cfg.step_reward_floor {
        step = step.max(floor);
    }
    let replace = cfg.terminal_rewards_replace_step;
    let base = if replace && lap_complete {
        1.0
    } else if replace && crashed {
        -1.0
    } else {
        step + f64::from(u8::from(lap_complete)) - f64::from(u8::from(crashed))
    };
    base + f64::from(overtakes)
}

/// Most decisions the ego's launch (`ego_launch_below`) may take.
const MAX_LAUNCH_DECISIONS: usize = 20;

/// A car's centre in single precision, as the collision shapes hold it.
fn centre_f32(v: &Vehicle) -> Point2<f32> {
    let p = v.position();
    Point2::new(p.x as f32, p.y as f32)
}

mod agents;
pub use agents::AgentStep;

/// The race environment.
pub struct RaceEnv {
    track: Arc<Track>,
    cfg: RaceConfig,
    params: VehicleParams,
    lidar: Lidar,
    nearby: NearbyWalls,
    cars: Vec<Car>,
    drivers: Vec<RivalDriver>,
    /// The other cars' boxes as one rival's scan sees them.
    others: Vec<CarBox>,
    rng: ChaCha8Rng,
    context: Context,
    steps: usize,
    max_steps: usize,
    /// Cars driven from outside: the ego and the `agents - 1` rivals behind the others
    /// ([`RaceEnv::set_agents`]).
    agents: usize,
    /// Each agent's rank by distance travelled (1 the leader).
    ranks: Vec<usize>,
    boxes: Vec<CarBox>,
    /// Every car's centre before the current physics step (for the `centre` wall contact).
    centres: Vec<Point2<f32>>,
    metrics: EpisodeMetrics,
    finished: bool,
}

impl RaceEnv {
    /// An environment on `track`; call [`RaceEnv::reset`] before stepping. With `[rival]
    /// driver = "policy"` the rivals' agent is read here, once.
    pub fn new(track: Arc<Track>, cfg: RaceConfig) -> Result<Self, RaceError> {
        cfg.validate().map_err(RaceError::Config)?;
        cfg.validate_grid(&track.name, track.length())
            .map_err(RaceError::Config)?;
        let params = VehicleParams::default();
        let drivers = match (&cfg.rival.policy, cfg.rival.driver) {
            (Some(path), RivalDriverKind::Policy) => {
                let agent = RivalAgent::load(path)?;
                (0..cfg.rivals)
                    .map(|_| {
                        Ok(RivalDriver::Policy(Box::new(PolicyRival::new(
                            &agent, &cfg,
                        )?)))
                    })
                    .collect::<Result<_, RaceError>>()?
            }
            _ => Vec::new(),
        };
        Ok(Self {
            lidar: Lidar::new(&cfg.lidar),
            nearby: NearbyWalls::default(),
            max_steps: cfg.max_decisions(),
            track,
            params,
            cars: Vec::new(),
            drivers,
            others: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(0),
            context: Context::default(),
            steps: 0,
            agents: 1,
            ranks: Vec::new(),
            boxes: Vec::new(),
            centres: Vec::new(),
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
        let spacing = self.cfg.grid_spacing(&self.track.name, self.track.length());
        self.cars = (0..=self.cfg.rivals)
            .map(|i| {
                let s = i as f64 * spacing;
                let (p, yaw) = grid_pose(&self.track, self.cfg.grid_line, s);
                let (seg, _) = centre.locate(s);
                Car {
                    vehicle: Vehicle::new(self.params.clone(), p.x, p.y, yaw, self.cfg.steer_delay)
                        .with_integrator(self.cfg.integrator),
                    crashed: false,
                    wall_hit: false,
                    car_hit: false,
                    retired: false,
                    travelled: s,
                    furthest: s,
                    s,
                    hint: seg,
                }
            })
            .collect();
        let mut kept = 0;
        for (i, d) in self.drivers.iter_mut().enumerate() {
            kept += usize::from(d.restart(gains, context, seed, i));
        }
        if kept != self.cfg.rivals {
            self.drivers = (0..self.cfg.rivals)
                .filter_map(|_| {
                    RivalDriver::scripted(&self.cfg.rival, gains, context, &self.params)
                })
                .collect();
        }
        self.steps = 0;
        self.ranks = (0..self.agents).map(|i| self.rank_of(i)).collect();
        self.metrics = EpisodeMetrics::default();
        self.finished = false;
        self.launch();
        self.observe_car(0)
    }

    /// With `ego_launch_below`, drives the ego straight at `ego_launch_speed` (the rivals
    /// racing as usual) until it is that fast, as the paper's code did before its agents took
    /// over. From the back of the grid this takes about 0.1 s and cannot reach a rival.
    fn launch(&mut self) {
        self.launch_decisions();
        for i in 0..self.agents {
            self.ranks[i] = self.rank_of(i);
        }
    }

    /// The launch's decisions, while the ego is slower than `ego_launch_below` (at most
    /// [`MAX_LAUNCH_DECISIONS`], none past the time limit); returns (ego hit a wall, ego hit a
    /// rival) as [`RaceEnv::advance`].
    fn launch_decisions(&mut self) -> (bool, bool) {
        let below = self.cfg.ego_launch_below;
        // a stand-still start reaches 1 m/s in 1–2 decisions; the bound only guards odd configs
        for _ in 0..MAX_LAUNCH_DECISIONS {
            if below <= 0.0 || self.cars[0].vehicle.speed() >= below || self.steps >= self.max_steps
            {
                break;
            }
            let launch = vec![(0.0, self.cfg.ego_launch_speed); self.agents];
            let (wall_crash, a2a) = self.advance(&launch);
            if wall_crash || a2a {
                return (wall_crash, a2a);
            }
        }
        (false, false)
    }

    /// One decision of physics: the rivals plan, then every car drives `physics_steps_per_action`
    /// steps (agent `i` under the command `commands[i]`, `(steer, speed)`) until every agent
    /// has crashed; then every car's progress is updated. Returns (ego hit a wall, ego hit a
    /// rival) at the last physics step.
    fn advance(&mut self, commands: &[(f64, f64)]) -> (bool, bool) {
        if self.drivers.iter().any(RivalDriver::sees_cars) {
            self.boxes.clear();
            self.boxes.extend(
                self.cars
                    .iter()
                    .map(|c| CarBox::new(&c.vehicle.state, &self.params)),
            );
        }
        let mut planned = Vec::with_capacity(self.drivers.len());
        for (i, (d, car)) in self.drivers.iter_mut().zip(&self.cars[1..]).enumerate() {
            if car.crashed || i + 1 < self.agents {
                planned.push((0.0, 0.0));
                continue;
            }
            self.others.clear();
            if d.sees_cars() {
                // every car but this rival (index i + 1), the ego and crashed ones included
                let boxes = self.boxes.iter().enumerate();
                self.others
                    .extend(boxes.filter(|&(j, _)| j != i + 1).map(|(_, b)| *b));
            }
            planned.push(d.command(&self.track, &self.others, &car.vehicle.state));
        }
        let mut wall_crash = false;
        let mut a2a = false;
        let steps = self.cfg.physics_steps_per_action;
        let rivals_every_step = self.cfg.rival_contacts == RivalContacts::PerStep;
        for k in 0..steps {
            self.centres.clear();
            self.centres
                .extend(self.cars.iter().map(|c| centre_f32(&c.vehicle)));
            for (car, &(st, sp)) in self.cars.iter_mut().zip(commands) {
                if !car.crashed {
                    car.vehicle.step(st, sp);
                }
            }
            let coast = self.cfg.crashed_rivals == CrashedRivals::Coast;
            let scripted = self.cars[self.agents..].iter_mut();
            for (car, &(st, sp)) in scripted.zip(&planned[self.agents - 1..]) {
                if coast || !car.crashed {
                    car.vehicle.step(st, sp);
                }
            }
            (wall_crash, a2a) = self.resolve_collisions(rivals_every_step || k + 1 == steps);
            if self.cars[..self.agents].iter().all(|c| c.crashed) {
                break;
            }
        }
        self.steps += 1;
        for i in 0..self.cars.len() {
            self.update_progress(i);
        }
        (wall_crash, a2a)
    }

    /// Advances one decision with the ego action `a ∈ [-1, 1]²` (clipped).
    pub fn step(&mut self, action: [f64; 2]) -> Result<Step, RaceError> {
        if self.finished {
            return Err(RaceError::Finished);
        }
        if self.agents != 1 {
            return Err(RaceError::Agents {
                agents: self.agents,
                actions: 1,
            });
        }
        if !action.iter().all(|a| a.is_finite()) {
            return Err(RaceError::BadAction(action));
        }
        let command = self.action_to_command(action);
        let (mut wall_crash, mut a2a) = self.advance(&[command]);
        if self.cfg.ego_relaunch && !(wall_crash || a2a) {
            // the launch's decisions belong to this step: the agent sees none of them
            (wall_crash, a2a) = self.launch_decisions();
        }
        if let Some(e) = self.drivers.iter_mut().find_map(RivalDriver::take_error) {
            self.finished = true;
            return Err(e.into());
        }
        let ego = &self.cars[0];
        let ego_proj = self.track.project(&ego.vehicle.position(), Some(ego.hint));
        let length = self.track.length();
        let lap_complete = ego.travelled >= length;
        let reversed = !(wall_crash || a2a || lap_complete)
            && self
                .cfg
                .reverse_limit
                .is_some_and(|limit| ego.travelled < ego.furthest - limit);
        let progress = (ego.travelled / length).clamp(0.0, 1.0);
        self.metrics.progress = self.metrics.progress.max(progress);
        let rank = self.rank_of(0);
        let overtakes = self.ranks[0] as i32 - rank as i32;
        self.ranks[0] = rank;

        let reward = reward(
            &self.cfg,
            ego.vehicle.speed(),
            ego.vehicle.yaw() - ego_proj.heading,
            ego_proj.lateral,
            wall_crash || a2a || reversed,
            lap_complete,
            overtakes,
        );
        let time = self.steps as f64 * self.cfg.physics_steps_per_action as f64 * DT;
        let timed_out = self.steps >= self.max_steps;
        let ended = wall_crash || a2a || reversed || lap_complete;
        let terminated = ended || (timed_out && self.cfg.timeout_is_terminal);
        let truncated = !terminated && timed_out;
        self.finished = terminated || truncated;

        let m = &mut self.metrics;
        if !self.finished || self.cfg.overtakes_last_step {
            m.overtakes += overtakes;
        }
        m.a2a |= a2a;
        m.wall_crash |= wall_crash;
        m.reversed |= reversed;
        m.steps = self.steps;
        m.episode_return += reward;
        if lap_complete {
            m.progress = if self.cfg.progress_past_line {
                ego.travelled / length
            } else {
                1.0
            };
            m.lap_time = Some(time);
        }
        m.rivals_crashed = self.cars[1..].iter().filter(|c| c.crashed).count();
        m.leader = (1..self.cars.len()).fold(0, |lead, k| {
            if self.cars[k].travelled > self.cars[lead].travelled {
                k
            } else {
                lead
            }
        });
        Ok(Step {
            obs: self.observe_car(0),
            reward,
            terminated,
            truncated,
            info: StepInfo {
                progress: self.metrics.progress,
                overtakes,
                wall_crash,
                a2a,
                reversed,
                lap_complete,
                time,
            },
        })
    }

    /// Maps an ego action to the command `(steering angle, speed)`
    /// ([`RaceConfig::action_to_command`]).
    pub fn action_to_command(&self, action: [f64; 2]) -> (f64, f64) {
        self.cfg.action_to_command(action)
    }

    /// Maps a command `(steering angle, speed)` back to the ego action (clipped to `[-1, 1]²`).
    pub fn command_to_action(&self, steer: f64, speed: f64) -> [f64; 2] {
        let c = &self.cfg;
        [
            (-steer / c.max_steer).clamp(-1.0, 1.0),
            (2.0 * (speed - c.min_speed) / (c.max_speed - c.min_speed) - 1.0).clamp(-1.0, 1.0),
        ]
    }

    /// Marks crashes for this physics step; returns (ego hit a wall, ego hit a rival). The
    /// ego's contacts are always tested, the rivals' own (with a wall, or with each other) only
    /// when `rivals` is set.
    fn resolve_collisions(&mut self, rivals: bool) -> (bool, bool) {
        self.boxes.clear();
        self.boxes.extend(
            self.cars
                .iter()
                .map(|c| CarBox::new(&c.vehicle.state, &self.params)),
        );
        let n = self.cars.len();
        let mut ego_wall = false;
        let mut ego_a2a = false;
        let tested = if rivals { n } else { self.agents };
        for i in 0..tested {
            if self.cars[i].crashed {
                continue;
            }
            let now = self.cars[i].vehicle.position();
            if self.boxes[i].hits_wall_by(self.cfg.wall_contact, self.centres[i], &now, &self.track)
            {
                self.crash(i);
                self.cars[i].wall_hit = true;
                ego_wall |= i == 0;
            }
        }
        for i in 0..tested {
            for j in i + 1..n {
                if (self.cars[i].crashed && self.cars[j].crashed)
                    || !self.boxes[i].overlaps(&self.boxes[j])
                {
                    continue;
                }
                self.crash(i);
                self.crash(j);
                self.cars[i].car_hit = true;
                self.cars[j].car_hit = true;
                ego_a2a |= i == 0;
            }
        }
        (ego_wall, ego_a2a)
    }

    fn crash(&mut self, i: usize) {
        self.cars[i].crashed = true;
        if i < self.agents || self.cfg.crashed_rivals == CrashedRivals::Stop {
            self.cars[i].vehicle.stop();
        }
    }

    /// Moves car `i`'s progress to its current position.
    fn update_progress(&mut self, i: usize) {
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
        car.furthest = car.furthest.max(car.travelled);
        car.s = proj.s;
        car.hint = proj.segment;
    }

    /// 1-based rank of car `i` by distance travelled (ties favour car `i`).
    fn rank_of(&self, i: usize) -> usize {
        let me = self.cars[i].travelled;
        let others = self.cars.iter().enumerate().filter(|&(j, _)| j != i);
        1 + others.filter(|(_, c)| c.travelled > me).count()
    }

    /// Car `i`'s LiDAR observation: its scan of the walls and every other car, normalised with
    /// the race's noise.
    fn observe_car(&mut self, i: usize) -> Vec<f32> {
        self.boxes.clear();
        let others = self.cars.iter().enumerate().filter(|&(j, _)| j != i);
        self.boxes
            .extend(others.map(|(_, c)| CarBox::new(&c.vehicle.state, &self.params)));
        let ego = &self.cars[i].vehicle;
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

    /// Race time between two decisions (s): `physics_steps_per_action` physics steps.
    pub fn decision_period(&self) -> f64 {
        self.cfg.decision_period()
    }

    /// Number of LiDAR beams in an observation.
    pub fn obs_dim(&self) -> usize {
        self.lidar.beams()
    }

    /// Values of [`RaceEnv::state_into`]: [`EGO_STATE`] and [`RIVAL_STATE`] per rival.
    pub fn state_dim(&self) -> usize {
        EGO_STATE + RIVAL_STATE * self.cfg.rivals
    }

    /// The race's state as f1tenth_gym returns it beside the scan, into `out`
    /// ([`RaceEnv::state_dim`] values): the ego's pose `x, y` (m, the map's frame) and yaw
    /// `ψ` (rad, wrapped to (−π, π]), its speed `v` (m/s) and yaw rate `ψ̇` (rad/s); then each
    /// rival's position relative to the ego in the ego's frame (`Δx` ahead, `Δy` to its left,
    /// m), its heading relative to the ego's (wrapped) and its speed. Every value lies within
    /// [`RaceEnv::state_bounds`].
    pub fn state_into(&self, out: &mut [f32]) {
        self.state_of(0, out);
    }

    /// [`RaceEnv::state_into`] as car `i` sees the race: its own pose, speed and yaw rate, then
    /// every other car relative to it, in grid order.
    pub fn state_of(&self, i: usize, out: &mut [f32]) {
        use crate::vehicle::idx;
        let ego = &self.cars[i].vehicle.state;
        let (yaw, (sin, cos)) = (ego[idx::YAW], ego[idx::YAW].sin_cos());
        out[..EGO_STATE].copy_from_slice(&[
            ego[idx::X] as f32,
            ego[idx::Y] as f32,
            wrap_angle(yaw) as f32,
            ego[idx::V] as f32,
            ego[idx::YAW_RATE] as f32,
        ]);
        let others = self.cars.iter().enumerate().filter(|&(j, _)| j != i);
        for ((_, rival), o) in others.zip(out[EGO_STATE..].chunks_exact_mut(RIVAL_STATE)) {
            let r = &rival.vehicle.state;
            let (dx, dy) = (r[idx::X] - ego[idx::X], r[idx::Y] - ego[idx::Y]);
            o.copy_from_slice(&[
                (cos * dx + sin * dy) as f32,
                (-sin * dx + cos * dy) as f32,
                wrap_angle(r[idx::YAW] - yaw) as f32,
                r[idx::V] as f32,
            ]);
        }
    }

    /// Bounds `(low, high)` of each value of [`RaceEnv::state_into`]: positions within
    /// [`STATE_MARGIN`] of the farthest centreline coordinate (twice that for the rivals'
    /// offsets), angles within ±π, speeds within the plausible speed of a race config and yaw
    /// rates within [`MAX_YAW_RATE`].
    pub fn state_bounds(&self) -> (Vec<f32>, Vec<f32>) {
        let farthest = self.track.centreline.curve.points().iter();
        let reach = farthest.fold(0.0f64, |m, p| m.max(p.x.abs()).max(p.y.abs())) + STATE_MARGIN;
        let (pi, v) = (
            std::f32::consts::PI,
            ctxrace_config::config::MAX_PLAUSIBLE_SPEED as f32,
        );
        let ego = [reach as f32, reach as f32, pi, v, MAX_YAW_RATE];
        let rival = [2.0 * reach as f32, 2.0 * reach as f32, pi, v];
        let high: Vec<f32> = ego
            .into_iter()
            .chain((0..self.cfg.rivals).flat_map(|_| rival))
            .collect();
        (high.iter().map(|h| -h).collect(), high)
    }
}

/// How far beyond the centreline's farthest coordinate [`RaceEnv::state_bounds`] admits a car
/// (m): the walls are a few metres from it.
pub const STATE_MARGIN: f64 = 100.0;

/// The largest yaw rate [`RaceEnv::state_bounds`] admits (rad/s): a car spinning at 50 turns a
/// second.
pub const MAX_YAW_RATE: f32 = 100.0 * std::f32::consts::PI;

/// `a` wrapped to (−π, π].
fn wrap_angle(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let w = (a + PI).rem_euclid(TAU) - PI;
    if w == -PI {
        PI
    } else {
        w
    }
}

/// Values of the ego's part of [`RaceEnv::state_into`]: x, y, yaw, speed, yaw rate.
pub const EGO_STATE: usize = 5;
/// Values of each rival's part of [`RaceEnv::state_into`]: Δx, Δy (the ego's frame), Δyaw,
/// speed.
pub const RIVAL_STATE: usize = 4;
