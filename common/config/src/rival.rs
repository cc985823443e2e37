//! The rivals' driver and how the context scales it (`[race.rival]`): pure pursuit on the
//! raceline, follow-the-gap on the rival's own scan (`[race.rival.follow_the_gap]`) or a trained
//! agent, each scaled by the context's gains.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Where on the raceline a rival reads the speed it drives.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SpeedPoint {
    /// The raceline vertex nearest the car (the paper's code).
    Nearest,
    /// The pure-pursuit target point (the paper's text: "the speed associated with the
    /// lookahead point").
    Target,
    /// The slowest raceline speed between the nearest point and the target: brakes as early as
    /// `target` and accelerates as late as `nearest`.
    #[default]
    SlowestAhead,
}

/// Which driver plans each rival's commands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RivalDriverKind {
    /// Pure pursuit on the raceline (the paper's rivals; the keys of `[rival]` other than
    /// `follow_the_gap`).
    #[default]
    PurePursuit,
    /// Follow-the-gap on the rival's own LiDAR scan, reactive and raceline-free (the keys of
    /// `[rival.follow_the_gap]`).
    FollowTheGap,
    /// A trained ctxrace agent acting on the rival's own LiDAR scan and the race's context
    /// (`policy`, `policy_deterministic`; its speed scaled by `1 + λ_v c_v`).
    Policy,
}

impl RivalDriverKind {
    /// Every driver.
    pub const ALL: [Self; 3] = [Self::PurePursuit, Self::FollowTheGap, Self::Policy];

    /// Its name in configs (`driver = "..."`), on the command line and in titles.
    pub fn name(self) -> &'static str {
        match self {
            Self::PurePursuit => "pure-pursuit",
            Self::FollowTheGap => "follow-the-gap",
            Self::Policy => "policy",
        }
    }

    /// Whether it looks at the other cars: then its rival's command needs their boxes.
    pub fn sees_cars(self) -> bool {
        match self {
            Self::PurePursuit => false,
            Self::FollowTheGap | Self::Policy => true,
        }
    }
}

impl std::fmt::Display for RivalDriverKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Where a follow-the-gap driver aims inside the largest gap.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GapAim {
    /// The gap's middle beam (Sezer & Gokasan's gap centre).
    Middle,
    /// The gap's farthest point: the middle of its longest run of beams at the gap's largest
    /// range (F1TENTH's "best point").
    #[default]
    Farthest,
}

/// Follow-the-gap (Sezer & Gokasan 2012, in the form the F1TENTH course teaches), planning from
/// an exact LiDAR scan of the car's own pose (no noise, reaching `max_range`) that sees the walls
/// and every other car.
///
/// Each decision, with beam `k` at angle `α_k` from the heading (left positive) and range `r_k`:
///
/// 1. **Preprocess**: `r̂_k = min(r_k, range_clip)`, then a centred moving average over
///    `smoothing` beams (1: none; the window is cut at the ends of the scan).
/// 2. **Safety bubble**: with `r* = r̂_{k*}` the closest smoothed range, every beam that crosses
///    the line through that point, square to its beam, within `bubble_radius` `R` of it,
///    `|α_k − α_{k*}| ≤ atan(R / r*)`, is set to 0.
/// 3. **Largest gap**: the longest run of consecutive beams with `r̂_k > free_range`; of equally
///    long runs, the one whose middle is nearest the heading. No free beam: the best point is
///    the farthest beam.
/// 4. **Best point** `α_t`: the gap's middle or its farthest point ([`GapAim`]).
/// 5. **Steering**: `δ = clamp(steer_gain · α_t / (1 + λ_θ c_θ), ±δ_max)`. Pure pursuit steers
///    `δ ≈ 2 L α / L_d` for small angles, so scaling its lookahead `L_d` by `1 + λ_θ c_θ`, as
///    the context does to the pure-pursuit rival, is dividing this gain by it.
/// 6. **Speed** from the context-free steering `δ_0 = clamp(steer_gain · α_t, ±δ_max)`:
///    `v = v_s − (v_s − v_c) · min(|δ_0| / δ_c, 1)` (`straight_speed` `v_s`, `corner_speed`
///    `v_c`, `corner_steer` `δ_c`), capped by the braking distance on the way to the best point,
///    `v ≤ √(2 a_b · max(0, d − stop_margin))` (`brake_decel` `a_b`, 0 disables; `d` the
///    distance along the best point's direction to the nearest scan point within half the car's
///    width of that line, unclipped, `max_range` when none), and then times `1 + λ_v c_v`.
///
/// With the defaults a car alone laps f1_esp, f1_gbr, f1_mco, f1_aut, Monza, Oschersleben,
/// Spielberg and generated tracks without touching a wall at the zero context, and a rival laps
/// both paper maps from each grid place in all 49 evaluation contexts (f1_mco: 146 of 147).
/// The short `range_clip` matters: at 3.5 or 5 m, aiming at points farther round the corners,
/// the car cut the inside of f1_esp's first right-hander into the wall.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FollowTheGapConfig {
    /// Beams of the driver's scan, spread evenly over `fov_deg`, ends included.
    pub beams: usize,
    /// Field of view of the scan (degrees), centred on the heading.
    pub fov_deg: f64,
    /// Reach of the scan (m): the braking distance is measured up to it.
    pub max_range: f64,
    /// Ranges are capped at this before the gap is planned (m): farther free space counts the
    /// same, so the best point is never far round a corner.
    pub range_clip: f64,
    /// Width of the centred moving average over the clipped ranges (beams; 1: no smoothing).
    pub smoothing: usize,
    /// Radius `R` of the safety bubble around the closest point (m).
    pub bubble_radius: f64,
    /// A beam is free when its clipped, smoothed range is above this (m).
    pub free_range: f64,
    /// The best point in the largest gap.
    pub aim: GapAim,
    /// Steering per radian of the best point's angle.
    pub steer_gain: f64,
    /// Speed with straight wheels (m/s), before the context.
    pub straight_speed: f64,
    /// Speed at `corner_steer` and beyond (m/s), before the context.
    pub corner_speed: f64,
    /// Steering angle (rad) from which `corner_speed` is driven.
    pub corner_steer: f64,
    /// Deceleration planned to stop before what lies on the way (m/s²): lower anticipates
    /// corners earlier; 0 disables the cap.
    pub brake_decel: f64,
    /// Distance kept to what lies on the way when braking (m).
    pub stop_margin: f64,
}

