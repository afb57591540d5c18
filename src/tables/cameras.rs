//! The `cameras` table: one row per (camera, frame) image of a scene.
//!
//! Convention (DESIGN.md): OpenCV axes, `w2c` 4x4 row-major, pixel centres at +0.5,
//! intrinsics in pixels. Paths are relative to the scene directory. Rows are written in the
//! order given; readers validate finiteness, positive sizes and unique (camera, frame).

use std::path::Path;

use glam::{DMat3, DMat4, DVec3};
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, FixedSizeListArray, Float32Array, Float64Array, StringArray, UInt32Array,
};
use arrow::datatypes::{DataType, Field, Float32Type, Float64Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, fixed_list, nullable, write_table};
use super::{Error, Provenance, Result, validate};

/// Which part of the dataset an image belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// The monocular training video.
    Train,
    /// Held-out evaluation views (DyCheck "val").
    Eval,
}

impl Split {
    /// The name stored in the `split` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Eval => "eval",
        }
    }

    /// Parse a stored split name.
    pub fn parse(s: &str) -> Option<Split> {
        match s {
            "train" => Some(Split::Train),
            "eval" => Some(Split::Eval),
            _ => None,
        }
    }
}

/// A pinhole camera: intrinsics in pixels of a `width`×`height` image and the
/// world-to-camera pose, OpenCV axes (the columns `fx` to `w2c` of the `cameras` and
/// `model_cameras` tables).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel centres at +0.5).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// World-to-camera 4x4, row-major, OpenCV axes (x right, y down, z forward).
    pub w2c: [f64; 16],
}

impl Pinhole {
    /// A pinhole of focal length `focal` (both axes) with the principal point at the centre
    /// of a `width`×`height` image.
    pub fn centred(focal: f64, width: u32, height: u32, w2c: [f64; 16]) -> Pinhole {
        let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
        Pinhole { fx: focal, fy: focal, cx, cy, width, height, w2c }
    }

    /// The image size (W, H).
    pub fn size(&self) -> (usize, usize) {
        (self.width as usize, self.height as usize)
    }

    /// The table columns `fx`, `fy`, `cx`, `cy`, `width`, `height`, `w2c`, in this order.
    pub(super) fn fields() -> [Field; 7] {
        [
            field("fx", DataType::Float64),
            field("fy", DataType::Float64),
            field("cx", DataType::Float64),
            field("cy", DataType::Float64),
            field("width", DataType::UInt32),
            field("height", DataType::UInt32),
            field("w2c", fixed_list(DataType::Float64, 16)),
        ]
    }

    /// The columns of [`Pinhole::fields`] holding `pinholes`, one row each.
    pub(super) fn columns(pinholes: &[&Pinhole]) -> [ArrayRef; 7] {
        let f = |g: fn(&Pinhole) -> f64| -> ArrayRef {
            Arc::new(Float64Array::from_iter_values(pinholes.iter().map(|p| g(p))))
        };
        let u = |g: fn(&Pinhole) -> u32| -> ArrayRef {
            Arc::new(UInt32Array::from_iter_values(pinholes.iter().map(|p| g(p))))
        };
        let item = Arc::new(Field::new("item", DataType::Float64, false));
        let w2c: Vec<f64> = pinholes.iter().flat_map(|p| p.w2c).collect();
        let w2c = FixedSizeListArray::new(item, 16, Arc::new(Float64Array::from(w2c)), None);
        [
            f(|p| p.fx),
            f(|p| p.fy),
            f(|p| p.cx),
            f(|p| p.cy),
            u(|p| p.width),
            u(|p| p.height),
            Arc::new(w2c),
        ]
    }

