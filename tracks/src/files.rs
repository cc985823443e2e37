//! Track files in both dialects, and resolving a `--track` argument to them.
//!
//! - The paper's: `NAME.yaml`, `NAME.png`, `NAME_centerline.csv` (x, y, w_right, w_left) and
//!   `NAME_raceline.csv` (s, x, y, psi, kappa, vx, ax), comma-separated, no header.
//! - The F1TENTH racetracks repository's: `NAME_map.yaml`/`.png`, `NAME_centerline.csv` with a `#`
//!   header, `NAME_raceline.csv` `;`-separated with `#` comment lines.
//!
//! Lines starting with `#` and blank lines are skipped; the separator is `;` when a line has one,
//! else `,`.

use crate::error::{Result, TrackError};
use crate::path::{Centreline, ClosedCurve, Raceline};
use nalgebra::Point2;
use std::path::{Path, PathBuf};

/// Environment variable naming the default tracks directory.
pub const TRACKS_DIR_ENV: &str = "CTXRACE_TRACKS_DIR";
/// Environment variable naming ctxrace's per-user data directory.
pub const DATA_DIR_ENV: &str = "CTXRACE_DATA_DIR";

/// The per-user folder that `ctxrace track download` fills and track names also resolve in:
/// `$CTXRACE_DATA_DIR/tracks`, else `$XDG_DATA_HOME/ctxrace/tracks`, else
/// `~/.local/share/ctxrace/tracks`; `None` without a home directory.
pub fn user_tracks_dir() -> Option<PathBuf> {
    let var = |name: &str| {
        std::env::var_os(name)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    let data = var(DATA_DIR_ENV)
        .or_else(|| var("XDG_DATA_HOME").map(|d| d.join("ctxrace")))
        .or_else(|| var("HOME").map(|h| h.join(".local/share/ctxrace")))?;
    Some(data.join("tracks"))
}

/// The files of one track on disk.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackFiles {
    /// Track name (file stem without dialect suffixes).
    pub name: String,
    /// The map yaml.
    pub yaml: PathBuf,
    /// The centreline CSV.
    pub centreline: PathBuf,
    /// The raceline CSV (may not exist).
    pub raceline: PathBuf,
}

impl TrackFiles {
    /// The files belonging to a map yaml, in either dialect.
    pub fn from_yaml(yaml: &Path) -> Self {
        let stem = yaml
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let name = stem.strip_suffix("_map").unwrap_or(&stem).to_string();
        let dir = yaml.parent().unwrap_or_else(|| Path::new("."));
        Self {
            centreline: dir.join(format!("{name}_centerline.csv")),
            raceline: dir.join(format!("{name}_raceline.csv")),
            yaml: yaml.to_path_buf(),
            name,
        }
    }

    /// Resolves a track name in `dir` (and its immediate subfolders), else in
    /// [`user_tracks_dir`], or a path to a map yaml. A name that several tracks of the same
    /// folder bear is an error listing them.
    pub fn resolve(spec: &str, dir: &Path) -> Result<Self> {
        let as_path = Path::new(spec);
        if as_path
            .extension()
            .is_some_and(|e| e == "yaml" || e == "yml")
        {
            if as_path.is_file() {
                return Ok(Self::from_yaml(as_path));
            }
            return Err(TrackError::Io {
                path: as_path.to_path_buf(),
                cause: std::io::Error::new(std::io::ErrorKind::NotFound, "no such map yaml"),
            });
        }
        let found = known_tracks(dir);
        let named: Vec<&TrackFiles> = found.iter().filter(|t| t.name == spec).collect();
        // the tracks folder before the per-user one; within one folder a name is unique
        let first_root = named.first().map(|t| track_root(t, dir));
        let same_root: Vec<&TrackFiles> = named
            .iter()
            .copied()
            .filter(|t| Some(track_root(t, dir)) == first_root)
            .collect();
        if same_root.len() > 1 {
            return Err(TrackError::AmbiguousTrack {
                name: spec.to_string(),
                candidates: same_root.iter().map(|t| t.yaml.clone()).collect(),
            });
        }
        same_root
            .first()
            .map(|&t| t.clone())
            .ok_or_else(|| TrackError::UnknownTrack {
                name: spec.to_string(),
                dir: dir.to_path_buf(),
                found: if found.is_empty() {
                    "none".into()
                } else {
                    found
                        .iter()
                        .map(|t| t.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                },
            })
    }
}

/// Every track a name may resolve to from the tracks folder `dir`: those of `dir` and its
/// immediate subfolders, then those of the per-user folder ([`user_tracks_dir`]), each part
/// sorted by name.
pub fn known_tracks(dir: &Path) -> Vec<TrackFiles> {
    let mut found = list_tracks(dir);
    if let Some(user) = user_tracks_dir().filter(|u| u != dir) {
        found.extend(list_tracks(&user));
    }
    found
}

/// Whether `track` was found in the tracks folder `dir` (else in the per-user one).
fn track_root(track: &TrackFiles, dir: &Path) -> bool {
    track.yaml.starts_with(dir)
}

/// Every track (map yaml with a centreline beside it) in `dir` and its immediate subfolders,
/// sorted by name.
pub fn list_tracks(dir: &Path) -> Vec<TrackFiles> {
    let mut dirs = vec![dir.to_path_buf()];
    if let Ok(rd) = std::fs::read_dir(dir) {
        dirs.extend(rd.flatten().map(|e| e.path()).filter(|p| p.is_dir()));
    }
    let mut out: Vec<TrackFiles> = dirs
        .iter()
        .filter_map(|d| std::fs::read_dir(d).ok())
        .flat_map(|rd| rd.flatten().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "yaml" || e == "yml"))
        .map(|p| TrackFiles::from_yaml(&p))
        .filter(|t| t.centreline.is_file())
        .collect();
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}

