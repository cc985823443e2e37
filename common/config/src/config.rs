//! Race configuration: the scenario, the ego's sensor and action mapping, and the rivals (their
//! driver's keys in [`crate::rival`]).
//!
//! Every struct rejects unknown keys and fills missing ones from a preset: by default ctxrace's
//! scenario (the paper's text, with the rival speed and starting grid of the code that produced
//! its tables, and the fixes listed below),
//! or with `preset = "paper-code"` the race exactly as the paper's public code ran it
//! ([`RaceConfig::paper_code`]). A TOML file only names what it changes.
//!
//! The two presets differ in these keys (docs/guides/race.md has the full table with the
//! reasons):
//!
//! | key | default | `paper-code` |
//! |---|---|---|
//! | `min_speed` | 0 (paper text) | 1 |
//! | `max_steer` | 0.4189 (the car's limit) | 0.4 (`max_steer` of config_file.yaml) |
//! | `reward_speed` | 6 (`v_max`, paper text) | 8 |
//! | `step_reward_floor` | none | 0 |
//! | `terminal_rewards_replace_step` | false (added, paper text) | true |
//! | `reverse_limit` | none | 1 m |
//! | `timeout_is_terminal` | false (truncation) | true |
//! | `shipped_raceline` | false (computed) | true |
//! | `wall_contact` | `footprint` | `centre-pixel` |
//! | `rival_contacts` | `per-step` | `decision-end` |
//! | `integrator` | `rk4` | `euler` |
//! | `ego_launch_below` | 0 (off) | 1 m/s (at `ego_launch_speed` 7 m/s) |
//! | `ego_relaunch` | false | true |
//! | `crashed_rivals` | `stop` | `coast` |
//! | `grid_line` | `raceline` | `x-axis` |
//! | `overtakes_last_step` | true | false |
//! | `progress_past_line` | false | true |
//! | `rival.steer_lookahead` | none (the target's distance) | 1.5 m |
//! | `rival.target_at_vertex` | false | true |
//! | `rival.speed_point` | `slowest-ahead` | `nearest` |
//! | `rival.launch_below` | 0 (off) | 1 m/s (at `launch_speed` 4 m/s) |
//! | `rival.lift_off_line` | 0.15 m | 0 (off) |
//! | `rival.wheelbase` | none (the car's, 0.3302 m) | 0.329 m |
//! | `rival.max_steer` | none (the car's limit, 0.4189) | 0.4 |
//!
//! Until 2026-12-06 the `paper-code` preset had `wall_contact = "centre"`, `rival_contacts =
//! "per-step"`, `grid_line = "centreline"` and the car's wheelbase and steering limit for the
//! rivals (configs/scenarios/paper-code-table-era.toml; docs/table2/sim_agreement.md has what
//! the comparison with the paper's simulator found).

