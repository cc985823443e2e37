//! `ctxrace track download NAME...`: fetches tracks ([`ctxrace_tracks::download`]) into the
//! per-user tracks folder, where track names resolve too, and says whether each is raceable.

use anyhow::Result;
use ctxrace_config::RaceConfig;
use ctxrace_sim::track_check::{check_track, CheckPlan};
use ctxrace_tracks::download::{default_download_dir, download};
use std::path::Path;
use std::sync::Arc;

/// Downloads the tracks `names` into `into` (default: the per-user tracks folder) from `from`
/// (default: their public repositories), each loaded, and says whether each is raceable
/// (`track check`, its failures listed).
pub fn run(names: &[String], from: Option<&str>, into: Option<&Path>) -> Result<()> {
    let root = match into {
        Some(d) => d.to_path_buf(),
        None => default_download_dir()?,
    };
    for name in names {
        let got = download(name, from, &root)?;
        println!(
            "{name}: {} ({:.1} m) -> {}",
            got.files.join(", "),
            got.track.length(),
            got.dir.display()
        );
        // a map that loads may still not race: say so now rather than in a training run
        let race = RaceConfig::default();
        let report = check_track(Arc::new(got.track), &race, CheckPlan::default())?;
        println!("{}", report.to_text(true));
    }
    Ok(())
}
