//! The per-episode context `c = [c_v, c_θ]` that sets the rivals' driving style.
//!
//! Rival speed is scaled by `1 + λ_v c_v` and the pure-pursuit lookahead by `1 + λ_θ c_θ`. The paper
//! trains with each element uniform in `[-0.15, 0.15]` and evaluates on the 7 × 7 grid
//! `{-0.3, -0.2, …, 0.3}²`.

use serde::{Deserialize, Serialize};

/// Largest magnitude accepted for a context element (the scale factors stay positive for λ ≤ 1).
pub const CONTEXT_LIMIT: f64 = 0.9;

/// A context `[c_v, c_θ]`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Context {
    /// Speed coefficient `c_v`.
    pub speed: f64,
    /// Steering (lookahead) coefficient `c_θ`.
    pub steer: f64,
}

/// A context value that cannot be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ContextError {
    /// Not two comma-separated numbers.
    #[error("context '{0}' must be two numbers CV,CT, e.g. 0.1,-0.2")]
    Syntax(String),
    /// A value outside `[-CONTEXT_LIMIT, CONTEXT_LIMIT]` or not finite.
    #[error("context element {name} = {value} is out of range: use values in [-{CONTEXT_LIMIT}, {CONTEXT_LIMIT}] (the paper trains on ±0.15 and evaluates on ±0.3)")]
    OutOfRange {
        /// `c_v` or `c_theta`.
        name: &'static str,
        /// The value given.
        value: f64,
    },
}

impl Context {
    /// A checked context.
    pub fn new(speed: f64, steer: f64) -> Result<Self, ContextError> {
        for (name, value) in [("c_v", speed), ("c_theta", steer)] {
            if !(value.is_finite() && value.abs() <= CONTEXT_LIMIT) {
                return Err(ContextError::OutOfRange { name, value });
            }
        }
        Ok(Self { speed, steer })
    }

    /// As an array `[c_v, c_θ]`.
    pub fn to_array(self) -> [f64; 2] {
        [self.speed, self.steer]
    }

    /// Whether both elements lie within `±range` (in-distribution for a training range).
    pub fn within(self, range: f64) -> bool {
        self.speed.abs() <= range + 1e-9 && self.steer.abs() <= range + 1e-9
    }

    /// The evaluation grid: `n × n` contexts evenly spaced over `[-range, range]²`, c_v major.
    pub fn grid(n: usize, range: f64) -> Vec<Context> {
        let vals: Vec<f64> = (0..n)
            .map(|i| {
                if n == 1 {
                    0.0
                } else {
                    // round to 1e-12 so 0.1 steps print cleanly
                    ((-range + 2.0 * range * i as f64 / (n - 1) as f64) * 1e12).round() / 1e12
                }
            })
            .collect();
        vals.iter()
            .flat_map(|&v| vals.iter().map(move |&t| Context { speed: v, steer: t }))
            .collect()
    }
}

impl std::str::FromStr for Context {
    type Err = ContextError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        let [v, t] = parts[..] else {
            return Err(ContextError::Syntax(s.to_string()));
        };
        let parse = |x: &str| {
            x.parse::<f64>()
                .map_err(|_| ContextError::Syntax(s.to_string()))
        };
        Context::new(parse(v)?, parse(t)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_checks_ranges() {
        assert_eq!(
            "0.1,-0.2".parse::<Context>().unwrap(),
            Context {
                speed: 0.1,
                steer: -0.2
            }
        );
        assert!(matches!(
            "0.1".parse::<Context>(),
            Err(ContextError::Syntax(_))
        ));
        assert!(matches!(
            "a,b".parse::<Context>(),
            Err(ContextError::Syntax(_))
        ));
        let err = "1.5,0".parse::<Context>().unwrap_err();
        assert_eq!(
            err,
            ContextError::OutOfRange {
                name: "c_v",
                value: 1.5
            }
        );
        assert!(err.to_string().contains("out of range"));
        assert!("0,NaN".parse::<Context>().is_err());
    }

    #[test]
    fn the_paper_grid_has_49_contexts_9_in_distribution() {
        let g = Context::grid(7, 0.3);
        assert_eq!(g.len(), 49);
        assert_eq!(
            g[0],
            Context {
                speed: -0.3,
                steer: -0.3
            }
        );
        assert_eq!(
            g[8],
            Context {
                speed: -0.2,
                steer: -0.2
            }
        );
        assert_eq!(g.iter().filter(|c| c.within(0.15)).count(), 9);
    }
}