use crate::preset::PresetError;
use crate::rival::{RivalConfig, RivalDriverKind, SpeedPoint};
use crate::validate::{bounded_floats, finite_floats, in_range, ValueError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::ops::Bound;

/// Largest observation (one LiDAR frame, in beams) a run may have: the frame the transport's
/// trajectory chunks are sized for.
pub const MAX_OBS: usize = 256;

/// The longest episode (`[race] max_time`, s; the paper's: 240).
pub const MAX_EPISODE_SECS: f64 = 3600.0;

/// The simulator's physics time step in seconds.
pub const PHYSICS_DT: f64 = 0.01;
/// Most physics steps (0.01 s) per agent decision: 10 s of blind driving.
pub const MAX_PHYSICS_STEPS_PER_ACTION: usize = 1000;
/// Longest steering delay in physics steps (1 s).
pub const MAX_STEER_DELAY: usize = 100;
/// The fastest speed a race config may give a car (m/s): 5 times F1TENTH's 20 m/s top speed.
pub const MAX_PLAUSIBLE_SPEED: f64 = 100.0;
/// The longest distance a race config may give a lookahead, a scan or a grid gap (m).
pub const MAX_LOOKAHEAD: f64 = 200.0;
/// Most rivals a race holds (the start grid's cars besides the ego).
pub const MAX_RIVALS: usize = 7;

/// Why a race configuration is refused: each names the key, its value and how to fix it.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RaceConfigError {
    /// Not TOML, or a key or a value that the table does not take (with its line).
    #[error("{}", crate::validate::toml_message(.0))]
    Toml(toml::de::Error),
    /// The table could not be read over its preset.
    #[error(transparent)]
    Preset(#[from] PresetError),
    /// A float that is not finite, or a value outside its range.
    #[error(transparent)]
    Value(#[from] ValueError),
    /// A length, speed or time that must be positive.
    #[error("{key} = {value} must be a positive number")]
    NotPositive {
        /// The key.
        key: String,
        /// Its value.
        value: f64,
    },
    /// A threshold or gain that must not be negative.
    #[error("{key} = {value} must be a number >= 0 (0 disables it)")]
    Negative {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
    },
    /// `step_reward_floor` is not a number.
    #[error("step_reward_floor = {0} must be a number (leave it out for none)")]
    StepRewardFloor(f64),
    /// More rivals than a race holds.
    #[error("rivals = {0} must be 0 to {MAX_RIVALS}")]
    Rivals(usize),
    /// `[rival] driver = "policy"` without the agent to drive.
    #[error(
        "[rival] driver = \"policy\" needs the trained agent: set [rival] policy = \"RUN_DIR\" \
         (its best checkpoint), a checkpoint folder or an MLP policy file (*.safetensors)"
    )]
    PolicyMissing,
    /// `min_speed` is negative or not below `max_speed`.
    #[error("min_speed = {min_speed} must be in [0, max_speed = {max_speed})")]
    MinSpeed {
        /// `min_speed`.
        min_speed: f64,
        /// `max_speed`.
        max_speed: f64,
    },
    /// The rivals' gap as a lap fraction is not positive or does not fit the lap.
    #[error(
        "start_gap = {start_gap} must be positive and leave the {rivals} rivals within 90% of \
         the lap"
    )]
    StartGap {
        /// `start_gap`.
        start_gap: f64,
        /// `rivals`.
        rivals: usize,
    },
    /// The starting grid does not fit on the track's lap.
    #[error(
        "{key}: {rivals} rivals {spacing:.1} m apart do not fit within 90% of {track}'s \
         {length:.1} m lap; lower it or the number of rivals"
    )]
    Grid {
        /// The key that sets the spacing.
        key: String,
        /// `rivals`.
        rivals: usize,
        /// The spacing (m).
        spacing: f64,
        /// The track.
        track: String,
        /// The track's lap (m).
        length: f64,
    },
}

/// A named starting point for a race scenario: keys a file leaves out take the preset's values.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RacePreset {
    /// ctxrace's scenario ([`RaceConfig::default`]).
    #[default]
    Default,
    /// The race as the paper's public code ran it ([`RaceConfig::paper_code`]).
    PaperCode,
}

impl RacePreset {
    /// The scenario of the preset.
    pub fn config(self) -> RaceConfig {
        match self {
            RacePreset::Default => RaceConfig::default(),
            RacePreset::PaperCode => RaceConfig::paper_code(),
        }
    }
}

/// When a car has hit a wall.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WallContact {
    /// Its rectangle touches a wall (exact, as REFERENCE §2 asks).
    #[default]
    Footprint,
    /// Its centre crosses a traced wall during the physics step (the paper's code in spirit,
    /// against the walls traced from the map image).
    Centre,
    /// Its centre lies in an occupied pixel of the track's map image, or outside the image,
    /// after the physics step: the paper's code exactly, whose gym had the footprint (TTC)
    /// check switched off and ended a car only when the distance transform at its centre's
    /// pixel was 0 (f110_env `check_location`). The traced walls run up to half a pixel
    /// (Douglas–Peucker) from the pixel edges, so `centre` and this differ near the walls.
    /// Tracks without a map image (generated ones) test `centre`.
    CentrePixel,
}

/// How the vehicle model is integrated over a physics step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Integrator {
    /// Classical fourth-order Runge–Kutta (today's f1tenth_gym).
    #[default]
    Rk4,
    /// Explicit Euler, `x ← x + f(x, u) dt` (the f1tenth_gym copy in the paper's code).
    Euler,
}

/// How the cars are spaced on the starting grid, along the centreline, the ego last.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StartGrid {
    /// `start_spacing` metres apart along the centreline: the code that produced the paper's
    /// tables (c0fd903 `TestSimulation.calc_offsets`, which spaced them along the map's x axis
    /// from the origin, where f1_esp and f1_gbr start facing +x).
    #[default]
    Spacing,
    /// `start_gap` of the lap apart (the release of the paper's code, from 017a176, Dec 2025).
    LapFraction,
}

/// The line the cars stand on at their grid places.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GridLine {
    /// On the raceline beside each grid place, facing along it: a rival then drives off along
    /// the line it follows instead of joining it from the side while it accelerates.
    #[default]
    Raceline,
    /// On the centreline, facing along it (near the paper's code on f1_esp and f1_gbr, whose
    /// start is the centreline; f1_esp's centreline runs 0.05 m left of the x axis from 4.6 m
    /// to 17.1 m, where the rivals stand (5.5, 11 and 16.5 m)).
    Centreline,
    /// On the map's x axis, facing +x, each car at its grid distance from the origin: the paper's
    /// code (c0fd903 `TestSimulation.calc_offsets` and `reset_simulation`), meaningful only on
    /// maps that start at the origin facing +x (f1_esp, f1_gbr).
    XAxis,
}

