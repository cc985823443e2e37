//! Errors raised while loading, building or optimising a track.

use std::path::PathBuf;

/// Everything that can go wrong with a track: each variant names what, where and how to fix it.
#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    /// A file could not be read.
    #[error("cannot read {path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause (in the message, not a `source`, so that a chain prints it once).
        cause: std::io::Error,
    },
    /// A CSV cell is not a number, or a row has the wrong number of columns.
    #[error("{path}:{line}: {message}")]
    Csv {
        /// The file.
        path: PathBuf,
        /// One-based line number.
        line: usize,
        /// What is wrong and what was expected.
        message: String,
    },
    /// The map yaml is malformed or inconsistent with its image.
    #[error("map {path}: {message}")]
    Map {
        /// The yaml or image file.
        path: PathBuf,
        /// What is wrong and how to fix it.
        message: String,
    },
    /// A curve has too few distinct points to describe a closed track.
    #[error("{what} has {found} distinct points; a closed track needs at least {needed}")]
    TooFewPoints {
        /// Which curve (with its file when known).
        what: String,
        /// Points found.
        found: usize,
        /// Points needed.
        needed: usize,
    },
    /// A track name did not resolve to any file.
    #[error("unknown track '{name}' in {dir} and the per-user tracks folder; tracks found: {found}. Fetch it with `ctxrace track download {name}`, or pass --tracks-dir (or set CTXRACE_TRACKS_DIR), a path to a map yaml, or generated:SEED")]
    UnknownTrack {
        /// The name asked for.
        name: String,
        /// The directory searched.
        dir: PathBuf,
        /// Comma-separated names that exist.
        found: String,
    },
    /// A track name names several tracks in one folder and its subfolders.
    #[error("track '{name}' is ambiguous: {} each hold one; pass the map yaml's path instead", .candidates.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "))]
    AmbiguousTrack {
        /// The name asked for.
        name: String,
        /// The map yamls of that name.
        candidates: Vec<PathBuf>,
    },
    /// A track's file could not be downloaded.
    #[error("downloading {url}: {message}")]
    Download {
        /// The file's address.
        url: String,
        /// Why, and what to do.
        message: String,
    },
    /// A parameter is outside its valid range.
    #[error("invalid {what}: {message}")]
    Invalid {
        /// The parameter.
        what: String,
        /// Why, and the valid range.
        message: String,
    },
    /// The reference material beside the workspace (`../shared`) lacks a folder a check needs.
    #[error(
        "{} not found: this check needs the project's reference material (the folder \
         `shared` beside the repository: the paper's maps and test vectors); put it there",
        .dir.display()
    )]
    MissingReference {
        /// The folder looked for.
        dir: PathBuf,
    },
    /// The image a map yaml names could not be opened as a regular image file.
    #[error(
        "map {}: cannot open the image named by {} ({cause}); the yaml's 'image' must name a \
         PNG beside it",
        .path.display(),
        .yaml.display()
    )]
    MapImage {
        /// The image file.
        path: PathBuf,
        /// The yaml that names it.
        yaml: PathBuf,
        /// Why it could not be opened.
        cause: ImageError,
    },
    /// The raceline optimisation failed.
    #[error("raceline optimisation failed: {0}")]
    Optimisation(String),
}

/// Why a map's image could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The path is a symbolic link.
    #[error("a symbolic link, which ctxrace does not follow")]
    Link,
    /// The path is not a regular file.
    #[error("not a regular file (a FIFO, device or folder)")]
    NotAFile,
    /// The file could not be opened or read.
    #[error("{0}")]
    Io(std::io::Error),
    /// The file is not an image that can be decoded.
    #[error("{0}")]
    Decode(image::ImageError),
    /// The image is larger than a map may be.
    #[error(
        "larger than a map may be (at most {max_side} pixels a side and {max_mib} MiB decoded; \
         the paper's maps have at most 2,000 pixels a side): is it the right image?"
    )]
    TooLarge {
        /// The most pixels a side may have.
        max_side: u32,
        /// The most memory the decoded image may take (MiB).
        max_mib: u64,
    },
}

/// Shorthand for results with [`TrackError`].
pub type Result<T> = std::result::Result<T, TrackError>;