/// The reference material beside the workspace (`../shared`: the paper's maps, the vehicle test
/// vectors, the paper-code benchmark tools), as fixed at build time: for tests and benchmarks.
pub const SHARED_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared");

/// `SHARED_DIR/<sub>`, or an error naming the missing folder, so that a test needing the
/// reference material fails with it instead of passing without checking anything.
pub fn shared_reference(sub: &str) -> Result<PathBuf> {
    let dir = Path::new(SHARED_DIR).join(sub);
    if dir.exists() {
        Ok(dir)
    } else {
        Err(TrackError::MissingReference { dir })
    }
}

/// The default tracks directory: `$CTXRACE_TRACKS_DIR`, else `../shared/tracks` when it exists,
/// else the current directory.
pub fn default_tracks_dir() -> PathBuf {
    if let Some(d) = std::env::var_os(TRACKS_DIR_ENV) {
        return PathBuf::from(d);
    }
    let shared = PathBuf::from("../shared/tracks");
    if shared.is_dir() {
        shared
    } else {
        PathBuf::from(".")
    }
}

/// Reads a numeric CSV with at least `min_cols` columns per row.
pub fn read_numeric_csv(path: &Path, min_cols: usize) -> Result<Vec<Vec<f64>>> {
    let text = std::fs::read_to_string(path).map_err(|cause| TrackError::Io {
        path: path.to_path_buf(),
        cause,
    })?;
    parse_numeric_csv(&text, min_cols, path)
}

/// Parses numeric CSV text (see the module doc); `path` only names the source in errors.
pub fn parse_numeric_csv(text: &str, min_cols: usize, path: &Path) -> Result<Vec<Vec<f64>>> {
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let sep = if line.contains(';') { ';' } else { ',' };
        let mut row = Vec::with_capacity(min_cols);
        for (col, cell) in line.split(sep).enumerate() {
            let cell = cell.trim();
            let v: f64 = cell.parse().map_err(|_| TrackError::Csv {
                path: path.to_path_buf(),
                line: i + 1,
                message: format!(
                    "column {}: '{cell}' is not a number (comment lines must start with '#')",
                    col + 1
                ),
            })?;
            if !v.is_finite() {
                return Err(TrackError::Csv {
                    path: path.to_path_buf(),
                    line: i + 1,
                    message: format!("column {}: '{cell}' is not finite", col + 1),
                });
            }
            row.push(v);
        }
        if row.len() < min_cols {
            return Err(TrackError::Csv {
                path: path.to_path_buf(),
                line: i + 1,
                message: format!("{} columns, expected at least {min_cols}", row.len()),
            });
        }
        rows.push(row);
    }
    Ok(rows)
}

/// Loads a centreline CSV (`x, y, w_right, w_left`).
pub fn load_centreline(path: &Path) -> Result<Centreline> {
    let rows: Vec<[f64; 4]> = read_numeric_csv(path, 4)?
        .into_iter()
        .map(|r| [r[0], r[1], r[2], r[3]])
        .collect();
    Centreline::new(&rows, &format!("centreline {}", path.display()))
}

/// Loads a raceline CSV (`s, x, y, psi, kappa, vx, ax`); the curve and kappa come from x, y, kappa,
/// the speed profile from vx and ax. A repeated closing point is dropped.
pub fn load_raceline(path: &Path) -> Result<Raceline> {
    let mut rows = read_numeric_csv(path, 7)?;
    rows.dedup_by(|b, a| (a[1] - b[1]).hypot(a[2] - b[2]) <= 1e-9);
    while rows.len() > 1 {
        let (f, l) = (&rows[0], &rows[rows.len() - 1]);
        if (f[1] - l[1]).hypot(f[2] - l[2]) > 1e-9 {
            break;
        }
        rows.pop();
    }
    if let Some((i, r)) = rows.iter().enumerate().find(|(_, r)| r[5] <= 0.0) {
        return Err(TrackError::Csv {
            path: path.to_path_buf(),
            line: i + 1,
            message: format!("speed {} must be positive", r[5]),
        });
    }
    let curve = ClosedCurve::new(
        rows.iter().map(|r| Point2::new(r[1], r[2])).collect(),
        &format!("raceline {}", path.display()),
    )?;
    Ok(Raceline {
        curve,
        kappa: rows.iter().map(|r| r[4]).collect(),
        speed: rows.iter().map(|r| r[5]).collect(),
        accel: rows.iter().map(|r| r[6]).collect(),
    })
}