    /// Read the columns of [`Pinhole::fields`] from `c`, checking that they are finite and,
    /// row by row, that the focal lengths are positive and the image is not empty.
    pub(super) fn read(path: &Path, c: &Columns) -> Result<Vec<Pinhole>> {
        let k: Vec<&[f64]> = ["fx", "fy", "cx", "cy"]
            .iter()
            .map(|n| c.values::<Float64Type>(n))
            .collect::<Result<_>>()?;
        let width = c.values::<UInt32Type>("width")?;
        let height = c.values::<UInt32Type>("height")?;
        let w2c = c.fixed_f64("w2c", 16)?;
        for (name, v) in [("fx", k[0]), ("fy", k[1]), ("cx", k[2]), ("cy", k[3])] {
            validate::finite(path, name, 0, v)?;
        }
        validate::finite_items(path, "w2c", 0, w2c, 16)?;
        let mut out = Vec::with_capacity(width.len());
        for i in 0..width.len() {
            let bad = |column: &str, msg: String| Error::Value {
                path: path.to_path_buf(),
                column: column.into(),
                row: i as u64,
                msg,
            };
            if width[i] == 0 || height[i] == 0 {
                return Err(bad(
                    "width",
                    format!("image size {}x{} is empty", width[i], height[i]),
                ));
            }
            if k[0][i] <= 0.0 || k[1][i] <= 0.0 {
                return Err(bad(
                    "fx",
                    format!("focal lengths must be positive, got {} {}", k[0][i], k[1][i]),
                ));
            }
            let mut m = [0.0; 16];
            m.copy_from_slice(&w2c[i * 16..i * 16 + 16]);
            out.push(Pinhole {
                fx: k[0][i],
                fy: k[1][i],
                cx: k[2][i],
                cy: k[3][i],
                width: width[i],
                height: height[i],
                w2c: m,
            });
        }
        Ok(out)
    }
}

/// One image's camera: a pinhole with optional distortion, OpenCV axes.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Time index 0..T-1 of the training video this image was taken at.
    pub frame: u32,
    /// Camera name (e.g. `"0"` for the training camera).
    pub camera: String,
    /// Train or eval.
    pub split: Split,
    /// Intrinsics, image size and pose.
    pub pinhole: Pinhole,
    /// RGB(A) PNG path relative to the scene directory.
    pub image_path: String,
    /// z-depth `.npy` path (float32, 0 = invalid), if any.
    pub depth_path: Option<String>,
    /// Mask PNG path (covisibility or foreground), if any.
    pub mask_path: Option<String>,
    /// Horizontal angular offset from the training camera, degrees (synthetic benchmark).
    pub angle_offset_deg: Option<f32>,
    /// Distortion `[k1, k2, k3, p1, p2]` when non-zero.
    pub distortion: Option<[f64; 5]>,
}

impl Camera {
    /// The camera `camera` of `frame` with the scene layout's image path
    /// `rgb/<camera>/<frame:05>.png`, and no depth, mask, angle offset or distortion.
    pub fn new(frame: u32, camera: &str, split: Split, pinhole: Pinhole) -> Camera {
        Camera {
            frame,
            camera: camera.into(),
            split,
            pinhole,
            image_path: format!("rgb/{camera}/{frame:05}.png"),
            depth_path: None,
            mask_path: None,
            angle_offset_deg: None,
            distortion: None,
        }
    }

    /// The world-to-camera matrix (glam is column-major; `w2c` is stored row-major).
    pub fn w2c_mat(&self) -> DMat4 {
        DMat4::from_cols_array(&self.pinhole.w2c).transpose()
    }

    /// Rotation part of world-to-camera.
    pub fn rotation(&self) -> DMat3 {
        DMat3::from_mat4(self.w2c_mat())
    }

    /// Camera centre in world coordinates.
    pub fn center(&self) -> DVec3 {
        let m = self.w2c_mat();
        m.inverse().w_axis.truncate()
    }

    /// Row-major `w2c` from a glam matrix.
    pub fn w2c_from_mat(m: DMat4) -> [f64; 16] {
        m.transpose().to_cols_array()
    }

    /// Pixel coordinates (pixel centres at +0.5) and z-depth of world point `p` (pinhole,
    /// distortion applied when present). `None` when behind the camera.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64, f64)> {
        let c = self.w2c_mat().transform_point3(p);
        if c.z <= 1e-9 {
            return None;
        }
        let (mut u, mut v) = (c.x / c.z, c.y / c.z);
        if let Some([k1, k2, k3, p1, p2]) = self.distortion {
            let r2 = u * u + v * v;
            let rad = 1.0 + r2 * (k1 + r2 * (k2 + k3 * r2));
            let du = 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
            let dv = 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v);
            u = u * rad + du;
            v = v * rad + dv;
        }
        let k = &self.pinhole;
        Some((k.fx * u + k.cx, k.fy * v + k.cy, c.z))
    }
}

/// Marker type of the `cameras` table.
pub struct CamerasTable;

