//! Configurations read over a named preset: a TOML table names its `preset` (or none, the
//! default), the preset's full configuration is the base, and the table's keys are laid over it
//! ([`merge_tables`]), so that a file only names what it changes (the race's and the
//! agent's presets).

use serde::{de::DeserializeOwned, Serialize};
use std::fmt::Debug;

/// Why a table cannot be read over its preset: each names the key and how to fix it.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PresetError {
    /// The `preset` key names no preset.
    #[error("preset: {0} (use \"default\" or \"paper-code\")")]
    Unknown(toml::de::Error),
    /// The preset's own configuration could not be written as a table.
    #[error("serialising the {preset} preset: {cause}")]
    Serialise {
        /// The preset (as `Debug` names it).
        preset: String,
        /// Why.
        cause: toml::ser::Error,
    },
    /// A key the configuration does not take, or a value of the wrong type (the message names
    /// the key).
    #[error("{}", .0.message())]
    Value(toml::de::Error),
}

/// `over` laid on `base`: keys of `over` replace those of `base`, tables merge key by key.
pub fn merge_tables(mut base: toml::Table, over: toml::Table) -> toml::Table {
    for (key, value) in over {
        let merged = match (base.remove(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => {
                toml::Value::Table(merge_tables(b, o))
            }
            (_, v) => v,
        };
        base.insert(key, merged);
    }
    base
}

/// The configuration of `table` over its preset `P` (`P::default()` when it names none), the
/// preset's configuration given by `config_of`; unknown keys and bad values are errors naming the
/// key. Validation is the caller's.
pub fn resolve<P, T>(table: toml::Table, config_of: fn(P) -> T) -> Result<T, PresetError>
where
    P: DeserializeOwned + Default + Debug + Copy,
    T: Serialize + DeserializeOwned,
{
    let preset = match table.get("preset") {
        Some(v) => v.clone().try_into::<P>().map_err(PresetError::Unknown)?,
        None => P::default(),
    };
    let base =
        toml::Table::try_from(config_of(preset)).map_err(|cause| PresetError::Serialise {
            preset: format!("{preset:?}"),
            cause,
        })?;
    toml::Value::Table(merge_tables(base, table))
        .try_into()
        .map_err(PresetError::Value)
}
