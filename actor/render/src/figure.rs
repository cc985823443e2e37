//! What every picture shares: the embedded font, and writing a drawing to PNG or SVG.
//!
//! plotters is built without system font support, so text needs the font embedded here
//! (DejaVu Sans, see `assets/DejaVuSans-LICENSE.txt`), registered once per process.

use ctxrace_run::run_dir::write_atomic_with;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Why a picture could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The embedded font could not be registered.
    #[error("the embedded font is not a valid TrueType font")]
    Font,
    /// plotters failed while drawing.
    #[error("drawing a picture: {0}")]
    Draw(Box<dyn std::error::Error + Send + Sync>),
    /// A picture that cannot be drawn as asked (its file type, its size, no frames), and why.
    #[error("{0}")]
    Refused(String),
    /// The picture's file could not be written.
    #[error("writing {}: {source}", .path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The file (or its temporary) could not be created or moved into place.
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// A drawing's result.
pub type Result<T, E = RenderError> = std::result::Result<T, E>;

impl RenderError {
    /// A failure writing `path`.
    pub fn write(path: &Path, source: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self::Write {
            path: path.to_path_buf(),
            source: Box::new(source),
        }
    }
}

/// DejaVu Sans, the font of every label.
static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Registers the embedded font as plotters' `sans-serif` (once; later calls return the first
/// result).
pub fn register_font() -> Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(RenderError::Font)
    }
}

/// A picture that can be drawn onto any plotters backend.
pub trait Figure {
    /// Picture size in pixels.
    fn size(&self) -> (u32, u32);
    /// Draws the picture.
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<()>
    where
        DB::ErrorType: 'static;
}

/// Draws `figure` into a PNG or SVG file chosen by the extension of `path`, written atomically
/// without following a link there ([`write_atomic_with`]).
pub fn save(figure: &impl Figure, path: &Path) -> Result<()> {
    let size = figure.size();
    let svg = match path.extension().and_then(|e| e.to_str()) {
        Some("png") => false,
        Some("svg") => true,
        _ => {
            return Err(RenderError::Refused(format!(
                "cannot draw to {}: the file name must end in .png or .svg",
                path.display()
            )))
        }
    };
    write_atomic_with(path, |tmp, _| {
        if svg {
            present(figure, SVGBackend::new(tmp, size), path)
        } else {
            present(figure, BitMapBackend::new(tmp, size), path)
        }
    })
}

/// Draws `figure` on `backend` and finishes the file at `path`.
fn present<DB: DrawingBackend>(figure: &impl Figure, backend: DB, path: &Path) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let root = backend.into_drawing_area();
    figure.draw(&root)?;
    root.present().map_err(|e| RenderError::write(path, e))
}

/// Draws `figure` as both `<stem>.png` and `<stem>.svg` in `dir`; returns the files written.
pub fn save_png_and_svg(figure: &impl Figure, dir: &Path, stem: &str) -> Result<Vec<PathBuf>> {
    ["png", "svg"]
        .iter()
        .map(|ext| {
            let path = dir.join(format!("{stem}.{ext}"));
            save(figure, &path)?;
            Ok(path)
        })
        .collect()
}

/// Turns a plotters drawing error into an error naming what was being drawn.
pub fn plot_err<E: std::error::Error + Send + Sync + 'static>(e: E) -> RenderError {
    RenderError::Draw(Box::new(e))
}