impl Table for CamerasTable {
    const NAME: &'static str = "cameras";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        let mut fields = vec![
            field("frame", DataType::UInt32),
            field("camera", DataType::Utf8),
            field("split", DataType::Utf8),
        ];
        fields.extend(Pinhole::fields());
        fields.extend([
            field("image_path", DataType::Utf8),
            nullable("depth_path", DataType::Utf8),
            nullable("mask_path", DataType::Utf8),
            nullable("angle_offset_deg", DataType::Float32),
            nullable("distortion", fixed_list(DataType::Float64, 5)),
        ]);
        Arc::new(Schema::new(fields))
    }
}

/// Write `cameras` to `path` atomically (one row group).
pub fn write(path: &Path, cameras: &[Camera], provenance: &Provenance) -> Result<()> {
    let item = Arc::new(Field::new("item", DataType::Float64, false));
    let dist_valid: Vec<bool> = cameras.iter().map(|c| c.distortion.is_some()).collect();
    let dist: Vec<f64> = cameras.iter().flat_map(|c| c.distortion.unwrap_or([0.0; 5])).collect();
    let dist = FixedSizeListArray::new(
        item,
        5,
        Arc::new(Float64Array::from(dist)),
        Some(dist_valid.into()),
    );
    let pinholes: Vec<&Pinhole> = cameras.iter().map(|c| &c.pinhole).collect();
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(cameras.iter().map(|c| c.frame))),
        Arc::new(StringArray::from_iter_values(cameras.iter().map(|c| c.camera.as_str()))),
        Arc::new(StringArray::from_iter_values(cameras.iter().map(|c| c.split.as_str()))),
    ];
    cols.extend(Pinhole::columns(&pinholes));
    cols.extend::<[ArrayRef; 5]>([
        Arc::new(StringArray::from_iter_values(cameras.iter().map(|c| c.image_path.as_str()))),
        Arc::new(StringArray::from_iter(cameras.iter().map(|c| c.depth_path.as_deref()))),
        Arc::new(StringArray::from_iter(cameras.iter().map(|c| c.mask_path.as_deref()))),
        Arc::new(Float32Array::from_iter(cameras.iter().map(|c| c.angle_offset_deg))),
        Arc::new(dist),
    ]);
    write_table::<CamerasTable>(path, provenance, [batch::<CamerasTable>(cols)])
}

/// Read and validate the cameras of `path`.
pub fn read(path: &Path) -> Result<Vec<Camera>> {
    let reader = TableReader::open::<CamerasTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let frame = c.values::<UInt32Type>("frame")?;
    let camera = c.strings("camera")?;
    let split = c.strings("split")?;
    let image = c.strings("image_path")?;
    let depth = c.opt_strings("depth_path")?;
    let mask = c.opt_strings("mask_path")?;
    let angle = c.opt_values::<Float32Type>("angle_offset_deg")?;
    let dist_arr = c.get::<FixedSizeListArray>("distortion")?;
    let pinholes = Pinhole::read(path, &c)?;
    let value_err = |column: &str, row: usize, msg: String| Error::Value {
        path: path.to_path_buf(),
        column: column.into(),
        row: row as u64,
        msg,
    };
    let mut seen = std::collections::HashMap::new();
    let mut out = Vec::with_capacity(b.num_rows());
    for i in 0..b.num_rows() {
        let split = Split::parse(&split[i]).ok_or_else(|| {
            value_err("split", i, format!("unknown split '{}' (train or eval)", split[i]))
        })?;
        if let Some(first) = seen.insert((camera[i].clone(), frame[i]), i) {
            return Err(value_err(
                "camera",
                i,
                format!("camera '{}' frame {} repeats row {first}", camera[i], frame[i]),
            ));
        }
        let distortion = if dist_arr.is_valid(i) {
            let v = dist_arr.value(i);
            let v = v
                .as_any()
                .downcast_ref::<Float64Array>()
                .map(|a| a.values().to_vec())
                .unwrap_or_default();
            validate::finite_items(path, "distortion", i as u64, &v, 5)?;
            let mut d = [0.0; 5];
            d.copy_from_slice(&v[..5]);
            Some(d)
        } else {
            None
        };
        out.push(Camera {
            frame: frame[i],
            camera: camera[i].clone(),
            split,
            pinhole: pinholes[i],
            image_path: image[i].clone(),
            depth_path: depth[i].clone(),
            mask_path: mask[i].clone(),
            angle_offset_deg: angle[i],
            distortion,
        });
    }
    Ok(out)
}
