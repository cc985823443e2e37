//! The vehicle against the reference trajectories in ../shared/testdata/vehicle: every
//! `NAME_controls.csv` (steer, speed per 0.01 s step, from rest, no steering delay) must reproduce
//! `NAME_states.csv` (t, x, y, delta, v, yaw, yaw_rate, beta) to 1e-6.

use ctxrace_sim::vehicle::{Vehicle, VehicleParams};
use ctxrace_tracks::files::shared_reference;
use std::path::PathBuf;

fn read_rows(path: &PathBuf) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split(',').map(|c| c.trim().parse().unwrap()).collect())
        .collect()
}

#[test]
fn reproduces_every_reference_trajectory() {
    let dir = shared_reference("testdata/vehicle").unwrap_or_else(|e| panic!("{e}"));
    let entries = std::fs::read_dir(&dir).unwrap();
    let mut checked = 0;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix("_controls.csv") else {
            continue;
        };
        let controls = read_rows(&e.path());
        let states = read_rows(&dir.join(format!("{stem}_states.csv")));
        assert_eq!(controls.len(), states.len(), "{stem}: row counts differ");
        let mut car = Vehicle::new(VehicleParams::default(), 0.0, 0.0, 0.0, 0);
        for (k, (u, want)) in controls.iter().zip(&states).enumerate() {
            car.step(u[0], u[1]);
            for j in 0..7 {
                let got = car.state[j];
                assert!(
                    (got - want[j + 1]).abs() < 1e-6,
                    "{stem} step {k} (t = {}) state[{j}] = {got:.9}, expected {:.9}",
                    want[0],
                    want[j + 1]
                );
            }
        }
        checked += 1;
    }
    assert!(checked > 0, "no *_controls.csv in {}", dir.display());
}