/// When a rival's own contacts (with a wall, or with another rival) crash it. Contacts of the
/// ego, with a wall or a rival, end the episode at the physics step where they happen either way.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RivalContacts {
    /// At any physics step.
    #[default]
    PerStep,
    /// Only a contact at the end of the decision (its last physics step): the paper's code,
    /// whose loop read a rival's collision flag once per decision from the last step's
    /// observation (c0fd903 `build_observation`), while its gym rebuilt the flags at every
    /// step, so a rival that grazed a wall pixel, or another rival, between two decisions drove
    /// on.
    DecisionEnd,
}

/// What a rival that crashed does for the rest of the episode.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CrashedRivals {
    /// It stops where it crashed and stays there as an obstacle.
    #[default]
    Stop,
    /// It is still simulated under the command (0 rad, 0 m/s), braking from its speed and
    /// passing through walls (the paper's code: its planners' command for a crashed car, in a
    /// gym without wall physics).
    Coast,
}

/// One head-to-head race scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RaceConfig {
    /// The preset the other keys start from (see [`RaceConfig::from_table`]).
    pub preset: RacePreset,
    /// Number of rival cars, 0 to 7.
    pub rivals: usize,
    /// How far apart the cars start: a fixed distance (`spacing`) or a fraction of the lap.
    pub start_grid: StartGrid,
    /// Which line the cars stand on at their grid places (`raceline` or `centreline`); the
    /// places themselves are measured along the centreline.
    pub grid_line: GridLine,
    /// Distance between consecutive cars on the grid, along the centreline (m), on tracks
    /// without an entry in `start_spacing_tracks` (`start_grid = "spacing"`; the paper's code
    /// at c0fd903: 5.5).
    pub start_spacing: f64,
    /// `start_spacing` per track name (the paper's code: 5.5 m on f1_esp, 4.0 on f1_gbr, 3.0 on
    /// f1_mco).
    pub start_spacing_tracks: BTreeMap<String, f64>,
    /// Gap between consecutive cars on the grid as a fraction of the lap
    /// (`start_grid = "lap-fraction"`; the release of the paper's code, Dec 2025: 0.05).
    pub start_gap: f64,
    /// Ego speed range top: action `a_1 ∈ [-1, 1]` maps onto `[min_speed, max_speed]` m/s.
    pub max_speed: f64,
    /// Ego speed range bottom (paper: 0; the paper's code: 1).
    pub min_speed: f64,
    /// Ego steering range: `a_0 ∈ [-1, 1]` maps onto `[-max_steer, max_steer]` rad, negative = left
    /// (the car's limit 0.4189; the paper's code: 0.4).
    pub max_steer: f64,
    /// Speed that normalises the reward's `v / v_max` term (m/s; paper: `v_max` = 6, its code: 8).
    pub reward_speed: f64,
    /// Lower bound of the per-step reward `v / v_max cos φ − d_c` (the paper's code: 0).
    pub step_reward_floor: Option<f64>,
    /// The crash (−1) and lap (+1) rewards replace the step reward instead of being added to it
    /// (the paper's code); overtakes are added either way.
    pub terminal_rewards_replace_step: bool,
    /// The episode ends, as a crash, when the ego's progress falls this far (m) behind the
    /// furthest it reached: it drove backwards (the paper's code: 1 m).
    pub reverse_limit: Option<f64>,
    /// Reaching `max_time` terminates the episode (stored as terminal, the paper's code) instead
    /// of truncating it (bootstrapped).
    pub timeout_is_terminal: bool,
    /// Rivals drive the raceline shipped with the track (`NAME_raceline.csv`, the paper's code)
    /// instead of the computed min-curvature line.
    pub shipped_raceline: bool,
    /// When a car has hit a wall.
    pub wall_contact: WallContact,
    /// When a rival's own contacts crash it (the ego's end the episode at once either way).
    pub rival_contacts: RivalContacts,
    /// How the vehicle model is integrated.
    pub integrator: Integrator,
    /// While the ego is slower than this (m/s) at the start of an episode, it drives straight at
    /// `ego_launch_speed` before the agent takes over (the paper's code: 1 m/s, its planners'
    /// `v_min_plan`; it stores none of these steps); 0 disables it.
    pub ego_launch_below: f64,
    /// The ego's launch speed command (m/s; the paper's code: 7).
    pub ego_launch_speed: f64,
    /// The launch also takes over whenever the ego drops below `ego_launch_below` mid-episode
    /// (the paper's code, whose planners applied it every step); its decisions are folded into
    /// the agent's step that slowed the ego, which sees none of them.
    pub ego_relaunch: bool,
    /// What a crashed rival does.
    pub crashed_rivals: CrashedRivals,
    /// OT counts the rank change of the episode's last step (the paper's code left it out: it
    /// summed each step's change before stepping, so the step that ends the episode is lost).
    pub overtakes_last_step: bool,
    /// PG of a completed lap is the distance driven over the lap's length, a little above 1
    /// (the paper's code) instead of exactly 1.
    pub progress_past_line: bool,
    /// Physics steps (0.01 s) per agent decision.
    pub physics_steps_per_action: usize,
    /// Steering command delay in physics steps (f1tenth_gym: 2).
    pub steer_delay: usize,
    /// Episode time limit in seconds.
    pub max_time: f64,
    /// The ego's LiDAR.
    pub lidar: LidarConfig,
    /// The rivals' driver.
    pub rival: RivalConfig,
}

