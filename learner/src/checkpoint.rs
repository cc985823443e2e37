//! Checkpoint files: each algorithm saves named safetensors blobs (weights and optimiser
//! moments) and a TOML file of counters into one directory; errors name the file.
//!
//! A checkpoint is written into a temporary folder, sealed (every file's size and CRC-32 listed
//! in [`MANIFEST_FILE`], every file and the folder fsynced), renamed into place and the rename
//! fsynced, so that a crash leaves either the whole checkpoint or none of it. Reading verifies
//! the seal (`ctxrace_run::checkpoint`, re-exported here): a damaged newest checkpoint is passed
//! over, with a warning, for the one before.

use ctxrace_run::checkpoint::Sealed;
pub use ctxrace_run::checkpoint::{
    checkpoint_dir, checkpoint_step, checkpoints, io_error, latest_checkpoint, verify,
    CheckpointError, Result, MANIFEST_FILE, STATE_FILE,
};
use ctxrace_run::run_dir::{remove_path, replace_dir, AGENT_FILE, POLICY_FILE};
use serde::{de::DeserializeOwned, Serialize};
use std::path::Path;

/// File in every regular checkpoint with the state of the learner's smoothed training return
/// (written as [`write_checkpoint`] is given it).
pub const TRACKER_FILE: &str = "returns.toml";

/// Writes `value` as TOML to `path`, naming the file in its error.
pub(crate) fn write_toml(path: &Path, value: &impl Serialize) -> Result<()> {
    let text = toml::to_string(value).map_err(|e| io_error("serialising", path, e))?;
    std::fs::write(path, text).map_err(|e| io_error("writing", path, e))
}

/// Writes `<dir>/<name>.safetensors` for every blob and the counters `state` as
/// [`STATE_FILE`], creating `dir`.
pub fn save(dir: &Path, blobs: &[(&str, Vec<u8>)], state: &impl Serialize) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io_error("creating", dir, e))?;
    for (name, bytes) in blobs {
        let path = dir.join(format!("{name}.safetensors"));
        std::fs::write(&path, bytes).map_err(|e| io_error("writing", &path, e))?;
    }
    write_toml(&dir.join(STATE_FILE), state)
}

/// Reads `<dir>/<name>.safetensors` and hands it to `load`, naming the file in its error.
pub fn load_blob<E: std::fmt::Display>(
    dir: &Path,
    name: &str,
    load: impl FnOnce(&[u8]) -> std::result::Result<(), E>,
) -> Result<()> {
    let path = dir.join(format!("{name}.safetensors"));
    let bytes = std::fs::read(&path).map_err(|e| io_error("reading", &path, e))?;
    load(&bytes).map_err(|e| io_error("loading", &path, e))
}

/// Reads the counters file of a checkpoint directory.
pub fn load_state<T: DeserializeOwned>(dir: &Path) -> Result<T> {
    let path = dir.join(STATE_FILE);
    let text = std::fs::read_to_string(&path).map_err(|e| io_error("reading", &path, e))?;
    toml::from_str(&text).map_err(|e| io_error("parsing", &path, e))
}

/// Checkpoints kept in a run directory (older ones are removed).
const KEEP: usize = 3;
/// Lists every file of `dir` in its manifest and flushes the files, the manifest and the
/// folder to disk.
fn seal(dir: &Path) -> Result<()> {
    let mut manifest = std::collections::BTreeMap::new();
    let entries = std::fs::read_dir(dir).map_err(|e| io_error("listing", dir, e))?;
    for entry in entries {
        let path = entry.map_err(|e| io_error("listing", dir, e))?.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default()
            .to_string();
        if name == MANIFEST_FILE || !path.is_file() {
            continue;
        }
        let bytes = std::fs::read(&path).map_err(|e| io_error("reading", &path, e))?;
        sync(&path)?;
        let crc32 = crc32fast::hash(&bytes);
        manifest.insert(
            name,
            Sealed {
                bytes: bytes.len() as u64,
                crc32,
            },
        );
    }
    let path = dir.join(MANIFEST_FILE);
    let text = toml::to_string(&manifest).map_err(|e| io_error("serialising", &path, e))?;
    std::fs::write(&path, text).map_err(|e| io_error("writing", &path, e))?;
    sync(&path)?;
    sync(dir)
}

/// fsync of a file or folder.
fn sync(path: &Path) -> Result<()> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| io_error("syncing", path, e))
}