impl Default for FollowTheGapConfig {
    fn default() -> Self {
        Self {
            beams: 108,
            fov_deg: 180.0,
            max_range: 10.0,
            range_clip: 2.5,
            smoothing: 5,
            bubble_radius: 1.0,
            free_range: 1.0,
            aim: GapAim::Farthest,
            steer_gain: 1.0,
            straight_speed: 5.0,
            corner_speed: 2.5,
            corner_steer: 0.3,
            brake_decel: 2.0,
            stop_margin: 0.5,
        }
    }
}

/// The rivals' driver and how the context scales it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RivalConfig {
    /// Which driver plans the rivals' commands: `pure-pursuit` (the default, the paper's),
    /// `follow-the-gap` (reactive, from each rival's own scan; it reads `follow_the_gap` and the
    /// context gains, not the pure-pursuit keys) or `policy` (a trained agent: `policy`).
    pub driver: RivalDriverKind,
    /// With `driver = "policy"`: the agent every rival is, a run folder (its best checkpoint),
    /// one checkpoint folder, or a policy trained elsewhere as an MLP file (`*.safetensors`,
    /// `ctxrace_nn::policy::mlp`), relative to the working directory. Each rival acts
    /// on its own scan (the ego and the other rivals in it) and the race's context, as the agent
    /// was trained to act as the ego; its speed command is scaled by `1 + λ_v c_v`.
    pub policy: Option<std::path::PathBuf>,
    /// With `driver = "policy"`: the rivals take the mode of each distribution instead of
    /// sampling it (seeded per episode and rival).
    pub policy_deterministic: bool,
    /// Fraction of the raceline speed driven (`slow_down`: 0.85 in the code that produced the
    /// paper's tables, c0fd903 and the development line before it; 0.8 in the release; its text
    /// says "reduced by 70%", i.e. 0.3, which its code never used).
    pub speed_factor: f64,
    /// Raceline speeds are capped at this before scaling (paper code: the ego's max speed, 6 m/s).
    pub max_speed: f64,
    /// Distance at standstill (m) at which the target point is searched: `lookahead +
    /// lookahead_gain · v`.
    pub lookahead: f64,
    /// Growth of the search distance with speed (s; the paper's code: 0.1).
    pub lookahead_gain: f64,
    /// The steering law `δ = atan(2 L y / L_d²)` uses this fixed `L_d` (m) times
    /// `1 + λ_θ c_θ` (the paper's code: 1.5, while it searched the target at `1 + 0.1 v`
    /// unscaled); none: `L_d` is the target's search distance, and the context scales both.
    pub steer_lookahead: Option<f64>,
    /// The target is the raceline vertex that starts the segment where the search circle cuts
    /// it (the paper's code), not the cut point itself.
    pub target_at_vertex: bool,
    /// Where the raceline speed is read.
    pub speed_point: SpeedPoint,
    /// Below this speed (m/s) the rival drives straight at `launch_speed` instead of pursuing
    /// (the paper's code: 1); 0 disables it.
    pub launch_below: f64,
    /// Speed commanded below `launch_below`, unscaled (m/s; the paper's code: 4).
    pub launch_speed: f64,
    /// A rival told to drive faster than its line (`speed_factor (1 + λ_v c_v) > 1`) that is
    /// more than this far off the line (m) lifts to the line's speed until it is back; 0
    /// disables it (the paper's code).
    pub lift_off_line: f64,
    /// Wheelbase `L` of the pure-pursuit steering law (m); none: the car's `l_f + l_r`
    /// (0.3302). The paper's code: 0.329, `l_f + l_r` of its planners' config_file.yaml (0.158
    /// + 0.171), not its gym's car.
    pub wheelbase: Option<f64>,
    /// Largest steering angle the rivals' drivers command (rad); none: the car's limit
    /// (0.4189). The paper's code: 0.4, its planners' `max_steer`.
    pub max_steer: Option<f64>,
    /// Context gains used on tracks without an entry in `tracks`.
    pub gains: ContextGains,
    /// Context gains per track name (paper code: λ_θ = 0.4 on f1_esp and f1_gbr, 0.3 on f1_mco).
    pub tracks: BTreeMap<String, ContextGains>,
    /// The follow-the-gap driver's parameters (`driver = "follow-the-gap"`, and the
    /// `follow-the-gap` reference ego).
    pub follow_the_gap: FollowTheGapConfig,
}

