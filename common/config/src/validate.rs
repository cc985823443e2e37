//! Checks of configuration values whose messages name the key, its value and the fix: every
//! float of a configuration finite ([`finite_floats`]) and within ±[`MAX_FLOAT`]
//! ([`bounded_floats`]), walks over its serialized form that report the key's path, tables of
//! per-track overrides included, and ranges ([`in_range`]),
//! both refusing with a [`ValueError`]. [`ConfigError`] marks an error that a restarted process
//! would meet again; [`Causes`] prints an error with its causes, for the libraries' log lines.

use serde::Serialize;
use std::fmt::Display;
use std::ops::{Bound, RangeBounds};

/// Exit code of a process that failed with a [`ConfigError`] (`EX_CONFIG` of sysexits.h): the
/// launcher does not restart it.
pub const CONFIG_EXIT_CODE: i32 = 78;

/// An error that a restart would meet again (a bad value in the run's configuration, a damaged
/// run file): a process failing with it (anywhere in its chain of causes) exits with
/// [`CONFIG_EXIT_CODE`], and the launcher stops the run at once with the process's reason
/// instead of restarting it. It is its cause, marked: it shows the cause's message and chains
/// the cause's own sources.
#[derive(Debug, thiserror::Error)]
#[error(transparent)]
pub struct ConfigError(Box<dyn std::error::Error + Send + Sync>);

impl ConfigError {
    /// `cause` (any error, or a message) marked as one a restart would meet again.
    pub fn new(cause: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> Self {
        Self(cause.into())
    }
}

/// An error with its causes (its [`std::error::Error::source`] chain), printed as the binary
/// prints an error, `what: cause: cause`: for a library's log line, where `{error}` would print
/// the first link only.
#[derive(Clone, Copy, Debug)]
pub struct Causes<'a>(pub &'a (dyn std::error::Error + 'static));

impl Display for Causes<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut cause = self.0.source();
        while let Some(e) = cause {
            write!(f, ": {e}")?;
            cause = e.source();
        }
        Ok(())
    }
}

/// The largest magnitude of any float of a configuration: no speed, range, time, gain,
/// learning rate or temperature an experiment means comes near it (the largest ctxrace's
/// configs hold are a few thousand), while a value beyond it overflows what it scales. Each
/// key's own range, where it has one, is narrower.
pub const MAX_FLOAT: f64 = 1e6;

/// Why a configuration value is refused: each names the key (by its path), the value and the
/// fix.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ValueError {
    /// A float that is not finite.
    #[error(
        "{key} = {} is not a finite number; give a finite value{}",
        toml::Value::Float(*.value),
        .default.as_ref().map_or(String::new(), |d| format!(" (the default is {d})"))
    )]
    NotFinite {
        /// The key's path (`race.rival.gains.lambda_v`).
        key: String,
        /// Its value.
        value: f64,
        /// The value the defaults hold at that path, when they hold one.
        default: Option<toml::Value>,
    },
    /// A float beyond ±[`MAX_FLOAT`].
    #[error(
        "{key} = {value:e} is beyond ±{MAX_FLOAT:e}, which no experiment means; give a value of \
         the key's scale{}",
        .default.as_ref().map_or(String::new(), |d| format!(" (the default is {d})"))
    )]
    Implausible {
        /// The key's path.
        key: String,
        /// Its value.
        value: f64,
        /// The value the defaults hold at that path, when they hold one.
        default: Option<toml::Value>,
    },
    /// A value outside its range.
    #[error("{key} = {value} must be {bounds}; {fix}")]
    OutOfRange {
        /// The key.
        key: String,
        /// Its value, as written.
        value: String,
        /// The range in words (`at least 1 and at most 3`).
        bounds: String,
        /// How to choose a value.
        fix: String,
    },
    /// The configuration could not be written as TOML to be checked.
    #[error("serialising: {0}")]
    Serialise(toml::ser::Error),
}

/// The longest line of a TOML error shown (a value it quotes is cut there).
const TOML_LINE_CHARS: usize = 200;

