//! `ctxrace track download NAME...`: fetches tracks into the per-user tracks folder
//! ([`ctxrace_tracks::files::user_tracks_dir`]), where track names resolve too.
//!
//! The paper's maps (`f1_*`: f1_esp, f1_gbr, f1_aut, f1_mco) come from its repository's `maps/`
//! folder in the paper's dialect (`NAME.yaml`, `NAME_centerline.csv`, …); every other name from
//! the F1TENTH racetracks repository (`NAME/NAME_map.yaml`, …). The map image is the one the yaml
//! names; the raceline is optional. A track is kept only if it then loads.

use crate::TrackArgs;
use anyhow::{bail, Context as _, Result};
use ctxrace_config::RaceConfig;
use ctxrace_sim::track_check::{check_track, CheckPlan};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Where the paper's maps are fetched from.
pub const PAPER_SOURCE: &str = "https://raw.githubusercontent.com/lilpharaoh1/context-f110/HEAD";
/// Where the other F1TENTH tracks are fetched from.
pub const RACETRACKS_SOURCE: &str =
    "https://raw.githubusercontent.com/f1tenth/f1tenth_racetracks/HEAD";

/// The files of one track in its repository: (path in the repository, local file name).
fn layout(name: &str) -> (String, Vec<(String, String)>) {
    let files = |dir: &str, yaml: &str| {
        let mut v = vec![(format!("{dir}{yaml}"), yaml.to_string())];
        for suffix in ["_centerline.csv", "_raceline.csv"] {
            v.push((format!("{dir}{name}{suffix}"), format!("{name}{suffix}")));
        }
        v
    };
    if name.starts_with("f1_") {
        ("maps/".into(), files("maps/", &format!("{name}.yaml")))
    } else {
        (
            format!("{name}/"),
            files(&format!("{name}/"), &format!("{name}_map.yaml")),
        )
    }
}

/// Fetches `url`: `Ok(None)` when the server has no such file (404).
fn fetch(url: &str) -> Result<Option<Vec<u8>>> {
    match ureq::get(url).call() {
        Ok(mut response) => Ok(Some(
            response
                .body_mut()
                .with_config()
                .limit(64 << 20)
                .read_to_vec()
                .with_context(|| format!("reading {url}"))?,
        )),
        Err(ureq::Error::StatusCode(404)) => Ok(None),
        Err(e) => bail!(
            "downloading {url}: {e}; check the network connection (or copy the track's files \
             into the tracks folder by hand)"
        ),
    }
}

/// The image file a map yaml names.
fn image_of(yaml: &str, origin: &str) -> Result<String> {
    let v: serde_yaml::Value =
        serde_yaml::from_str(yaml).with_context(|| format!("parsing {origin}"))?;
    v.get("image")
        .and_then(|i| i.as_str())
        .and_then(ctxrace_tracks::map::image_beside)
        .map(str::to_string)
        .with_context(|| format!("{origin} names no map image (a file beside it)"))
}

/// Downloads the tracks `names` into `into` (default: the per-user tracks folder) from `from`
/// (default: their public repositories), checks that each loads and says whether it is
/// raceable (`track check`, its failures listed).
pub fn run(
    names: &[String],
    from: Option<&str>,
    into: Option<&Path>,
    tracks: &TrackArgs,
) -> Result<()> {
    let root: PathBuf = match into {
        Some(d) => d.to_path_buf(),
        None => ctxrace_tracks::files::user_tracks_dir()
            .context("no home directory for the per-user tracks folder; pass --into DIR")?,
    };
    for name in names {
        if name.is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "_-".contains(c))
        {
            bail!("'{name}' is not a track name (letters, digits, _ and - only), e.g. f1_esp or Monza");
        }
        let base = from.map_or_else(
            || {
                if name.starts_with("f1_") {
                    PAPER_SOURCE
                } else {
                    RACETRACKS_SOURCE
                }
                .to_string()
            },
            |f| f.trim_end_matches('/').to_string(),
        );
        let (folder, files) = layout(name);
        let dir = root.join(name);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let mut fetched = Vec::new();
        for (k, (remote, local)) in files.iter().enumerate() {
            let url = format!("{base}/{remote}");
            let required = k < 2; // the yaml and the centreline; the raceline is optional
            match fetch(&url)? {
                Some(bytes) => {
                    if k == 0 {
                        let image = image_of(&String::from_utf8_lossy(&bytes), &url)?;
                        let image_url = format!("{base}/{folder}{image}");
                        let png = fetch(&image_url)?
                            .with_context(|| format!("{image_url} does not exist"))?;
                        std::fs::write(dir.join(&image), png)?;
                        fetched.push(image);
                    }
                    std::fs::write(dir.join(local), bytes)
                        .with_context(|| format!("writing {}", dir.join(local).display()))?;
                    fetched.push(local.clone());
                }
                None if required => bail!(
                    "{url} does not exist: is '{name}' a track of {base}? (the paper's maps are \
                     f1_esp, f1_gbr, f1_aut, f1_mco; the F1TENTH racetracks are named like Monza)"
                ),
                None => {}
            }
        }
        let mut check = tracks.clone();
        check.tracks_dir = Some(root.clone());
        let track = match check.load(name, &RaceConfig::default()) {
            Ok(t) => t,
            Err(e) => {
                std::fs::remove_dir_all(&dir).ok();
                return Err(e.context(format!("the downloaded {name} does not load; removed it")));
            }
        };
        println!(
            "{name}: {} ({:.1} m) -> {}",
            fetched.join(", "),
            track.length(),
            dir.display()
        );
        // a map that loads may still not race: say so now rather than in a training run
        let report = check_track(
            Arc::new(track),
            &RaceConfig::default(),
            CheckPlan::default(),
        )?;
        println!("{}", report.to_text(true));
    }
    Ok(())
}