impl Default for RivalConfig {
    fn default() -> Self {
        let paper = |lambda_theta| ContextGains {
            lambda_v: 1.0,
            lambda_theta,
        };
        Self {
            driver: RivalDriverKind::default(),
            policy: None,
            policy_deterministic: false,
            speed_factor: 0.85,
            max_speed: 6.0,
            lookahead: 1.0,
            lookahead_gain: 0.1,
            steer_lookahead: None,
            target_at_vertex: false,
            speed_point: SpeedPoint::default(),
            launch_below: 0.0,
            launch_speed: 4.0,
            lift_off_line: 0.15,
            wheelbase: None,
            max_steer: None,
            gains: paper(0.4),
            tracks: BTreeMap::from([
                ("f1_esp".to_string(), paper(0.4)),
                ("f1_gbr".to_string(), paper(0.4)),
                ("f1_mco".to_string(), paper(0.3)),
            ]),
            follow_the_gap: FollowTheGapConfig::default(),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::RaceConfig;

    #[test]
    fn a_rival_drivers_name_is_the_one_configs_use() {
        for kind in RivalDriverKind::ALL {
            let value = toml::Value::try_from(kind).unwrap();
            assert_eq!(value.as_str(), Some(kind.name()));
            assert_eq!(kind.to_string(), kind.name());
        }
    }

    #[test]
    fn the_rival_driver_is_a_key_with_its_parameters_validated_by_name() {
        assert_eq!(
            RaceConfig::default().rival.driver,
            RivalDriverKind::PurePursuit
        );
        let c = RaceConfig::from_toml(
            "[rival]\ndriver = \"follow-the-gap\"\n[rival.follow_the_gap]\nbubble_radius = 0.8\n",
        )
        .unwrap();
        assert_eq!(c.rival.driver, RivalDriverKind::FollowTheGap);
        assert_eq!(c.rival.follow_the_gap.bubble_radius, 0.8);
        assert_eq!(c.rival.follow_the_gap.range_clip, 2.5);
        // serialised with the other keys, and read back
        let text = toml::to_string(&c).unwrap();
        assert!(text.contains("driver = \"follow-the-gap\""), "{text}");
        assert!(text.contains("[rival.follow_the_gap]"), "{text}");
        assert_eq!(RaceConfig::from_toml(&text).unwrap(), c);
        for preset in ["", "preset = \"paper-code\"\n"] {
            let err =
                RaceConfig::from_toml(&format!("{preset}[rival]\ndriver = \"wall-hugger\"\n"))
                    .unwrap_err()
                    .to_string();
            for part in ["driver", "wall-hugger", "pure-pursuit", "follow-the-gap"] {
                assert!(err.contains(part), "{preset}: {err}");
            }
        }
        for (text, key) in [
            ("bubble_radius = -0.1", "rival.follow_the_gap.bubble_radius"),
            ("range_clip = 0.0", "rival.follow_the_gap.range_clip"),
            ("beams = 1", "rival.follow_the_gap.beams"),
            ("smoothing = 0", "rival.follow_the_gap.smoothing"),
            ("fov_deg = 400.0", "rival.follow_the_gap.fov_deg"),
            ("free_range = 3.0", "rival.follow_the_gap.free_range"),
            ("corner_speed = 9.0", "rival.follow_the_gap.corner_speed"),
            ("steer_gain = nan", "rival.follow_the_gap.steer_gain"),
            ("aim = \"nearest\"", "aim"),
            ("bubble = 1.0", "bubble"),
        ] {
            let err = RaceConfig::from_toml(&format!("[rival.follow_the_gap]\n{text}\n"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{text}: {err}");
        }
    }
}