/// Saves `algo` as `<run>/checkpoints/step-<steps>/`, with the policy weights and the agent's
/// configuration beside its own files so that evaluation needs nothing else, and the smoothed
/// training return's state `tracker` as [`TRACKER_FILE`]. The checkpoint is written to a temporary
/// folder and renamed into place, so a crash never leaves half of one; only the newest few are
/// kept. Returns its path.
pub fn write_checkpoint(
    run_dir: &Path,
    algo: &dyn crate::Algorithm,
    agent: &ctxrace_config::AgentConfig,
    tracker: &impl Serialize,
) -> Result<std::path::PathBuf> {
    let final_dir = write_atomically(&checkpoint_dir(run_dir, algo.steps()), |tmp| {
        algo.save(tmp)?;
        write_policy_files(tmp, algo, agent)?;
        write_toml(&tmp.join(TRACKER_FILE), tracker)
    })?;
    let all = checkpoints(run_dir);
    for old in all.iter().take(all.len().saturating_sub(KEEP)) {
        std::fs::remove_dir_all(old).map_err(|e| io_error("removing", old, e))?;
    }
    Ok(final_dir)
}

/// Writes the acting policy's weights ([`POLICY_FILE`]) and the agent's configuration
/// ([`AGENT_FILE`]) into `dir`: everything evaluation needs.
pub(crate) fn write_policy_files(
    dir: &Path,
    algo: &dyn crate::Algorithm,
    agent: &ctxrace_config::AgentConfig,
) -> Result<()> {
    let policy = dir.join(POLICY_FILE);
    let weights = algo
        .policy_weights()
        .map_err(|e| io_error("serialising the policy for", &policy, e))?;
    std::fs::write(&policy, weights).map_err(|e| io_error("writing", &policy, e))?;
    write_toml(&dir.join(AGENT_FILE), agent)
}