impl Default for RaceConfig {
    fn default() -> Self {
        Self {
            preset: RacePreset::Default,
            rivals: 1,
            start_grid: StartGrid::Spacing,
            grid_line: GridLine::Raceline,
            start_spacing: 5.5,
            start_spacing_tracks: BTreeMap::from([
                ("f1_esp".to_string(), 5.5),
                ("f1_gbr".to_string(), 4.0),
                ("f1_mco".to_string(), 3.0),
            ]),
            start_gap: 0.05,
            max_speed: 6.0,
            min_speed: 0.0,
            max_steer: 0.4189,
            reward_speed: 6.0,
            step_reward_floor: None,
            terminal_rewards_replace_step: false,
            reverse_limit: None,
            timeout_is_terminal: false,
            shipped_raceline: false,
            wall_contact: WallContact::Footprint,
            rival_contacts: RivalContacts::PerStep,
            integrator: Integrator::Rk4,
            ego_launch_below: 0.0,
            ego_launch_speed: 7.0,
            ego_relaunch: false,
            crashed_rivals: CrashedRivals::Stop,
            overtakes_last_step: true,
            progress_past_line: false,
            physics_steps_per_action: 10,
            steer_delay: 2,
            max_time: 240.0,
            lidar: LidarConfig::default(),
            rival: RivalConfig::default(),
        }
    }
}

impl RaceConfig {
    /// Race time between two decisions (s): `physics_steps_per_action` physics steps.
    pub fn decision_period(&self) -> f64 {
        self.physics_steps_per_action as f64 * PHYSICS_DT
    }

    /// The command `(steering angle δ, speed v)` of a car's action `a ∈ [-1, 1]²` (clipped):
    /// `δ = −a₀ max_steer` (negative `a₀` turns left) and `v = min_speed + (a₁ + 1)/2 ·
    /// (max_speed − min_speed)`.
    pub fn action_to_command(&self, action: [f64; 2]) -> (f64, f64) {
        let a0 = action[0].clamp(-1.0, 1.0);
        let a1 = action[1].clamp(-1.0, 1.0);
        (
            -a0 * self.max_steer,
            self.min_speed + (a1 + 1.0) / 2.0 * (self.max_speed - self.min_speed),
        )
    }

    /// Most decisions in one episode: `max_time` over a decision's period.
    pub fn max_decisions(&self) -> usize {
        (self.max_time / self.decision_period()).ceil() as usize
    }

    /// The race as the paper's public code (lilpharaoh1/context-f110) ran it when it produced
    /// the tables (the `paper` branch, c0fd903, Jun 2025, `TrajectoryAidedLearning/`): its reward
    /// (RewardSignals.py `CrossTrackHeadReward`), ego speed map and launch, backwards-driving
    /// end, time-outs stored as terminal (TestSimulation.py, the planners), its gym's Euler
    /// integration and centre-point wall check (f110_gym), the shipped raceline and its pure
    /// pursuit (Planners/PurePursuit.py).
    pub fn paper_code() -> Self {
        Self {
            preset: RacePreset::PaperCode,
            min_speed: 1.0,
            max_steer: 0.4,
            reward_speed: 8.0,
            step_reward_floor: Some(0.0),
            terminal_rewards_replace_step: true,
            reverse_limit: Some(1.0),
            timeout_is_terminal: true,
            shipped_raceline: true,
            wall_contact: WallContact::CentrePixel,
            rival_contacts: RivalContacts::DecisionEnd,
            integrator: Integrator::Euler,
            ego_launch_below: 1.0,
            ego_relaunch: true,
            crashed_rivals: CrashedRivals::Coast,
            grid_line: GridLine::XAxis,
            overtakes_last_step: false,
            progress_past_line: true,
            rival: RivalConfig {
                steer_lookahead: Some(1.5),
                target_at_vertex: true,
                speed_point: SpeedPoint::Nearest,
                launch_below: 1.0,
                launch_speed: 4.0,
                lift_off_line: 0.0,
                wheelbase: Some(0.329),
                max_steer: Some(0.4),
                ..RivalConfig::default()
            },
            ..Self::default()
        }
    }

