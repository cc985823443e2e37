//! Config files read with a size bound and never echoed ([`read_config_text`]): a mistaken
//! path to a large or binary file is refused by name before it is read whole.

use std::io::Read;
use std::path::{Path, PathBuf};

/// The largest config or matrix file read (bytes): ctxrace's own are a few kilobytes.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Why a config file cannot be read (its content is never shown).
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    /// The file could not be opened or read.
    #[error("reading {}: {cause}", .path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The file is larger than a config may be (its content is not shown).
    #[error(
        "{} holds {bytes} bytes, more than the {} a config may hold; is it the right file?",
        .path.display(),
        MAX_CONFIG_BYTES
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
    },
    /// The file is not UTF-8 text (its content is not shown).
    #[error("{} is not UTF-8 text; is it the right file?", .path.display())]
    NotText {
        /// The file.
        path: PathBuf,
    },
    /// The file is not a TOML table (the message has the line).
    #[error("{}: {}", .path.display(), crate::validate::toml_message(.cause))]
    Toml {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: toml::de::Error,
    },
}

/// Reads a config file as text: a regular file of at most [`MAX_CONFIG_BYTES`] (checked before
/// it is read, and again while reading a file that grows), UTF-8; the errors name the file and
/// never show its content.
pub fn read_config_text(path: &Path) -> Result<String, ConfigFileError> {
    let read_error = |cause| ConfigFileError::Read {
        path: path.to_path_buf(),
        cause,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let meta = file.metadata().map_err(read_error)?;
    if meta.is_dir() {
        return Err(read_error(std::io::Error::other("it is a folder")));
    }
    let too_large = |bytes| ConfigFileError::TooLarge {
        path: path.to_path_buf(),
        bytes,
    };
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(too_large(meta.len()));
    }
    let mut bytes = Vec::new();
    file.take(MAX_CONFIG_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(read_error)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(too_large(bytes.len() as u64));
    }
    String::from_utf8(bytes).map_err(|_| ConfigFileError::NotText {
        path: path.to_path_buf(),
    })
}

/// Reads a config file ([`read_config_text`]) as a TOML table, for laying tables over one
/// another before they are read as a configuration.
pub fn read_config_table(path: &Path) -> Result<toml::Table, ConfigFileError> {
    toml::from_str(&read_config_text(path)?).map_err(|cause| ConfigFileError::Toml {
        path: path.to_path_buf(),
        cause,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_files_are_read_bounded_and_never_echoed() {
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big.toml");
        let line = format!("track = \"{}\"\n", "x".repeat(2 << 20));
        std::fs::write(&big, &line).unwrap();
        let err = read_config_text(&big).unwrap_err().to_string();
        assert!(
            err.contains("more than the 1048576") && !err.contains("xxxx"),
            "{err}"
        );
        let binary = dir.path().join("bin.toml");
        std::fs::write(&binary, [0xff, 0xfe, b'a']).unwrap();
        let err = read_config_text(&binary).unwrap_err().to_string();
        assert!(err.contains("not UTF-8"), "{err}");
        let err = read_config_text(dir.path()).unwrap_err().to_string();
        assert!(err.contains("folder"), "{err}");
        std::fs::write(&big, "track = \"f1_esp\"\n").unwrap();
        assert_eq!(read_config_text(&big).unwrap(), "track = \"f1_esp\"\n");
        assert_eq!(
            read_config_table(&big).unwrap()["track"].as_str(),
            Some("f1_esp")
        );
        std::fs::write(&big, "track = \n").unwrap();
        let err = read_config_table(&big).unwrap_err().to_string();
        assert!(err.contains("big.toml") && err.contains("line 1"), "{err}");
    }
}