/// Fills a fresh temporary folder beside `final_dir` with `fill` and puts it in place
/// ([`replace_dir`]: an earlier `final_dir` is exchanged for it in one step, so that a crash
/// leaves one of the two whole); returns `final_dir`. The temporary folder is created
/// exclusively under a fresh name, so nothing planted beside `final_dir` is written through.
pub(crate) fn write_atomically(
    final_dir: &Path,
    fill: impl FnOnce(&Path) -> Result<()>,
) -> Result<std::path::PathBuf> {
    let name = final_dir
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| io_error("naming", final_dir, "the path ends in no folder name"))?;
    let parent = final_dir
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).map_err(|e| io_error("creating", parent, e))?;
    // the temporaries a crash left behind (the run's lock keeps other writers out)
    let prefix = format!(".tmp-{name}");
    let entries = std::fs::read_dir(parent).map_err(|e| io_error("listing", parent, e))?;
    for entry in entries.filter_map(|e| e.ok()) {
        if entry.file_name().to_string_lossy().starts_with(&prefix) {
            let path = entry.path();
            remove_path(&path).map_err(|e| io_error("removing", &path, e))?;
        }
    }
    let tmp = tempfile::Builder::new()
        .prefix(&format!("{prefix}-"))
        .permissions(std::os::unix::fs::PermissionsExt::from_mode(0o755))
        .tempdir_in(parent)
        .map_err(|e| io_error("creating a temporary folder in", parent, e))?;
    fill(tmp.path())?;
    seal(tmp.path())?;
    // the old folder (if any) goes where the temporary was, and is removed from there
    let tmp = tmp.keep();
    replace_dir(&tmp, final_dir).map_err(|e| io_error("putting in place", final_dir, e))?;
    sync(parent)?;
    Ok(final_dir.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;
    use ctxrace_run::checkpoint::MAX_MANIFEST_BYTES;

    /// A cMask checkpoint written by the binary of commit d6b5c40 (the last before the networks
    /// were rewritten over a named-parameter store; `testdata/d6b5c40/README.md`) loads into a
    /// learner of its configuration, and that learner saves back every blob byte for byte and
    /// the same policy weights: every tensor's name, shape and value read as written.
    #[test]
    fn a_checkpoint_written_by_d6b5c40_loads_and_saves_back_the_same_bytes() {
        let dir =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/d6b5c40/cmask/checkpoint");
        verify(&dir).unwrap();
        let text = std::fs::read_to_string(dir.join(AGENT_FILE)).unwrap();
        let agent: ctxrace_config::AgentConfig = toml::from_str(&text).unwrap();
        let mut algo = crate::build(&agent, 108, 1).unwrap();
        algo.load(&dir).unwrap();
        assert_eq!(algo.steps(), 20);
        let again = tempfile::tempdir().unwrap();
        algo.save(again.path()).unwrap();
        let mut blobs = 0;
        for entry in std::fs::read_dir(again.path()).unwrap() {
            let name = entry.unwrap().file_name();
            if name.to_string_lossy().ends_with(".safetensors") {
                let saved = std::fs::read(again.path().join(&name)).unwrap();
                assert!(
                    saved == std::fs::read(dir.join(&name)).unwrap(),
                    "{name:?} differs"
                );
                blobs += 1;
            }
        }
        assert_eq!(
            blobs, 13,
            "weights and optimiser states of the world model, actor, critics and mask"
        );
        assert!(algo.policy_weights().unwrap() == std::fs::read(dir.join(POLICY_FILE)).unwrap());
    }

    #[test]
    fn a_damaged_newest_checkpoint_falls_back_to_the_one_before() {
        let run = tempfile::tempdir().unwrap();
        let step = |n: u64| checkpoint_dir(run.path(), n);
        for n in [1u64, 2] {
            write_atomically(&step(n), |d| {
                std::fs::write(d.join(STATE_FILE), format!("step = {n}")).unwrap();
                std::fs::write(d.join(POLICY_FILE), vec![n as u8; 100]).unwrap();
                Ok(())
            })
            .unwrap();
        }
        assert_eq!(latest_checkpoint(run.path()), Some(step(2)));
        assert!(step(2).join(MANIFEST_FILE).is_file());
        let mut bytes = std::fs::read(step(2).join(POLICY_FILE)).unwrap();
        bytes[50] ^= 1;
        std::fs::write(step(2).join(POLICY_FILE), bytes).unwrap();
        let err = verify(&step(2)).unwrap_err().to_string();
        assert!(
            err.contains(POLICY_FILE) && err.contains("damaged"),
            "{err}"
        );
        assert_eq!(latest_checkpoint(run.path()), Some(step(1)));
        // a checkpoint without its manifest cannot be verified: refused, and passed over
        std::fs::remove_file(step(2).join(MANIFEST_FILE)).unwrap();
        std::fs::write(step(2).join(POLICY_FILE), vec![2u8; 100]).unwrap();
        let err = verify(&step(2)).unwrap_err().to_string();
        assert!(
            err.contains("step-0000000002") && err.contains("no manifest.toml"),
            "{err}"
        );
        assert_eq!(latest_checkpoint(run.path()), Some(step(1)));
    }

    /// An empty sealed checkpoint in a temporary run, its manifest replaced by `manifest`.
    fn with_manifest(manifest: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let run = tempfile::tempdir().unwrap();
        let dir = checkpoint_dir(run.path(), 1);
        write_atomically(&dir, |_| Ok(())).unwrap();
        std::fs::write(dir.join(MANIFEST_FILE), manifest).unwrap();
        (run, dir)
    }

    #[test]
    fn manifest_names_outside_the_folder_or_not_regular_files_are_refused() {
        let outside = "bytes = 1\ncrc32 = 0\n";
        for name in ["../x", "/dev/zero", "sub/x", "..", MANIFEST_FILE] {
            let (_run, dir) = with_manifest(&format!("[\"{name}\"]\n{outside}"));
            let err = verify(&dir).unwrap_err().to_string();
            assert!(
                err.contains(&format!("lists '{name}'")) && err.contains("damaged"),
                "{name}: {err}"
            );
        }
        // a file of the folder that is a link to a device is refused, not read
        let (_run, dir) = with_manifest(&format!("[zero]\n{outside}"));
        std::os::unix::fs::symlink("/dev/zero", dir.join("zero")).unwrap();
        let err = verify(&dir).unwrap_err().to_string();
        assert!(err.contains("symbolic link"), "{err}");
        // and so is one the manifest does not list
        let (_run, dir) = with_manifest("");
        std::os::unix::fs::symlink("/dev/zero", dir.join(POLICY_FILE)).unwrap();
        let err = verify(&dir).unwrap_err().to_string();
        assert!(
            err.contains(POLICY_FILE) && err.contains("does not list"),
            "{err}"
        );
        // a huge manifest is refused before it is read
        let (_run, dir) = with_manifest("");
        std::fs::File::create(dir.join(MANIFEST_FILE))
            .unwrap()
            .set_len(MAX_MANIFEST_BYTES + 1)
            .unwrap();
        let err = verify(&dir).unwrap_err().to_string();
        assert!(
            err.contains(MANIFEST_FILE) && err.contains("more than"),
            "{err}"
        );
    }

    #[test]
    fn a_link_planted_at_the_temporary_folder_is_not_followed() {
        let run = tempfile::tempdir().unwrap();
        let elsewhere = tempfile::tempdir().unwrap();
        let root = run.path().join(ctxrace_run::run_dir::CHECKPOINTS);
        std::fs::create_dir_all(&root).unwrap();
        let planted = root.join(".tmp-step-0000000001");
        std::os::unix::fs::symlink(elsewhere.path(), &planted).unwrap();
        let dir = root.join("step-0000000001");
        write_atomically(&dir, |d| {
            std::fs::write(d.join(STATE_FILE), "step = 1").unwrap();
            Ok(())
        })
        .unwrap();
        assert_eq!(std::fs::read_dir(elsewhere.path()).unwrap().count(), 0);
        assert!(planted.symlink_metadata().is_err());
        assert!(verify(&dir).is_ok());
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(128))]

            #[test]
            /// A byte flipped (`bits` > 0) or the file cut at `at` (`bits` = 0) in either file.
            fn any_damaged_file_breaks_the_seal(
                at in any::<usize>(),
                bits in any::<u8>(),
                victim in prop_oneof![Just(STATE_FILE), Just(POLICY_FILE)],
                policy in prop::collection::vec(any::<u8>(), 1..200),
            ) {
                let run = tempfile::tempdir().unwrap();
                let dir = checkpoint_dir(run.path(), 1);
                write_atomically(&dir, |d| {
                    std::fs::write(d.join(STATE_FILE), "step = 1").unwrap();
                    std::fs::write(d.join(POLICY_FILE), &policy).unwrap();
                    Ok(())
                })
                .unwrap();
                prop_assert!(verify(&dir).is_ok());
                let path = dir.join(victim);
                let mut bytes = std::fs::read(&path).unwrap();
                let at = at % bytes.len();
                if bits == 0 {
                    bytes.truncate(at);
                } else {
                    bytes[at] ^= bits;
                }
                std::fs::write(&path, bytes).unwrap();
                let err = verify(&dir).err().map(|e| e.to_string());
                prop_assert!(err.as_ref().is_some_and(|e| e.contains(victim)), "{err:?}");
                prop_assert_eq!(latest_checkpoint(run.path()), None);
            }

            #[test]
            fn arbitrary_manifests_and_states_are_errors_not_panics(
                manifest in prop::collection::vec(any::<u8>(), 0..200),
                state in "[a-z =\\[\\]0-9\"\n.]{0,80}",
            ) {
                let dir = tempfile::tempdir().unwrap();
                std::fs::write(dir.path().join(MANIFEST_FILE), &manifest).unwrap();
                std::fs::write(dir.path().join(STATE_FILE), &state).unwrap();
                let _ = verify(dir.path());
                let _ = load_state::<toml::Table>(dir.path());
            }
        }
    }
}