    /// Reads a race table: keys it leaves out take the values of its `preset` (the default
    /// scenario when it names none). Unknown keys and bad values are errors naming the key.
    pub fn from_table(table: toml::Table) -> Result<Self, RaceConfigError> {
        let cfg: Self = crate::preset::resolve(table, RacePreset::config)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Parses a race scenario TOML (see [`RaceConfig::from_table`]).
    pub fn from_toml(text: &str) -> Result<Self, RaceConfigError> {
        // parsed as the struct first so that syntax and unknown keys are reported with their line
        let direct: Self = toml::from_str(text).map_err(RaceConfigError::Toml)?;
        if direct.preset == RacePreset::Default {
            direct.validate()?;
            return Ok(direct);
        }
        Self::from_table(toml::from_str(text).map_err(RaceConfigError::Toml)?)
    }

    /// Distance between consecutive cars on the grid of `track` (m along the centreline), on a
    /// lap of `length` m.
    pub fn grid_spacing(&self, track: &str, length: f64) -> f64 {
        match self.start_grid {
            StartGrid::Spacing => self
                .start_spacing_tracks
                .get(track)
                .copied()
                .unwrap_or(self.start_spacing),
            StartGrid::LapFraction => self.start_gap * length,
        }
    }

    /// Checks that the grid fits on a lap of `length` m of `track`: the rivals within 90% of it.
    pub fn validate_grid(&self, track: &str, length: f64) -> Result<(), RaceConfigError> {
        let spacing = self.grid_spacing(track, length);
        if spacing * self.rivals as f64 > 0.9 * length {
            let key = match self.start_grid {
                StartGrid::Spacing if self.start_spacing_tracks.contains_key(track) => {
                    format!("start_spacing_tracks.{track}")
                }
                StartGrid::Spacing => "start_spacing".to_string(),
                StartGrid::LapFraction => "start_gap".to_string(),
            };
            return Err(RaceConfigError::Grid {
                key,
                rivals: self.rivals,
                spacing,
                track: track.to_string(),
                length,
            });
        }
        Ok(())
    }

    /// Checks ranges, every float finite and within ±[`crate::validate::MAX_FLOAT`]; the
    /// message names the key and its valid range.
    pub fn validate(&self) -> Result<(), RaceConfigError> {
        finite_floats(self, &self.preset.config())?;
        let gap = &self.rival.follow_the_gap;
        let positive = [
            ("max_speed", self.max_speed),
            ("max_steer", self.max_steer),
            ("reward_speed", self.reward_speed),
            ("max_time", self.max_time),
            ("lidar.max_range", self.lidar.max_range),
            ("lidar.fov_deg", self.lidar.fov_deg),
            ("rival.speed_factor", self.rival.speed_factor),
            ("rival.lookahead", self.rival.lookahead),
            ("rival.max_speed", self.rival.max_speed),
            ("rival.launch_speed", self.rival.launch_speed),
            ("ego_launch_speed", self.ego_launch_speed),
            ("start_spacing", self.start_spacing),
            ("rival.follow_the_gap.max_range", gap.max_range),
            ("rival.follow_the_gap.range_clip", gap.range_clip),
            ("rival.follow_the_gap.steer_gain", gap.steer_gain),
            ("rival.follow_the_gap.straight_speed", gap.straight_speed),
            ("rival.follow_the_gap.corner_speed", gap.corner_speed),
            ("rival.follow_the_gap.corner_steer", gap.corner_steer),
        ];
        let optional = [
            ("reverse_limit", self.reverse_limit),
            ("rival.steer_lookahead", self.rival.steer_lookahead),
            ("rival.wheelbase", self.rival.wheelbase),
            ("rival.max_steer", self.rival.max_steer),
        ];
        let per_track = self
            .start_spacing_tracks
            .iter()
            .map(|(t, v)| (format!("start_spacing_tracks.{t}"), *v));
        for (k, v) in positive
            .into_iter()
            .chain(optional.into_iter().filter_map(|(k, v)| v.map(|v| (k, v))))
            .map(|(k, v)| (k.to_string(), v))
            .chain(per_track)
        {
            if !(v.is_finite() && v > 0.0) {
                return Err(RaceConfigError::NotPositive { key: k, value: v });
            }
        }
        for (k, v) in [
            ("rival.lookahead_gain", self.rival.lookahead_gain),
            ("rival.launch_below", self.rival.launch_below),
            ("rival.lift_off_line", self.rival.lift_off_line),
            ("ego_launch_below", self.ego_launch_below),
            ("rival.follow_the_gap.bubble_radius", gap.bubble_radius),
            ("rival.follow_the_gap.free_range", gap.free_range),
            ("rival.follow_the_gap.brake_decel", gap.brake_decel),
            ("rival.follow_the_gap.stop_margin", gap.stop_margin),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(RaceConfigError::Negative { key: k, value: v });
            }
        }
        if let Some(floor) = self.step_reward_floor {
            if !floor.is_finite() {
                return Err(RaceConfigError::StepRewardFloor(floor));
            }
        }
        if self.rivals > MAX_RIVALS {
            return Err(RaceConfigError::Rivals(self.rivals));
        }
        match (self.rival.driver, &self.rival.policy) {
            (RivalDriverKind::Policy, None) => return Err(RaceConfigError::PolicyMissing),
            (RivalDriverKind::Policy, Some(p)) if p.as_os_str().is_empty() => {
                return Err(RaceConfigError::PolicyMissing)
            }
            _ => {}
        }
        if !(self.min_speed >= 0.0 && self.min_speed < self.max_speed) {
            return Err(RaceConfigError::MinSpeed {
                min_speed: self.min_speed,
                max_speed: self.max_speed,
            });
        }
        if !(self.start_gap > 0.0 && self.start_gap * self.rivals as f64 <= 0.9) {
            return Err(RaceConfigError::StartGap {
                start_gap: self.start_gap,
                rivals: self.rivals,
            });
        }
        in_range(
            "physics_steps_per_action",
            self.physics_steps_per_action,
            1..=MAX_PHYSICS_STEPS_PER_ACTION,
            "each is 0.01 s of simulation (the paper: 10)",
        )?;
        // physical plausibility: a value no car or sensor has is a typo, and some (a lookahead of
        // 1e308 m) would keep the geometry searching for a point until the end of time
        let physical = [
            (
                "max_speed",
                self.max_speed,
                MAX_PLAUSIBLE_SPEED,
                "m/s (the paper: 6)",
            ),
            (
                "rival.max_speed",
                self.rival.max_speed,
                MAX_PLAUSIBLE_SPEED,
                "m/s (the paper's 6)",
            ),
            (
                "rival.launch_speed",
                self.rival.launch_speed,
                MAX_PLAUSIBLE_SPEED,
                "m/s",
            ),
            (
                "ego_launch_speed",
                self.ego_launch_speed,
                MAX_PLAUSIBLE_SPEED,
                "m/s",
            ),
            (
                "rival.follow_the_gap.straight_speed",
                gap.straight_speed,
                MAX_PLAUSIBLE_SPEED,
                "m/s",
            ),
            (
                "rival.lookahead",
                self.rival.lookahead,
                MAX_LOOKAHEAD,
                "m (the paper: 1)",
            ),
            (
                "rival.lookahead_gain",
                self.rival.lookahead_gain,
                10.0,
                "s: m per m/s (the paper: 0.1)",
            ),
            (
                "rival.speed_factor",
                self.rival.speed_factor,
                10.0,
                "of the raceline's speed (the code's 0.85)",
            ),
            (
                "lidar.max_range",
                self.lidar.max_range,
                MAX_LOOKAHEAD,
                "m (the paper: 10)",
            ),
            (
                "rival.follow_the_gap.max_range",
                gap.max_range,
                MAX_LOOKAHEAD,
                "m",
            ),
            (
                "start_spacing",
                self.start_spacing,
                MAX_LOOKAHEAD,
                "m between grid places (the code's 5.5)",
            ),
        ];
        let optional_physical = [
            (
                "rival.steer_lookahead",
                self.rival.steer_lookahead,
                MAX_LOOKAHEAD,
                "m",
            ),
            (
                "rival.wheelbase",
                self.rival.wheelbase,
                10.0,
                "m (the car's 0.33)",
            ),
        ];
        let physical = physical.into_iter().chain(
            optional_physical
                .into_iter()
                .filter_map(|(k, v, max, why)| v.map(|v| (k, v, max, why))),
        );
        for (key, value, max, unit) in physical {
            in_range(
                key,
                value,
                ..=max,
                &format!("{unit}; no race goes beyond {max}"),
            )?;
        }
        in_range(
            "steer_delay",
            self.steer_delay,
            ..=MAX_STEER_DELAY,
            "it counts physics steps of 0.01 s (f1tenth_gym: 2)",
        )?;
        in_range(
            "lidar.beams",
            self.lidar.beams,
            1..=MAX_OBS,
            "the wire format carries at most that many (the paper: 108)",
        )?;
        in_range(
            "rival.follow_the_gap.beams",
            gap.beams,
            2..=4096,
            "the driver's scan needs beams to find a gap in (the ego's: 108)",
        )?;
        in_range(
            "rival.follow_the_gap.fov_deg",
            gap.fov_deg,
            1.0..=360.0,
            "it is the scan's field of view in degrees, centred on the heading (the ego's: 180)",
        )?;
        in_range(
            "rival.follow_the_gap.smoothing",
            gap.smoothing,
            1..=gap.beams,
            "it is a window in beams; 1 smooths nothing",
        )?;
        if gap.range_clip <= gap.free_range {
            return Err(ValueError::OutOfRange {
                key: "rival.follow_the_gap.free_range".into(),
                value: gap.free_range.to_string(),
                bounds: format!("below range_clip = {}", gap.range_clip),
                fix: "no beam could be free otherwise".into(),
            }
            .into());
        }
        if gap.corner_speed > gap.straight_speed {
            return Err(ValueError::OutOfRange {
                key: "rival.follow_the_gap.corner_speed".into(),
                value: gap.corner_speed.to_string(),
                bounds: format!("at most straight_speed = {}", gap.straight_speed),
                fix: "the driver slows down in turns".into(),
            }
            .into());
        }
        if let Some(steer) = self.rival.max_steer {
            in_range(
                "rival.max_steer",
                steer,
                ..=std::f64::consts::FRAC_PI_2,
                "it is a steering angle in radians (the car's limit: 0.4189; the paper's code: 0.4)",
            )?;
        }
        in_range(
            "lidar.noise_sd",
            self.lidar.noise_sd,
            0.0..=1.0,
            "it is in metres (the paper: 0.01)",
        )?;
        in_range(
            "max_time",
            self.max_time,
            (Bound::Excluded(0.0), Bound::Included(MAX_EPISODE_SECS)),
            "the seconds an episode lasts at most (the paper: 240)",
        )?;
        // last: the keys' own checks above say more about a value they bound
        Ok(bounded_floats(self, &self.preset.config())?)
    }
}

