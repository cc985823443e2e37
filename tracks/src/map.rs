//! Occupancy maps: a ROS map yaml (image, resolution, origin) and its PNG.
//!
//! Pixels with grey value `<= 128` are occupied, brighter ones drivable, as in f1tenth_gym. Rows
//! are flipped so that row 0 is the bottom of the image: pixel `(c, r)` covers the world square
//! `[o_x + c·res, o_x + (c+1)·res) × [o_y + r·res, o_y + (r+1)·res)`.

use crate::error::{ImageError, Result, TrackError};
use nalgebra::Point2;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// The fields of a ROS map yaml that ctxrace reads; other fields are ignored.
#[derive(Debug, Deserialize)]
struct MapYaml {
    image: String,
    resolution: f64,
    origin: Vec<f64>,
}

/// A binary occupancy grid in world coordinates.
#[derive(Clone, Debug)]
pub struct OccupancyMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Metres per pixel.
    pub resolution: f64,
    /// World position of the bottom-left corner of pixel (0, 0).
    pub origin: Point2<f64>,
    /// `true` where occupied, row-major with row 0 at the bottom.
    occupied: Vec<bool>,
    /// The image file it came from.
    pub image_path: PathBuf,
}

/// Grey values at or below this are occupied (f1tenth_gym's threshold).
const OCCUPIED_AT_OR_BELOW: u8 = 128;

/// The image a map yaml's `image:` names, if it is a plain file name (no folder part, not `.`
/// or `..`), which confines it to the yaml's folder: the only images ctxrace opens or fetches.
pub fn image_beside(image: &str) -> Option<&str> {
    let name = image.trim();
    (!name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\'])).then_some(name)
}

/// Decodes the image at `path` if it is a regular file: a link is not followed and a FIFO is
/// refused without waiting on it.
fn open_image(path: &Path) -> std::result::Result<image::DynamicImage, ImageError> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(libc::ELOOP) => ImageError::Link,
            _ => ImageError::Io(e),
        })?;
    if !file.metadata().map_err(ImageError::Io)?.is_file() {
        return Err(ImageError::NotAFile);
    }
    let mut limits = image::io::Limits::default();
    limits.max_image_width = Some(MAX_MAP_SIDE);
    limits.max_image_height = Some(MAX_MAP_SIDE);
    limits.max_alloc = Some(MAX_MAP_BYTES);
    let mut reader = image::io::Reader::new(std::io::BufReader::new(file))
        .with_guessed_format()
        .map_err(ImageError::Io)?;
    reader.limits(limits);
    reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => ImageError::TooLarge {
            max_side: MAX_MAP_SIDE,
            max_mib: MAX_MAP_BYTES >> 20,
        },
        e => ImageError::Decode(e),
    })
}

/// The most pixels a map image may have on a side (the paper's maps have at most 2,000).
pub const MAX_MAP_SIDE: u32 = 10_000;
/// The most memory a map image may take decoded (bytes): a 20,000-pixel-square PNG of a few
/// hundred KB would otherwise take gigabytes before the race starts.
pub const MAX_MAP_BYTES: u64 = 256 << 20;

impl OccupancyMap {
    /// Loads a map yaml and the image it names (relative to the yaml's folder).
    pub fn load(yaml_path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(yaml_path).map_err(|cause| TrackError::Io {
            path: yaml_path.to_path_buf(),
            cause,
        })?;
        let bad = |message: String| TrackError::Map {
            path: yaml_path.to_path_buf(),
            message,
        };
        let yaml: MapYaml = serde_yaml::from_str(&text).map_err(|e| {
            bad(format!(
                "{e}; expected keys image, resolution and origin: [x, y, yaw]"
            ))
        })?;
        if !(yaml.resolution.is_finite() && yaml.resolution > 0.0) {
            return Err(bad(format!(
                "resolution {} must be a positive number of metres per pixel",
                yaml.resolution
            )));
        }
        if yaml.origin.len() < 2 || yaml.origin.iter().any(|v| !v.is_finite()) {
            return Err(bad(format!(
                "origin {:?} must be [x, y, yaw] with finite numbers",
                yaml.origin
            )));
        }
        let name = image_beside(&yaml.image).ok_or_else(|| {
            bad(format!(
                "image '{}' is not a file name beside the yaml; name a PNG in the yaml's own \
                 folder (e.g. image: map.png), without a folder part",
                yaml.image
            ))
        })?;
        let image_path = yaml_path
            .parent()
            .unwrap_or_else(|| Path::new("."))
            .join(name);
        let img = open_image(&image_path)
            .map_err(|cause| TrackError::MapImage {
                path: image_path.clone(),
                yaml: yaml_path.to_path_buf(),
                cause,
            })?
            .to_luma8();
        let (width, height) = (img.width() as usize, img.height() as usize);
        let mut occupied = vec![false; width * height];
        for (c, r_top, px) in img.enumerate_pixels() {
            let r = height - 1 - r_top as usize;
            occupied[r * width + c as usize] = px.0[0] <= OCCUPIED_AT_OR_BELOW;
        }
        Ok(Self {
            width,
            height,
            resolution: yaml.resolution,
            origin: Point2::new(yaml.origin[0], yaml.origin[1]),
            occupied,
            image_path,
        })
    }

