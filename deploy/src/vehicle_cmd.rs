//! `ctxrace vehicle`: the vehicle model driven open-loop from a CSV of commands.

use anyhow::{bail, Context, Result};
use clap::Args;
use ctxrace_sim::vehicle::{Vehicle, VehicleParams, DT};
use std::io::Write;
use std::path::PathBuf;

/// Arguments of `ctxrace vehicle`.
#[derive(Args)]
pub struct VehicleArgs {
    /// CSV with rows `steer,speed` (desired steering angle in rad, speed in m/s), one per 0.01 s
    /// physics step, starting from rest; an optional header line is skipped.
    #[arg(long)]
    controls: PathBuf,
}

/// Prints `t,x,y,delta,v,yaw,yaw_rate,beta` after each step (no steering delay).
pub fn run(args: VehicleArgs) -> Result<()> {
    let text = std::fs::read_to_string(&args.controls)
        .with_context(|| format!("reading {}", args.controls.display()))?;
    let mut car = Vehicle::new(VehicleParams::default(), 0.0, 0.0, 0.0, 0);
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    writeln!(out, "t,x,y,delta,v,yaw,yaw_rate,beta")?;
    let mut step = 0usize;
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || (i == 0 && line.starts_with(|c: char| c.is_alphabetic())) {
            continue;
        }
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        let parse = |k: usize| -> Result<f64> {
            let cell = cells.get(k).copied().unwrap_or("");
            match cell.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(v),
                _ => bail!(
                    "{}:{}: column {}: '{cell}' is not a number; rows must be steer,speed",
                    args.controls.display(),
                    i + 1,
                    k + 1
                ),
            }
        };
        let (steer, speed) = (parse(0)?, parse(1)?);
        car.step(steer, speed);
        step += 1;
        let s = car.state;
        writeln!(
            out,
            "{:.9},{:.9},{:.9},{:.9},{:.9},{:.9},{:.9},{:.9}",
            step as f64 * DT,
            s[0],
            s[1],
            s[2],
            s[3],
            s[4],
            s[5],
            s[6]
        )?;
    }
    out.flush()?;
    Ok(())
}
