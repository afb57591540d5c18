//! DyCheck iPhone sequences (Gao et al., NeurIPS 2022): reading them into a scene directory
//! (`usplat4d import dycheck`), reading their camera path alone (used by `synth` to render
//! along a real handheld trajectory), and writing a scene back in the DyCheck folder layout.
//!
//! A DyCheck sequence directory holds `camera/<cam>_<t:05d>.json` (one camera per image),
//! `splits/{train,val}.json`, `rgb/{1x,2x}/<name>.png`, `depth/{1x,2x}/<name>.npy` (train
//! only), `covisible/2x/val/<name>.png`, `keypoint/2x/train/<name>.json`, `scene.json` and
//! `extra.json` (reference: formats-and-protocols.md §3).
//!
//! Mapping to our scene (DESIGN.md conventions):
//! - Camera names are the DyCheck camera ids as strings ("0" = the training phone, "1",
//!   "2" = the validation phones). Training frames are the ranks of the training time ids
//!   (0..T-1; DyCheck's train time ids are already 0..T-1); a validation image gets the
//!   frame of the training image with the same time id.
//! - Pixel coordinates: DyCheck's cameras use `use_center`, i.e. the pixel with integer
//!   index (i, j) has continuous coordinate (i + 0.5, j + 0.5) and K applies to those
//!   coordinates. That is our convention too, so the principal point is copied unchanged;
//!   no ±0.5 shift is applied anywhere. (The stored DyCheck keypoints are integer pixel
//!   indices at 2x: our coordinates at factor F are `(x + 0.5)·2/F`, [`to_scene_pixel`].)
//! - Intrinsics at downscale `factor` follow DyCheck's `rescale_image_domain(1/factor)`:
//!   focal length and principal point times `1/factor`, image size
//!   `round(size · (1/factor))` with Python's round-half-to-even.
//!   `fx = f/factor`, `fy = f·pixel_aspect_ratio/factor`; non-zero skew is rejected.
//! - `w2c = [O | −O·position]`; distortion `[k1, k2, k3, p1, p2]` kept when non-zero (our
//!   [`crate::scene::Camera::project`] applies the same model as DyCheck's `project`).
//! - World frame: [`World::Source`] keeps positions and depth as stored (metres for the
//!   iPhone captures); [`World::Dycheck`] applies DyCheck's parser normalisation
//!   `pos' = (pos − center)·scale`, `depth' = depth·scale` from `scene.json`.

mod camera_json;
mod import;
mod json;
mod keypoints;
mod layout;
mod sequence;

use std::path::PathBuf;

use crate::util::fs::IoError;

pub use camera_json::DycheckCamera;
pub use import::{ImportDycheckParams, run_import};
pub use keypoints::{
    KEYPOINT_DIR, Keypoint, SceneKeypoints, read_keypoints, read_scene_keypoints,
    to_keypoint_index, to_scene_pixel,
};
pub use layout::{over_white, write_layout};
pub use sequence::{Entry, Sequence, read_camera_path};

/// Which world frame imported cameras and depth use.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum World {
    /// Positions and depth as the camera files and depth maps store them (metres).
    #[default]
    Source,
    /// DyCheck's normalised frame: `pos' = (pos − center)·scale`, `depth' = depth·scale`
    /// (`scene.json`), the frame of DyCheck's baselines and of its near/far.
    Dycheck,
}

/// Errors of reading or writing DyCheck sequences; each names the file (and the key).
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file is malformed or inconsistent with the others.
    #[error("{}: {msg}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A required file does not exist.
    #[error("{}: file not found{}", path.display(), needed_by.as_ref().map(|b| format!(" (needed by {b})")).unwrap_or_default())]
    Missing {
        /// The missing file.
        path: PathBuf,
        /// What names or requires it, e.g. `splits/train.json entry 5`.
        needed_by: Option<String>,
    },
    /// A file could not be read or written.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A file is not valid JSON.
    #[error("{}: malformed JSON: {error}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// The parser's error (with line and column; in the message, not chained).
        error: serde_json::Error,
    },
    /// A JSON key is missing or has a wrong value.
    #[error("{}: key '{key}': {msg}", path.display())]
    Key {
        /// The file.
        path: PathBuf,
        /// The key (with an index for list entries, e.g. `time_ids[3]`).
        key: String,
        /// What is wrong.
        msg: String,
    },
    /// A downscale factor of 0.
    #[error("factor must be at least 1, got {0}")]
    Factor(u32),
    /// The scene cannot be written as a DyCheck sequence.
    #[error("{0}")]
    Scene(String),
    /// An image or array file failed. (Not chained as a source: the message already holds
    /// the cause, and `{:#}` would print it again.)
    #[error("{0}")]
    Image(crate::formats::Error),
    /// The cameras table failed (not chained, like [`Error::Image`]).
    #[error("{0}")]
    Table(crate::tables::Error),
}

impl From<crate::formats::Error> for Error {
    fn from(e: crate::formats::Error) -> Self {
        Error::Image(e)
    }
}

impl From<crate::tables::Error> for Error {
    fn from(e: crate::tables::Error) -> Self {
        Error::Table(e)
    }
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// Read `path` as JSON; a missing file is [`Error::Missing`] with `needed_by`.
fn read_json(path: &std::path::Path, needed_by: Option<&str>) -> Result<serde_json::Value> {
    let bytes = std::fs::read(path).map_err(|error| {
        if error.kind() == std::io::ErrorKind::NotFound {
            Error::Missing { path: path.into(), needed_by: needed_by.map(String::from) }
        } else {
            IoError::at(path)(error).into()
        }
    })?;
    serde_json::from_slice(&bytes).map_err(|error| Error::Json { path: path.into(), error })
}

/// Write `value` as pretty JSON (sorted keys), atomically.
fn write_json(path: &std::path::Path, value: &serde_json::Value) -> Result<()> {
    let mut bytes = serde_json::to_vec_pretty(value)
        .map_err(|e| Error::File { path: path.into(), msg: e.to_string() })?;
    bytes.push(b'\n');
    Ok(crate::util::fs::write_atomic(path, &bytes)?)
}

/// Nearest-neighbour resize of a row-major `[H, W, C]` array to `[h, w, C]`: output pixel
/// (x, y) takes input pixel `floor((x + 0.5)·W/w)`, `floor((y + 0.5)·H/h)` (pixel centres
/// at +0.5). An integer upscale replicates pixels, so box-downsampling it back is exact.
fn resize_nearest(
    data: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    w: usize,
    h: usize,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(w * h * channels);
    for y in 0..h {
        let sy = (((y as f64 + 0.5) * height as f64 / h as f64) as usize).min(height - 1);
        for x in 0..w {
            let sx = (((x as f64 + 0.5) * width as f64 / w as f64) as usize).min(width - 1);
            let i = (sy * width + sx) * channels;
            out.extend_from_slice(&data[i..i + channels]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn nearest_upscale_by_two_replicates_pixels() {
        let src = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let up = super::resize_nearest(&src, 3, 2, 1, 6, 4);
        assert_eq!(&up[..6], &[1.0, 1.0, 2.0, 2.0, 3.0, 3.0]);
        assert_eq!(&up[18..], &[4.0, 4.0, 5.0, 5.0, 6.0, 6.0]);
        assert_eq!(super::resize_nearest(&up, 6, 4, 1, 3, 2), src);
    }
}