    /// Whether pixel `(c, r)` (row 0 at the bottom) is occupied; outside the image counts as occupied.
    pub fn is_occupied(&self, c: isize, r: isize) -> bool {
        if c < 0 || r < 0 || c as usize >= self.width || r as usize >= self.height {
            return true;
        }
        self.occupied[r as usize * self.width + c as usize]
    }

    /// The pixel holding a world point, if inside the image.
    pub fn pixel_of(&self, p: &Point2<f64>) -> Option<(usize, usize)> {
        let c = ((p.x - self.origin.x) / self.resolution).floor();
        let r = ((p.y - self.origin.y) / self.resolution).floor();
        (c >= 0.0 && r >= 0.0 && (c as usize) < self.width && (r as usize) < self.height)
            .then_some((c as usize, r as usize))
    }

    /// Whether the pixel holding the world point `p` is occupied; outside the image counts as
    /// occupied (f1tenth_gym's `check_location`, which the paper's gym ran on each car's centre).
    pub fn occupied_at(&self, p: &Point2<f64>) -> bool {
        match self.pixel_of(p) {
            Some((c, r)) => self.occupied[r * self.width + c],
            None => true,
        }
    }

    /// World position of the centre of pixel `(c, r)`, in half-pixel units `(2c+1, 2r+1)/2`.
    pub fn half_pixel_to_world(&self, hx: i64, hy: i64) -> Point2<f64> {
        Point2::new(
            self.origin.x + (hx as f64 * 0.5 + 0.5) * self.resolution,
            self.origin.y + (hy as f64 * 0.5 + 0.5) * self.resolution,
        )
    }

    /// World extent `(min, max)` of the image.
    pub fn extent(&self) -> (Point2<f64>, Point2<f64>) {
        (
            self.origin,
            self.origin
                + nalgebra::Vector2::new(
                    self.width as f64 * self.resolution,
                    self.height as f64 * self.resolution,
                ),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error of loading a map yaml whose `image:` is `image`, in `dir`.
    fn load_error(dir: &Path, image: &str) -> String {
        let yaml = dir.join("m.yaml");
        std::fs::write(
            &yaml,
            format!("image: {image}\nresolution: 0.05\norigin: [0, 0, 0]\n"),
        )
        .unwrap();
        OccupancyMap::load(&yaml).unwrap_err().to_string()
    }

    #[test]
    fn the_image_is_confined_to_regular_files_beside_the_yaml() {
        let dir = tempfile::tempdir().unwrap();
        for image in ["../../etc/passwd", "/etc/passwd", "..", "sub/map.png"] {
            let err = load_error(dir.path(), image);
            assert!(
                err.contains(&format!(
                    "image '{image}' is not a file name beside the yaml"
                )),
                "{err}"
            );
        }
        let fifo = std::ffi::CString::new(
            dir.path()
                .join("fifo.png")
                .into_os_string()
                .into_encoded_bytes(),
        )
        .unwrap();
        // SAFETY: mkfifo reads the NUL-terminated path `fifo` owns, nothing else.
        assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
        let err = load_error(dir.path(), "fifo.png");
        assert!(
            err.contains("fifo.png") && err.contains("not a regular file"),
            "{err}"
        );
        std::os::unix::fs::symlink("/etc/passwd", dir.path().join("link.png")).unwrap();
        let err = load_error(dir.path(), "link.png");
        assert!(err.contains("symbolic link"), "{err}");
        assert_eq!(image_beside(" map.png "), Some("map.png"));
    }

    /// A tiny PNG can declare a huge image: refused from its header, before it is decoded.
    #[test]
    fn an_image_larger_than_a_map_may_be_is_refused_before_decoding() {
        let dir = tempfile::tempdir().unwrap();
        image::GrayImage::new(MAX_MAP_SIDE + 1, 1)
            .save(dir.path().join("wide.png"))
            .unwrap();
        let err = load_error(dir.path(), "wide.png");
        assert!(
            err.contains("wide.png") && err.contains("larger than a map may be"),
            "{err}"
        );
    }
}