/// The ego's 2D LiDAR.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LidarConfig {
    /// Number of beams, evenly spread over the field of view, ends included.
    pub beams: usize,
    /// Field of view in degrees, centred on the heading.
    pub fov_deg: f64,
    /// Ranges are clipped to this and divided by it (m).
    pub max_range: f64,
    /// Standard deviation of the Gaussian noise added to each range (m).
    pub noise_sd: f64,
}

impl Default for LidarConfig {
    fn default() -> Self {
        Self {
            beams: 108,
            fov_deg: 180.0,
            max_range: 10.0,
            noise_sd: 0.01,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_overrides_and_rejects_unknown_keys() {
        let c: RaceConfig = toml::from_str("rivals = 3\n[lidar]\nmax_range = 5.0\n").unwrap();
        assert_eq!(c.rivals, 3);
        assert_eq!(c.lidar.max_range, 5.0);
        assert_eq!(c.lidar.beams, 108);
        let err = toml::from_str::<RaceConfig>("rivalz = 3\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("unknown field `rivalz`"), "{err}");
        assert!(RaceConfig::default().validate().is_ok());
        let bad = RaceConfig {
            rivals: 9,
            ..Default::default()
        };
        let err = bad.validate().unwrap_err();
        assert_eq!(err, RaceConfigError::Rivals(9));
        assert!(err.to_string().contains("rivals = 9"));
        assert_eq!(RivalConfig::default().gains_for("f1_mco").lambda_theta, 0.3);
        assert_eq!(
            RivalConfig::default().gains_for("generated:3").lambda_theta,
            0.4
        );
    }

    #[test]
    fn a_grid_that_does_not_fit_names_the_key_that_spaces_it_the_track_and_the_lap() {
        let mut cfg = RaceConfig {
            rivals: 7,
            ..RaceConfig::default()
        };
        cfg.start_spacing_tracks.insert("f1_esp".into(), 300.0);
        assert!(cfg.validate_grid("f1_esp", 5000.0).is_ok());
        let err = cfg.validate_grid("f1_esp", 500.0).unwrap_err();
        assert_eq!(
            err.to_string(),
            "start_spacing_tracks.f1_esp: 7 rivals 300.0 m apart do not fit within 90% of \
             f1_esp's 500.0 m lap; lower it or the number of rivals"
        );
        cfg.start_spacing = 100.0;
        let err = cfg.validate_grid("generated:1", 500.0).unwrap_err();
        assert!(
            matches!(&err, RaceConfigError::Grid { key, .. } if key == "start_spacing"),
            "{err}"
        );
    }

    #[test]
    fn the_paper_code_preset_fills_what_a_file_leaves_out() {
        let c = RaceConfig::from_toml(
            "preset = \"paper-code\"\nrivals = 3\n[rival]\nspeed_factor = 0.3\n",
        )
        .unwrap();
        assert_eq!(c.rivals, 3);
        assert_eq!(c.rival.speed_factor, 0.3);
        assert_eq!(c.rival.steer_lookahead, Some(1.5));
        assert_eq!(c.rival.speed_point, SpeedPoint::Nearest);
        assert_eq!(c.reward_speed, 8.0);
        assert!(c.timeout_is_terminal && c.shipped_raceline);
        assert_eq!(c.crashed_rivals, CrashedRivals::Coast);
        assert_eq!(c.grid_line, GridLine::XAxis);
        assert_eq!(c.wall_contact, WallContact::CentrePixel);
        assert_eq!(c.rival_contacts, RivalContacts::DecisionEnd);
        assert_eq!(
            (c.rival.wheelbase, c.rival.max_steer),
            (Some(0.329), Some(0.4))
        );
        assert!(c.ego_relaunch);
        assert!(!c.overtakes_last_step && c.progress_past_line && c.max_steer == 0.4);
        // a resolved config round-trips, preset included
        let text = toml::to_string(&c).unwrap();
        assert_eq!(RaceConfig::from_toml(&text).unwrap(), c);
        // the default scenario: the paper's runs' rival speed, the text's reward
        let d = RaceConfig::from_toml("").unwrap();
        assert_eq!(d, RaceConfig::default());
        assert_eq!(d.rival.speed_factor, 0.85);
        assert_eq!(d.start_grid, StartGrid::Spacing);
        assert_eq!(d.grid_line, GridLine::Raceline);
        assert_eq!(d.rival_contacts, RivalContacts::PerStep);
        assert_eq!((d.rival.wheelbase, d.rival.max_steer), (None, None));
        assert_eq!(d.grid_spacing("f1_gbr", 500.0), 4.0);
        assert_eq!(d.grid_spacing("generated:1", 500.0), 5.5);
        assert_eq!(c.grid_spacing("f1_esp", 500.0), 5.5);
        assert_eq!(d.step_reward_floor, None);
        for (text, key) in [
            ("preset = \"paper\"", "preset"),
            (
                "preset = \"paper-code\"\nreverse_limit = -1.0",
                "reverse_limit",
            ),
            ("[rival]\nsteer_lookahead = 0.0", "rival.steer_lookahead"),
            // beyond any car or map: 1e308 m of lookahead once hung the track check
            ("[rival]\nlookahead = 1e308", "rival.lookahead"),
            ("[rival]\nlookahead_gain = 1e308", "rival.lookahead_gain"),
            ("[rival]\nsteer_lookahead = 1e6", "rival.steer_lookahead"),
            ("max_speed = 1e308", "max_speed"),
            ("[rival]\nmax_speed = 500.0", "rival.max_speed"),
            ("[lidar]\nmax_range = 1e308", "lidar.max_range"),
            ("[rival]\nlaunch_below = -1.0", "rival.launch_below"),
            ("[rival]\nspeed_point = \"middle\"", "speed_point"),
            ("start_spacing = 0.0", "start_spacing"),
            (
                "[start_spacing_tracks]\nf1_esp = -4.0",
                "start_spacing_tracks.f1_esp",
            ),
            ("start_grid = \"x-axis\"", "start_grid"),
            ("crashed_rivals = \"remove\"", "crashed_rivals"),
            ("grid_line = \"outside\"", "grid_line"),
            ("rival_contacts = \"never\"", "rival_contacts"),
            ("wall_contact = \"pixel\"", "wall_contact"),
            ("[rival]\nwheelbase = 0.0", "rival.wheelbase"),
            (
                "preset = \"paper-code\"\n[rival]\nwheelbase = -0.3",
                "rival.wheelbase",
            ),
            ("[rival]\nmax_steer = -0.4", "rival.max_steer"),
            ("[rival]\nmax_steer = 2.0", "rival.max_steer"),
            ("overtakes_last_step = 1", "overtakes_last_step"),
            (
                "preset = \"paper-code\"\n[rival]\nspeed_pont = \"target\"",
                "speed_pont",
            ),
        ] {
            let err = RaceConfig::from_toml(text).unwrap_err().to_string();
            assert!(err.contains(key), "{text}: {err}");
        }
    }
}
