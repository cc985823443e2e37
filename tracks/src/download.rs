//! Fetching a track into a tracks folder (the per-user one, [`user_tracks_dir`], by default),
//! for `ctxrace track download` and Python's `ctxrace.tracks.download` (feature `download`).
//!
//! The paper's maps (`f1_*`: f1_esp, f1_gbr, f1_aut, f1_mco) come from its repository's `maps/`
//! folder in the paper's dialect (`NAME.yaml`, `NAME_centerline.csv`, …); every other name from
//! the F1TENTH racetracks repository (`NAME/NAME_map.yaml`, …). The map image is the one the yaml
//! names; the raceline is optional. A track is kept only if it then loads.

use crate::error::{Result, TrackError};
use crate::files::user_tracks_dir;
use crate::track::{Track, TrackOptions};
use std::path::{Path, PathBuf};

/// Where the paper's maps are fetched from.
pub const PAPER_SOURCE: &str = "https://raw.githubusercontent.com/lilpharaoh1/context-f110/HEAD";
/// Where the other F1TENTH tracks are fetched from.
pub const RACETRACKS_SOURCE: &str =
    "https://raw.githubusercontent.com/f1tenth/f1tenth_racetracks/HEAD";
/// The largest file fetched (bytes).
const MAX_FILE_BYTES: u64 = 64 << 20;

/// A track fetched and loaded ([`download`]).
#[derive(Clone, Debug)]
pub struct Downloaded {
    /// The folder its files are in.
    pub dir: PathBuf,
    /// The files written, by name.
    pub files: Vec<String>,
    /// The track, loaded from them (the computed raceline).
    pub track: Track,
}

/// The files of one track in its repository: its folder there, and (path in the repository,
/// local file name) of the yaml, the centreline and the raceline.
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
    let failed = |message: String| TrackError::Download {
        url: url.to_string(),
        message,
    };
    match ureq::get(url).call() {
        Ok(mut response) => Ok(Some(
            response
                .body_mut()
                .with_config()
                .limit(MAX_FILE_BYTES)
                .read_to_vec()
                .map_err(|e| failed(e.to_string()))?,
        )),
        Err(ureq::Error::StatusCode(404)) => Ok(None),
        Err(e) => Err(failed(format!(
            "{e}; check the network connection (or copy the track's files into the tracks \
             folder by hand)"
        ))),
    }
}

/// The image file a map yaml names.
fn image_of(yaml: &str, url: &str) -> Result<String> {
    let invalid = |message: String| TrackError::Invalid {
        what: format!("map yaml {url}"),
        message,
    };
    let v: serde_yaml::Value = serde_yaml::from_str(yaml).map_err(|e| invalid(e.to_string()))?;
    v.get("image")
        .and_then(|i| i.as_str())
        .and_then(crate::map::image_beside)
        .map(str::to_string)
        .ok_or_else(|| invalid("it names no map image (a file beside it)".into()))
}

/// Checks that `name` can name a track folder: letters, digits, `_` and `-`.
fn check_name(name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-".contains(c));
    if ok {
        Ok(())
    } else {
        Err(TrackError::Invalid {
            what: format!("track name '{name}'"),
            message: "use letters, digits, _ and - only, e.g. f1_esp or Monza".into(),
        })
    }
}

/// The folder tracks are downloaded into when none is given: [`user_tracks_dir`].
pub fn default_download_dir() -> Result<PathBuf> {
    user_tracks_dir().ok_or_else(|| TrackError::Invalid {
        what: "the per-user tracks folder".into(),
        message: "there is no home directory (HOME, XDG_DATA_HOME and CTXRACE_DATA_DIR are \
                  unset): name a folder to download into"
            .into(),
    })
}

/// Downloads the track `name` into `into/<name>/` from `from` (default: its public repository,
/// [`PAPER_SOURCE`] for `f1_*`, else [`RACETRACKS_SOURCE`]) and loads it; a track that does not
/// load is removed again.
pub fn download(name: &str, from: Option<&str>, into: &Path) -> Result<Downloaded> {
    check_name(name)?;
    let base = match from {
        Some(f) => f.trim_end_matches('/').to_string(),
        None if name.starts_with("f1_") => PAPER_SOURCE.to_string(),
        None => RACETRACKS_SOURCE.to_string(),
    };
    let (folder, files) = layout(name);
    let dir = into.join(name);
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |cause| TrackError::Io { path, cause }
    };
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let mut fetched = Vec::new();
    for (k, (remote, local)) in files.iter().enumerate() {
        let url = format!("{base}/{remote}");
        let required = k < 2; // the yaml and the centreline; the raceline is optional
        match fetch(&url)? {
            Some(bytes) => {
                if k == 0 {
                    let image = image_of(&String::from_utf8_lossy(&bytes), &url)?;
                    let image_url = format!("{base}/{folder}{image}");
                    let png = fetch(&image_url)?.ok_or_else(|| TrackError::Download {
                        url: image_url.clone(),
                        message: "the map yaml names this image, which does not exist".into(),
                    })?;
                    std::fs::write(dir.join(&image), png).map_err(io(&dir.join(&image)))?;
                    fetched.push(image);
                }
                std::fs::write(dir.join(local), bytes).map_err(io(&dir.join(local)))?;
                fetched.push(local.clone());
            }
            None if required => {
                return Err(TrackError::Download {
                    url,
                    message: format!(
                        "no such file: is '{name}' a track of {base}? (the paper's maps are \
                         f1_esp, f1_gbr, f1_aut, f1_mco; the F1TENTH racetracks are named like \
                         Monza)"
                    ),
                })
            }
            None => {}
        }
    }
    let opts = TrackOptions {
        tracks_dir: into.to_path_buf(),
        ..TrackOptions::default()
    };
    match Track::load(name, &opts) {
        Ok(track) => Ok(Downloaded {
            dir,
            files: fetched,
            track,
        }),
        Err(e) => {
            std::fs::remove_dir_all(&dir).ok();
            Err(TrackError::Invalid {
                what: format!("the downloaded {name}"),
                message: format!("{e}; removed it"),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_that_are_no_folder_are_refused_before_any_fetch() {
        for bad in ["", "../x", "a/b", "f1 esp"] {
            let err = download(bad, Some("http://127.0.0.1:9"), Path::new("/nonexistent"))
                .unwrap_err()
                .to_string();
            assert!(err.contains("letters, digits"), "{bad}: {err}");
        }
    }

    #[test]
    fn each_repository_has_its_layout() {
        let (folder, files) = layout("f1_esp");
        assert_eq!(folder, "maps/");
        assert_eq!(files[0], ("maps/f1_esp.yaml".into(), "f1_esp.yaml".into()));
        let (folder, files) = layout("Monza");
        assert_eq!(folder, "Monza/");
        assert_eq!(files[0].0, "Monza/Monza_map.yaml");
        assert_eq!(files[1].1, "Monza_centerline.csv");
    }
}