/// Writes a raceline in the paper's dialect (`s, x, y, psi, kappa, vx, ax`, psi = heading − π/2).
pub fn write_raceline(raceline: &Raceline, out: &mut impl std::io::Write) -> std::io::Result<()> {
    let c = &raceline.curve;
    for (i, p) in c.points().iter().enumerate() {
        let d = c.segment_vector(i);
        let psi = d.y.atan2(d.x) - std::f64::consts::FRAC_PI_2;
        let psi =
            (psi + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        writeln!(
            out,
            "{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}",
            c.s_at_vertex(i),
            p.x,
            p.y,
            psi,
            raceline.kappa[i],
            raceline.speed[i],
            raceline.accel[i]
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_reference_folder_or_file_is_named_once() {
        let err = shared_reference("no-such-folder").unwrap_err();
        assert!(
            matches!(err, TrackError::MissingReference { .. }),
            "{err:?}"
        );
        let text = err.to_string();
        assert!(
            text.contains("no-such-folder not found") && text.ends_with("put it there"),
            "{text}"
        );
        let err = TrackFiles::resolve("missing.yaml", Path::new(".")).unwrap_err();
        // the cause is in the message, not a source that a chain (`{:#}`) would print again
        assert!(std::error::Error::source(&err).is_none());
        assert_eq!(
            err.to_string(),
            "cannot read missing.yaml: no such map yaml"
        );
    }

    #[test]
    fn parses_both_dialects_and_names_bad_cells() {
        let p = Path::new("t.csv");
        let rows = parse_numeric_csv("# x_m, y_m\n1, 2, 3, 4\n\n5,6,7,8\n", 4, p).unwrap();
        assert_eq!(
            rows,
            vec![vec![1.0, 2.0, 3.0, 4.0], vec![5.0, 6.0, 7.0, 8.0]]
        );
        let rows = parse_numeric_csv("# a\n# b\n0.0;1.5;2\n", 3, p).unwrap();
        assert_eq!(rows, vec![vec![0.0, 1.5, 2.0]]);
        let err = parse_numeric_csv("1,2,3,4\n1,x,3,4\n", 4, p).unwrap_err();
        assert_eq!(
            err.to_string(),
            "t.csv:2: column 2: 'x' is not a number (comment lines must start with '#')"
        );
        let err = parse_numeric_csv("1,2,3\n", 4, p).unwrap_err();
        assert!(err.to_string().contains("3 columns, expected at least 4"));
        let err = parse_numeric_csv("1,2,NaN,4\n", 4, p).unwrap_err();
        assert!(err.to_string().contains("not finite"));
    }

    #[test]
    fn dialect_names_from_yaml() {
        let t = TrackFiles::from_yaml(Path::new("/x/Monza_map.yaml"));
        assert_eq!(t.name, "Monza");
        assert_eq!(t.centreline, Path::new("/x/Monza_centerline.csv"));
        let t = TrackFiles::from_yaml(Path::new("/x/f1_esp.yaml"));
        assert_eq!(t.raceline, Path::new("/x/f1_esp_raceline.csv"));
    }

    #[test]
    fn unknown_track_lists_what_exists() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a.yaml"), "").unwrap();
        std::fs::write(dir.path().join("a_centerline.csv"), "").unwrap();
        let err = TrackFiles::resolve("b", dir.path())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("unknown track 'b'") && err.contains("tracks found: a"),
            "{err}"
        );
    }

    #[test]
    fn a_name_two_tracks_of_one_folder_bear_is_refused_listing_both() {
        let dir = tempfile::tempdir().unwrap();
        let track = |sub: &Path| {
            std::fs::create_dir_all(sub).unwrap();
            std::fs::write(sub.join("a.yaml"), "").unwrap();
            std::fs::write(sub.join("a_centerline.csv"), "").unwrap();
        };
        track(dir.path());
        assert_eq!(
            TrackFiles::resolve("a", dir.path()).unwrap().yaml,
            dir.path().join("a.yaml")
        );
        track(&dir.path().join("extra"));
        let err = TrackFiles::resolve("a", dir.path()).unwrap_err();
        assert!(
            matches!(&err, TrackError::AmbiguousTrack { candidates, .. } if candidates.len() == 2)
        );
        let text = err.to_string();
        assert!(
            text.contains("ambiguous") && text.contains("extra/a.yaml"),
            "{text}"
        );
    }
}