/// A trained agent read back (`ctxrace_run::trained`) from checkpoints this module wrote.
#[cfg(test)]
mod trained_tests {
    use super::{write_atomically, STATE_FILE};
    use ctxrace_config::AgentConfig;
    use ctxrace_run::checkpoint::BEST_FILE;
    use ctxrace_run::run_dir::{AGENT_FILE, BEST_DIR, CHECKPOINTS, POLICY_FILE};
    use ctxrace_run::trained::{CheckpointChoice, TrainedAgent};
    use std::path::{Path, PathBuf};

    /// A sealed checkpoint `name` of `run` holding an agent and a policy.
    fn checkpoint(run: &Path, name: &str) -> PathBuf {
        let agent = toml::to_string(&AgentConfig::default()).unwrap();
        write_atomically(&run.join(CHECKPOINTS).join(name), |d| {
            std::fs::write(d.join(STATE_FILE), "step = 1").unwrap();
            std::fs::write(d.join(BEST_FILE), "").unwrap();
            std::fs::write(d.join(AGENT_FILE), &agent).unwrap();
            std::fs::write(d.join(POLICY_FILE), name).unwrap();
            Ok(())
        })
        .unwrap()
    }

    #[test]
    fn an_intact_best_is_loaded_and_named_when_every_step_is_damaged() {
        let run = tempfile::tempdir().unwrap();
        for name in ["step-0000000001", "step-0000000002"] {
            let dir = checkpoint(run.path(), name);
            std::fs::write(dir.join(POLICY_FILE), "damaged").unwrap();
        }
        let best = checkpoint(run.path(), BEST_DIR);
        let agent = TrainedAgent::load(run.path(), CheckpointChoice::Best).unwrap();
        assert_eq!(agent.checkpoint, best);
        assert_eq!(agent.weights, BEST_DIR.as_bytes());
        let err = TrainedAgent::load(run.path(), CheckpointChoice::Latest)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no latest checkpoint intact")
                && err.contains("every step-* checkpoint is damaged")
                && err.contains("pass --checkpoint best (intact)"),
            "{err}"
        );
        // with the best damaged too, nothing is offered
        std::fs::write(best.join(POLICY_FILE), "damaged").unwrap();
        let err = format!(
            "{:#}",
            TrainedAgent::load(run.path(), CheckpointChoice::Best).unwrap_err()
        );
        assert!(err.contains("damaged"), "{err}");
        let err = TrainedAgent::load(run.path(), CheckpointChoice::Latest)
            .unwrap_err()
            .to_string();
        assert!(err.contains("no other intact one"), "{err}");
    }
}
