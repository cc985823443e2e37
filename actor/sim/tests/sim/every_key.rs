//! Every numeric key of an experiment, one at a time, set to each of the values no experiment
//! means (0, −1, ∞, −0.0, 1e308, the largest integer): the configuration is refused, or what
//! `ctxrace train` does before any process starts (the checks of the machine's memory and
//! cores, the track check of the rivals, a race) ends within a time bound. Never a panic, never
//! a hang. `EVERY_KEY_LIST=1` lists the values that raced (`-- --nocapture`).

use ctxrace_config::resources::{check_machine, Machine};
use ctxrace_config::{AgentConfig, Context, ExperimentConfig, RaceConfig};
use ctxrace_sim::track_check::{check_track, CheckPlan};
use ctxrace_sim::RaceEnv;
use ctxrace_tracks::{Track, TrackOptions};
use std::sync::{mpsc, Arc};
use std::time::Duration;

/// The longest a configuration may take to be refused or to race.
const TIME_BOUND: Duration = Duration::from_secs(20);
/// Decisions raced with an accepted configuration.
const DECISIONS: usize = 30;

/// The values no experiment means, as TOML writes them.
fn hostile_values() -> Vec<toml::Value> {
    vec![
        toml::Value::Integer(0),
        toml::Value::Integer(-1),
        toml::Value::Float(f64::INFINITY),
        toml::Value::Float(-0.0),
        toml::Value::Float(1e308),
        toml::Value::Integer(i64::MAX),
    ]
}

/// The dotted paths of every number in `table` (arrays left out).
fn numeric_paths(table: &toml::Table, prefix: &str, out: &mut Vec<String>) {
    for (key, value) in table {
        let path = if prefix.is_empty() {
            key.clone()
        } else {
            format!("{prefix}.{key}")
        };
        match value {
            toml::Value::Integer(_) | toml::Value::Float(_) => out.push(path),
            toml::Value::Table(t) => numeric_paths(t, &path, out),
            _ => {}
        }
    }
}

/// `table` with the number at `path` replaced by `value`.
fn with_value(mut table: toml::Table, path: &str, value: toml::Value) -> toml::Table {
    let mut keys: Vec<&str> = path.split('.').collect();
    let last = keys.pop().expect("a path has a key");
    let mut t = &mut table;
    for k in keys {
        t = t
            .get_mut(k)
            .and_then(toml::Value::as_table_mut)
            .expect("the path's tables exist");
    }
    t.insert(last.into(), value);
    table
}

/// The two experiments whose keys are drawn from: ctxrace's defaults and the paper code's
/// presets (whose optional keys are set), both on a procedural track.
fn bases() -> Vec<toml::Table> {
    let paper = ExperimentConfig {
        race: RaceConfig::paper_code(),
        agent: AgentConfig::paper_code(),
        ..ExperimentConfig::default()
    };
    [ExperimentConfig::default(), paper]
        .into_iter()
        .map(|mut cfg| {
            cfg.track = "generated:0".into();
            toml::from_str(&cfg.to_toml().unwrap()).unwrap()
        })
        .collect()
}

/// What `train` does with `text` before a process starts, then a short race; `Ok(false)` when
/// the configuration is refused, `Ok(true)` when it raced.
fn launch(text: &str, track: Arc<Track>) -> Result<bool, String> {
    let Ok(cfg) = ExperimentConfig::from_toml(text, "probe") else {
        return Ok(false);
    };
    let machine = Machine {
        memory: 24 << 30,
        cores: 2,
    };
    if cfg.validate_run(1).is_err() || check_machine(&cfg, 1, 0, &machine, false).is_err() {
        return Ok(false);
    }
    let plan = CheckPlan {
        grid: 1,
        range: cfg.train.context_range,
        places: cfg.race.rivals.min(1),
    };
    if check_track(track.clone(), &cfg.race, plan).is_err() {
        return Ok(false);
    }
    let Ok(mut env) = RaceEnv::new(track, cfg.race.clone()) else {
        return Ok(false);
    };
    env.reset(0, Context::new(0.1, -0.1).map_err(|e| e.to_string())?);
    for k in 0..DECISIONS {
        let action = [((k % 7) as f64 / 3.0) - 1.0, 0.8];
        let step = env.step(action).map_err(|e| format!("step {k}: {e}"))?;
        if step.terminated || step.truncated {
            env.reset(k as u64, Context::default());
        }
    }
    Ok(true)
}

#[test]
fn every_numeric_key_at_every_hostile_value_is_refused_or_races_in_time() {
    let track = Arc::new(Track::load("generated:0", &TrackOptions::default()).unwrap());
    let (mut cases, mut raced, mut keys) = (0, 0, std::collections::BTreeSet::new());
    let mut failures = Vec::new();
    for base in bases() {
        let mut paths = Vec::new();
        numeric_paths(&base, "", &mut paths);
        for path in paths {
            keys.insert(path.clone());
            for value in hostile_values() {
                let table = with_value(base.clone(), &path, value.clone());
                let text = toml::to_string(&table).unwrap();
                let (tx, rx) = mpsc::channel();
                let track = track.clone();
                std::thread::spawn(move || tx.send(launch(&text, track)).ok());
                cases += 1;
                match rx.recv_timeout(TIME_BOUND) {
                    Ok(Ok(true)) => {
                        raced += 1;
                        if std::env::var_os("EVERY_KEY_LIST").is_some() {
                            eprintln!("raced: {path} = {value}");
                        }
                    }
                    Ok(Ok(false)) => {}
                    Ok(Err(e)) => failures.push(format!("{path} = {value}: {e}")),
                    Err(mpsc::RecvTimeoutError::Timeout) => {
                        failures.push(format!("{path} = {value}: no end in {TIME_BOUND:?}"))
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => {
                        failures.push(format!("{path} = {value}: panicked"))
                    }
                }
            }
        }
    }
    eprintln!(
        "{} numeric keys, {cases} cases: {raced} raced, {} refused, {} failed",
        keys.len(),
        cases - raced - failures.len(),
        failures.len()
    );
    assert!(keys.len() > 100, "only {} numeric keys found", keys.len());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