/// A TOML parse error as a message that does not echo the file: where (line and column), the
/// line quoted (it names the key) and what, each line cut at [`TOML_LINE_CHARS`] characters,
/// so that a long line or a long value the message quotes is not shown whole.
pub fn toml_message(error: &toml::de::Error) -> String {
    error
        .to_string()
        .lines()
        .map(|l| match l.char_indices().nth(TOML_LINE_CHARS) {
            Some((at, _)) => format!("{}...", &l[..at]),
            None => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Checks that every float of `config`, serialized as TOML, is finite. The error names the
/// first other one by its key path (`race.rival.gains.lambda_v = nan`) and gives the value
/// `defaults` holds at that path, when it holds one. Run before the keys' own checks, which a
/// NaN would slip through.
pub fn finite_floats<T: Serialize>(config: &T, defaults: &T) -> Result<(), ValueError> {
    match first_float(config, defaults, |x| !x.is_finite())? {
        None => Ok(()),
        Some((key, value, default)) => Err(ValueError::NotFinite {
            key,
            value,
            default,
        }),
    }
}

/// Checks that every float of `config`, serialized as TOML, lies within ±[`MAX_FLOAT`], as
/// [`finite_floats`] names the first other one. Run after the keys' own checks, whose messages
/// say more.
pub fn bounded_floats<T: Serialize>(config: &T, defaults: &T) -> Result<(), ValueError> {
    match first_float(config, defaults, |x| x.abs() > MAX_FLOAT)? {
        None => Ok(()),
        Some((key, value, default)) => Err(ValueError::Implausible {
            key,
            value,
            default,
        }),
    }
}

/// A float's key path, its value and the value `defaults` holds there, when it holds one.
type FoundFloat = (String, f64, Option<toml::Value>);

/// The first float of `config`, serialized as TOML, that is `bad`.
fn first_float<T: Serialize>(
    config: &T,
    defaults: &T,
    bad: impl Fn(f64) -> bool + Copy,
) -> Result<Option<FoundFloat>, ValueError> {
    let value = toml::Value::try_from(config).map_err(ValueError::Serialise)?;
    let Some((path, found)) = find_float(&value, &mut Vec::new(), bad) else {
        return Ok(None);
    };
    let default = toml::Value::try_from(defaults).ok().and_then(|d| {
        path.iter().try_fold(d, |v, key| match v {
            toml::Value::Table(mut t) => t.remove(key),
            _ => None,
        })
    });
    Ok(Some((path.join("."), found, default)))
}

/// The key path and value of the first float under `value` that is `bad`.
fn find_float(
    value: &toml::Value,
    path: &mut Vec<String>,
    bad: impl Fn(f64) -> bool + Copy,
) -> Option<(Vec<String>, f64)> {
    match value {
        toml::Value::Float(x) if bad(*x) => Some((path.clone(), *x)),
        toml::Value::Table(table) => table.iter().find_map(|(key, v)| {
            path.push(key.clone());
            let found = find_float(v, path, bad);
            path.pop();
            found
        }),
        toml::Value::Array(items) => items.iter().enumerate().find_map(|(i, v)| {
            path.push(i.to_string());
            let found = find_float(v, path, bad);
            path.pop();
            found
        }),
        _ => None,
    }
}

/// Checks that `key = value` lies in `range`; the error names the key, the value, the range and
/// `fix` (NaN lies in no range).
pub fn in_range<T: PartialOrd + Display + std::fmt::LowerExp>(
    key: &str,
    value: T,
    range: impl RangeBounds<T>,
    fix: &str,
) -> Result<(), ValueError> {
    if range.contains(&value) {
        return Ok(());
    }
    let lower = match range.start_bound() {
        Bound::Included(a) => Some(format!("at least {a}")),
        Bound::Excluded(a) => Some(format!("above {a}")),
        Bound::Unbounded => None,
    };
    let upper = match range.end_bound() {
        Bound::Included(b) => Some(format!("at most {b}")),
        Bound::Excluded(b) => Some(format!("below {b}")),
        Bound::Unbounded => None,
    };
    let bounds: Vec<String> = lower.into_iter().chain(upper).collect();
    Err(ValueError::OutOfRange {
        key: key.to_string(),
        // a huge number in scientific notation (1e300, not 301 digits)
        value: match value.to_string() {
            long if long.len() > 20 => format!("{value:e}"),
            short => short,
        },
        bounds: bounds.join(" and "),
        fix: fix.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Serialize)]
    struct Inner {
        gain: f64,
        per_track: std::collections::BTreeMap<String, f64>,
    }

    #[derive(Serialize)]
    struct Outer {
        size: usize,
        inner: Inner,
    }

    fn outer(gain: f64, track: f64) -> Outer {
        Outer {
            size: 3,
            inner: Inner {
                gain,
                per_track: [("f1_esp".to_string(), track)].into(),
            },
        }
    }

    #[test]
    fn the_first_implausible_float_is_named_by_its_key_path_with_its_default() {
        let defaults = outer(1.0, 0.5);
        assert_eq!(finite_floats(&defaults, &defaults), Ok(()));
        let err = finite_floats(&outer(f64::NAN, 0.5), &defaults).unwrap_err();
        assert_eq!(
            err.to_string(),
            "inner.gain = nan is not a finite number; give a finite value (the default is 1.0)"
        );
        let err = finite_floats(&outer(1.0, f64::INFINITY), &defaults)
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("inner.per_track.f1_esp = inf"), "{err}");
        // finite, but beyond what any key means
        assert_eq!(finite_floats(&outer(9.2e18, 0.5), &defaults), Ok(()));
        let err = bounded_floats(&outer(9.2e18, 0.5), &defaults).unwrap_err();
        assert_eq!(
            err.to_string(),
            "inner.gain = 9.2e18 is beyond ±1e6, which no experiment means; give a value of the \
             key's scale (the default is 1.0)"
        );
        assert_eq!(bounded_floats(&outer(-MAX_FLOAT, 0.5), &defaults), Ok(()));
    }

    #[test]
    fn toml_errors_say_where_and_what_cutting_long_lines() {
        let long = format!("a = \"{}", "x".repeat(5000));
        let err = toml::from_str::<toml::Table>(&long).unwrap_err();
        let msg = toml_message(&err);
        assert!(msg.contains("line 1"), "{msg}");
        assert!(!msg.contains(&"x".repeat(300)), "{msg}");
        #[derive(Debug, serde::Deserialize)]
        #[allow(dead_code)]
        struct N {
            n: usize,
        }
        let text = format!("n = \"{}\"", "y".repeat(5000));
        let msg = toml_message(&toml::from_str::<N>(&text).unwrap_err());
        assert!(msg.contains("invalid type") && msg.len() < 1000, "{msg}");
    }

    #[test]
    fn ranges_name_key_value_bounds_and_fix() {
        assert_eq!(in_range("a", 1, 1..=3, "fix"), Ok(()));
        assert_eq!(
            in_range("a", 0, 1..=3, "raise it").unwrap_err().to_string(),
            "a = 0 must be at least 1 and at most 3; raise it"
        );
        let err = in_range(
            "lr",
            f64::NAN,
            (Bound::Excluded(0.0), Bound::Unbounded),
            "x",
        );
        assert_eq!(err.unwrap_err().to_string(), "lr = NaN must be above 0; x");
        assert_eq!(
            in_range("b", 9, ..9, "lower it").unwrap_err().to_string(),
            "b = 9 must be below 9; lower it"
        );
    }

    #[test]
    fn a_config_error_shows_its_cause_and_causes_print_the_chain() {
        #[derive(Debug, thiserror::Error)]
        #[error("restoring {0}")]
        struct Outer(&'static str, #[source] std::io::Error);
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let marked = ConfigError::new(Outer("x.snapshot", io));
        assert_eq!(marked.to_string(), "restoring x.snapshot");
        assert_eq!(
            Causes(&marked).to_string(),
            "restoring x.snapshot: no such file"
        );
        assert_eq!(ConfigError::new("bad value").to_string(), "bad value");
    }
}
