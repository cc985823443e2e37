//! Race configuration: the scenario, the ego's sensor and action mapping, and the rivals.
//!
//! Every struct rejects unknown keys and fills missing ones with the paper's values, so a TOML file
//! only names what it changes.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One head-to-head race scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RaceConfig {
    /// Number of rival cars, 0 to 7.
    pub rivals: usize,
    /// Gap between consecutive cars on the starting line, as a fraction of the lap (paper code: 0.05).
    pub start_gap: f64,
    /// Ego speed range top: action `a_1 ∈ [-1, 1]` maps onto `[min_speed, max_speed]` m/s.
    pub max_speed: f64,
    /// Ego speed range bottom (paper: 0; the paper's code used 1).
    pub min_speed: f64,
    /// Ego steering range: `a_0 ∈ [-1, 1]` maps onto `[-max_steer, max_steer]` rad, negative = left.
    pub max_steer: f64,
    /// Speed that normalises the reward's `v / v_max` term (m/s).
    pub reward_speed: f64,
    /// Physics steps (0.01 s) per agent decision.
    pub physics_steps_per_action: usize,
    /// Steering command delay in physics steps (f1tenth_gym: 2).
    pub steer_delay: usize,
    /// Episode time limit in seconds; reaching it truncates the episode.
    pub max_time: f64,
    /// The ego's LiDAR.
    pub lidar: LidarConfig,
    /// The rivals' driver.
    pub rival: RivalConfig,
}

impl Default for RaceConfig {
    fn default() -> Self {
        Self {
            rivals: 1,
            start_gap: 0.05,
            max_speed: 6.0,
            min_speed: 0.0,
            max_steer: 0.4189,
            reward_speed: 6.0,
            physics_steps_per_action: 10,
            steer_delay: 2,
            max_time: 240.0,
            lidar: LidarConfig::default(),
            rival: RivalConfig::default(),
        }
    }
}

impl RaceConfig {
    /// Checks ranges; the message names the key and its valid range.
    pub fn validate(&self) -> Result<(), String> {
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
        ];
        for (k, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{k} = {v} must be a positive number"));
            }
        }
        if self.rivals > 7 {
            return Err(format!("rivals = {} must be 0 to 7", self.rivals));
        }
        if !(self.min_speed >= 0.0 && self.min_speed < self.max_speed) {
            return Err(format!(
                "min_speed = {} must be in [0, max_speed = {})",
                self.min_speed, self.max_speed
            ));
        }
        if !(self.start_gap > 0.0 && self.start_gap * self.rivals as f64 <= 0.9) {
            return Err(format!(
                "start_gap = {} must be positive and leave the {} rivals within 90% of the lap",
                self.start_gap, self.rivals
            ));
        }
        if self.physics_steps_per_action == 0 {
            return Err("physics_steps_per_action must be at least 1".into());
        }
        if self.lidar.beams == 0 || !(0.0..=1.0).contains(&self.lidar.noise_sd) {
            return Err(format!(
                "lidar.beams = {} must be at least 1 and lidar.noise_sd = {} in [0, 1] m",
                self.lidar.beams, self.lidar.noise_sd
            ));
        }
        Ok(())
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

/// The rivals' pure-pursuit driver and how the context scales it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RivalConfig {
    /// Fraction of the raceline speed driven (paper: 0.3, "reduced by 70%"; its code: 0.8).
    pub speed_factor: f64,
    /// Raceline speeds are capped at this before scaling (paper code: the ego's max speed, 6 m/s).
    pub max_speed: f64,
    /// Pure-pursuit lookahead at standstill (m): the target point and the steering law
    /// `δ = atan(2 L y / L_d²)` use `L_d = (lookahead + lookahead_gain · v)(1 + λ_θ c_θ)`.
    pub lookahead: f64,
    /// Growth of the lookahead with speed (s; the paper's code: 0.1).
    pub lookahead_gain: f64,
    /// Context gains used on tracks without an entry in `tracks`.
    pub gains: ContextGains,
    /// Context gains per track name (paper code: λ_θ = 0.4 on f1_esp and f1_gbr, 0.3 on f1_mco).
    pub tracks: BTreeMap<String, ContextGains>,
}

impl Default for RivalConfig {
    fn default() -> Self {
        let paper = |lambda_theta| ContextGains {
            lambda_v: 1.0,
            lambda_theta,
        };
        Self {
            speed_factor: 0.3,
            max_speed: 6.0,
            lookahead: 1.0,
            lookahead_gain: 0.1,
            gains: paper(0.4),
            tracks: BTreeMap::from([
                ("f1_esp".to_string(), paper(0.4)),
                ("f1_gbr".to_string(), paper(0.4)),
                ("f1_mco".to_string(), paper(0.3)),
            ]),
        }
    }
}

impl RivalConfig {
    /// The gains for a track.
    pub fn gains_for(&self, track: &str) -> ContextGains {
        self.tracks.get(track).copied().unwrap_or(self.gains)
    }
}

/// How strongly the context scales rival speed (`1 + λ_v c_v`) and lookahead (`1 + λ_θ c_θ`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContextGains {
    /// λ_v.
    pub lambda_v: f64,
    /// λ_θ.
    pub lambda_theta: f64,
}

/// The replay process's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayOptions {
    /// Steps held, shared equally between the actors' streams.
    pub capacity: usize,
    /// Steps inserted before the first batch is sampled.
    pub min_fill: usize,
    /// Sampled steps allowed per inserted step (a `B x T` sequence batch samples `B·T` steps,
    /// a transition batch `B`); 0 disables the ratio and only `min_fill` holds.
    pub samples_per_insert: f64,
    /// How far, in inserted steps, the ratio may drift either way before sampling (or
    /// inserting) waits, as Reverb's `error_buffer` (in samples: this times the ratio).
    pub error_buffer_steps: f64,
    /// Seconds between periodic snapshots; 0 snapshots only on shutdown.
    pub snapshot_every_secs: u64,
    /// Snapshot file; none disables snapshots.
    pub snapshot_path: Option<std::path::PathBuf>,
    /// Seed of the sampling RNG.
    pub seed: u64,
    /// Largest batch payload in floats.
    pub max_batch_floats: usize,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            capacity: 1_000_000,
            min_fill: 1000,
            samples_per_insert: 0.0,
            error_buffer_steps: 1000.0,
            snapshot_every_secs: 60,
            snapshot_path: None,
            seed: 0,
            max_batch_floats: crate::ipc::DEFAULT_MAX_BATCH_FLOATS,
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
        assert!(bad.validate().unwrap_err().contains("rivals = 9"));
        assert_eq!(RivalConfig::default().gains_for("f1_mco").lambda_theta, 0.3);
        assert_eq!(
            RivalConfig::default().gains_for("generated:3").lambda_theta,
            0.4
        );
    }
}
