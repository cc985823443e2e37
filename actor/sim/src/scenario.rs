//! Where an evaluation races: the track, the race, its rivals and the training context range
//! that splits the contexts in and out of distribution. A trained agent whose run is known
//! races in its run's scenario; any other policy in the protocol's reference scenario
//! ([`REFERENCE_TRACK`], [`REFERENCE_RIVALS`], [`TRAIN_RANGE`], the default race). Whatever the
//! caller gives wins, in this order from the bottom up:
//!
//! 1. the race: the run's (its every key), or, given, a race table (a race config file's) in
//!    its place; neither: the default race;
//! 2. race keys laid over it key by key (tables merged key by key, [`merge_tables`]);
//! 3. the rivals: given, else the run's, else [`REFERENCE_RIVALS`];
//! 4. the track and the training range: given, else the run's, else the reference's.
//!
//! `ctxrace eval` and Python's `ctxrace.evaluate` both resolve their arguments here.

use crate::eval_dir::{REFERENCE_RIVALS, REFERENCE_TRACK, TRAIN_RANGE};
use ctxrace_config::preset::merge_tables;
use ctxrace_config::{ExperimentConfig, RaceConfig, RaceConfigError};

/// What the caller of an evaluation chose; `None` (or no keys): not chosen.
#[derive(Clone, Debug, Default)]
pub struct ScenarioChoice {
    /// The track (a name, a map yaml or `generated:SEED`).
    pub track: Option<String>,
    /// Rival cars.
    pub rivals: Option<usize>,
    /// Half-width of the training contexts, which splits the grid in and out of distribution.
    pub train_range: Option<f64>,
    /// A race table (a race config file's) in place of the run's race.
    pub race: Option<toml::Table>,
    /// Race keys laid over the race key by key.
    pub race_keys: toml::Table,
}

/// Where an evaluation races, resolved ([`EvalScenario::resolve`]).
#[derive(Clone, Debug, PartialEq)]
pub struct EvalScenario {
    /// The track.
    pub track: String,
    /// The race, its rivals included.
    pub race: RaceConfig,
    /// Half-width of the training contexts.
    pub train_range: f64,
}

impl EvalScenario {
    /// The scenario of `choice` over the trained run `run` (its recorded experiment; `None`
    /// for a reference policy or a checkpoint without its run), as the module's rules say.
    pub fn resolve(
        run: Option<&ExperimentConfig>,
        choice: ScenarioChoice,
    ) -> Result<Self, RaceConfigError> {
        let mut race = match (choice.race, run) {
            (None, Some(run)) if choice.race_keys.is_empty() => run.race.clone(),
            (None, None) if choice.race_keys.is_empty() => RaceConfig::default(),
            (table, run) => {
                let base = match (table, run) {
                    (Some(table), _) => table,
                    (None, Some(run)) => race_table(&run.race),
                    (None, None) => toml::Table::new(),
                };
                RaceConfig::from_table(merge_tables(base, choice.race_keys))?
            }
        };
        race.rivals = choice
            .rivals
            .or(run.map(|r| r.race.rivals))
            .unwrap_or(REFERENCE_RIVALS);
        race.validate()?;
        Ok(Self {
            track: choice
                .track
                .or(run.map(|r| r.track.clone()))
                .unwrap_or_else(|| REFERENCE_TRACK.into()),
            race,
            train_range: choice
                .train_range
                .or(run.map(|r| r.train.context_range))
                .unwrap_or(TRAIN_RANGE),
        })
    }
}

/// `race` as a table of its every key: read back with [`RaceConfig::from_table`], it is `race`.
fn race_table(race: &RaceConfig) -> toml::Table {
    toml::Table::try_from(race).expect("a race config is a TOML table")
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_config::RacePreset;

    fn run() -> ExperimentConfig {
        let mut run = ExperimentConfig {
            track: "f1_gbr".into(),
            ..ExperimentConfig::default()
        };
        run.race.rivals = 1;
        run.race.rival.speed_factor = 0.7;
        run.train.context_range = 0.1;
        run
    }

    fn keys(text: &str) -> toml::Table {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn a_reference_policy_races_the_reference_scenario() {
        let s = EvalScenario::resolve(None, ScenarioChoice::default()).unwrap();
        assert_eq!(s.track, REFERENCE_TRACK);
        assert_eq!(s.race.rivals, REFERENCE_RIVALS);
        assert_eq!(s.train_range, TRAIN_RANGE);
        assert_eq!(
            s.race,
            RaceConfig {
                rivals: REFERENCE_RIVALS,
                ..RaceConfig::default()
            }
        );
    }

    #[test]
    fn a_trained_agent_races_its_runs_scenario_and_what_is_given_wins() {
        let run = run();
        let s = EvalScenario::resolve(Some(&run), ScenarioChoice::default()).unwrap();
        assert_eq!((s.track.as_str(), s.train_range), ("f1_gbr", 0.1));
        assert_eq!(s.race, run.race);
        let given = ScenarioChoice {
            track: Some("f1_esp".into()),
            rivals: Some(2),
            train_range: Some(0.2),
            race_keys: keys("[lidar]\nmax_range = 20.0"),
            ..ScenarioChoice::default()
        };
        let s = EvalScenario::resolve(Some(&run), given).unwrap();
        assert_eq!((s.track.as_str(), s.train_range), ("f1_esp", 0.2));
        assert_eq!(s.race.rivals, 2);
        assert_eq!(s.race.lidar.max_range, 20.0);
        // the run's other keys stay, those of a table merged key by key too
        assert_eq!(s.race.rival.speed_factor, 0.7);
        assert_eq!(s.race.lidar.beams, run.race.lidar.beams);
    }

    #[test]
    fn a_race_table_replaces_the_runs_race_but_not_its_rivals() {
        let run = run();
        let given = ScenarioChoice {
            race: Some(keys("preset = \"paper-code\"")),
            ..ScenarioChoice::default()
        };
        let s = EvalScenario::resolve(Some(&run), given).unwrap();
        assert_eq!(s.race.preset, RacePreset::PaperCode);
        assert_eq!(s.race.rival.steer_lookahead, Some(1.5));
        assert_eq!(
            s.race.rival.speed_factor,
            RacePreset::PaperCode.config().rival.speed_factor
        );
        assert_eq!(s.race.rivals, 1);
        // without a run, a race table's rivals give way to the reference's
        let given = ScenarioChoice {
            race: Some(keys("rivals = 1")),
            ..ScenarioChoice::default()
        };
        let s = EvalScenario::resolve(None, given).unwrap();
        assert_eq!(s.race.rivals, REFERENCE_RIVALS);
    }

    #[test]
    fn every_preset_reads_back_from_its_table() {
        for preset in [RacePreset::Default, RacePreset::PaperCode] {
            let race = preset.config();
            assert_eq!(RaceConfig::from_table(race_table(&race)).unwrap(), race);
        }
    }

    #[test]
    fn a_bad_key_is_refused_naming_it() {
        let given = ScenarioChoice {
            race_keys: keys("[lidar]\nbeems = 3"),
            ..ScenarioChoice::default()
        };
        let err = EvalScenario::resolve(Some(&run()), given).unwrap_err();
        assert!(err.to_string().contains("beems"), "{err}");
    }
}
