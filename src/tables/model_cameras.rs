//! The `model_cameras` table: the base model's own camera of each training frame (MoSca's
//! solved poses and intrinsics, SoM's refined and normalised ones), in the model's world
//! frame, one row per frame 0..T-1; and `scene_to_model.json`, the similarity that maps the
//! scene's world frame to the model's (`x_model = s·R·x_scene + t`).
//!
//! Both are optional parts of a model directory, written by the importers; stages that
//! render training frames use these cameras when present (see `Model::training_camera`).

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, UInt32Array};
use arrow::datatypes::{DataType, Schema, SchemaRef, UInt32Type};

use super::cameras::{Camera, Pinhole};
use super::io::{Columns, Table, TableReader, batch, field, write_table};
use super::{Error, Provenance, Result};
use crate::util::fs::IoError;

/// Marker type of the `model_cameras` table.
pub struct ModelCamerasTable;

impl Table for ModelCamerasTable {
    const NAME: &'static str = "model_cameras";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        let frame = field("frame", DataType::UInt32);
        Arc::new(Schema::new([[frame].as_slice(), &Pinhole::fields()].concat()))
    }
}

/// The base model's camera of one training frame (OpenCV axes, pixel centres at +0.5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelCamera {
    /// Training frame t.
    pub frame: u32,
    /// Intrinsics (pixels of a `width`×`height` image) and world-to-camera, in the
    /// model's world frame.
    pub pinhole: Pinhole,
}

/// Write `cams` (frames 0..T-1 in order) to `path` atomically.
pub fn write(path: &Path, cams: &[ModelCamera], provenance: &Provenance) -> Result<()> {
    let pinholes: Vec<&Pinhole> = cams.iter().map(|c| &c.pinhole).collect();
    let frame: ArrayRef = Arc::new(UInt32Array::from_iter_values(cams.iter().map(|c| c.frame)));
    let cols = [[frame].as_slice(), &Pinhole::columns(&pinholes)].concat();
    write_table::<ModelCamerasTable>(path, provenance, [batch::<ModelCamerasTable>(cols)])
}

/// Read and validate `path`: frames 0..T-1 in order, finite values, positive sizes.
pub fn read(path: &Path) -> Result<Vec<ModelCamera>> {
    let reader = TableReader::open::<ModelCamerasTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let frame = c.values::<UInt32Type>("frame")?;
    let pinholes = Pinhole::read(path, &c)?;
    for (i, &f) in frame.iter().enumerate() {
        if f as usize != i {
            return Err(Error::Value {
                path: path.to_path_buf(),
                column: "frame".into(),
                row: i as u64,
                msg: format!("frame {f} at row {i}: expected frames 0..T-1 in order"),
            });
        }
    }
    Ok(frame.iter().zip(pinholes).map(|(&frame, pinhole)| ModelCamera { frame, pinhole }).collect())
}

/// A similarity `x_model = scale · rotation · x_scene + translation`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Similarity {
    /// Uniform scale s > 0.
    pub scale: f64,
    /// Rotation R, row-major 3x3.
    pub rotation: [[f64; 3]; 3],
    /// Translation t.
    pub translation: [f64; 3],
    /// How it was obtained (`identity: no scene given`, `fit to the scene's training cameras`).
    pub source: String,
}

impl Similarity {
    /// The identity, with its reason.
    pub fn identity(source: &str) -> Self {
        Similarity {
            scale: 1.0,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
            source: source.into(),
        }
    }

    /// Map a scene point into the model frame.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        std::array::from_fn(|i| {
            self.scale * (r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2]) + self.translation[i]
        })
    }

    /// The model camera of scene camera `c`: its intrinsics, and its pose mapped by
    /// [`Similarity::w2c_to_model`].
    pub fn camera_to_model(&self, c: &Camera) -> ModelCamera {
        let pinhole = Pinhole { w2c: self.w2c_to_model(&c.pinhole.w2c), ..c.pinhole };
        ModelCamera { frame: c.frame, pinhole }
    }

    /// The world-to-camera matrix (row-major) in the model frame of a scene camera `w2c`:
    /// `[R_c·Rᵀ | s·t_c − R_c·Rᵀ·t]` (camera coordinates scaled by s; projection unchanged).
    pub fn w2c_to_model(&self, w2c: &[f64; 16]) -> [f64; 16] {
        let rc = |i: usize, j: usize| w2c[i * 4 + j];
        let r = &self.rotation;
        let mut out = [0.0; 16];
        for i in 0..3 {
            for j in 0..3 {
                out[i * 4 + j] = (0..3).map(|k| rc(i, k) * r[j][k]).sum();
            }
        }
        for i in 0..3 {
            let rt: f64 = (0..3).map(|j| out[i * 4 + j] * self.translation[j]).sum();
            out[i * 4 + 3] = self.scale * rc(i, 3) - rt;
        }
        out[15] = 1.0;
        out
    }
}

/// Write `sim` as pretty JSON to `path` atomically.
pub fn write_similarity(path: &Path, sim: &Similarity) -> Result<()> {
    let text = serde_json::to_string_pretty(sim).map_err(|e| IoError::at(path)(e.into()))?;
    Ok(crate::util::fs::write_atomic(path, text.as_bytes())?)
}

/// Read `path` (a [`Similarity`] as JSON), checking s > 0 and finite values.
pub fn read_similarity(path: &Path) -> Result<Similarity> {
    let text = std::fs::read_to_string(path).map_err(IoError::at(path))?;
    let bad = |msg: String| Error::Mismatch { path: path.to_path_buf(), msg };
    let sim: Similarity = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    let finite = sim.rotation.iter().flatten().chain(&sim.translation).all(|x| x.is_finite());
    if !(sim.scale.is_finite() && sim.scale > 0.0 && finite) {
        return Err(bad(format!("scale must be positive and all values finite, got {sim:?}")));
    }
    Ok(sim)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_cameras_round_trip_and_w2c_maps_points() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model_cameras.parquet");
        let mut w2c = [0.0; 16];
        for i in 0..4 {
            w2c[i * 5] = 1.0;
        }
        w2c[3] = 0.5;
        let cams: Vec<ModelCamera> = (0..3)
            .map(|t| ModelCamera {
                frame: t,
                pinhole: Pinhole {
                    fx: 50.0,
                    fy: 51.0,
                    cx: 32.0,
                    cy: 24.0,
                    width: 64,
                    height: 48,
                    w2c,
                },
            })
            .collect();
        write(&p, &cams, &Provenance::default()).unwrap();
        assert_eq!(read(&p).unwrap(), cams);
        // A point seen by the scene camera projects to the same pixel from the model camera.
        let (c, s) = (0.6f64.cos(), 0.6f64.sin());
        let sim = Similarity {
            scale: 2.5,
            rotation: [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.3, -1.0, 2.0],
            source: "test".into(),
        };
        let m = sim.w2c_to_model(&w2c);
        let x = [0.2, -0.1, 3.0];
        let cam = |w: &[f64; 16], p: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|i| (0..3).map(|j| w[i * 4 + j] * p[j]).sum::<f64>() + w[i * 4 + 3])
        };
        let a = cam(&w2c, x);
        let b = cam(&m, sim.apply(x));
        for i in 0..3 {
            assert!((b[i] - 2.5 * a[i]).abs() < 1e-12, "{a:?} {b:?}");
        }
        let sp = dir.path().join("scene_to_model.json");
        write_similarity(&sp, &sim).unwrap();
        assert_eq!(read_similarity(&sp).unwrap(), sim);
    }
}
