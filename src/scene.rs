//! A scene: the cameras and images of one dataset (synthetic benchmark or DyCheck), as
//! stored in a scene directory.
//!
//! Layout of `SCENE_DIR`: `cameras.parquet` (all train and eval images), the image, depth
//! and mask files it names (paths relative to `SCENE_DIR`), and optionally
//! `tracks_3d.parquet` / `tracks_2d.parquet` (ground-truth or prior tracks), and optionally
//! `priors.json`, the manifest that says which files a monocular pipeline sees (the priors)
//! and which are ground truth kept for evaluation ([`MonocularInputs`]).

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};

use crate::tables::{self, Provenance, Table};

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

/// One image's camera: a pinhole with optional distortion, OpenCV axes.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Time index 0..T-1 of the training video this image was taken at.
    pub frame: u32,
    /// Camera name (e.g. `"0"` for the training camera).
    pub camera: String,
    /// Train or eval.
    pub split: Split,
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
    /// The world-to-camera matrix (glam is column-major; `w2c` is stored row-major).
    pub fn w2c_mat(&self) -> DMat4 {
        DMat4::from_cols_array(&self.w2c).transpose()
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
        Some((self.fx * u + self.cx, self.fy * v + self.cy, c.z))
    }
}

/// The cameras of a scene directory.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scene directory; camera paths are relative to it.
    pub dir: PathBuf,
    /// Every image of the scene, train and eval.
    pub cameras: Vec<Camera>,
}

impl Scene {
    /// Path of the cameras table inside a scene directory.
    pub fn cameras_path(dir: &Path) -> PathBuf {
        dir.join(tables::cameras::CamerasTable::file_name())
    }

    /// Load the cameras of `dir`; train frames must be 0..T-1 without gaps.
    pub fn load(dir: &Path) -> tables::Result<Scene> {
        let path = Self::cameras_path(dir);
        let cameras = tables::cameras::read(&path)?;
        let scene = Scene { dir: dir.to_path_buf(), cameras };
        let mut frames: Vec<u32> = scene.train().map(|c| c.frame).collect();
        frames.sort_unstable();
        for (i, f) in frames.iter().enumerate() {
            if *f as usize != i {
                return Err(tables::Error::Frame {
                    path,
                    frame: i as u64,
                    msg: format!(
                        "training frames must be 0..T-1 without gaps; found frame {f} at position {i}"
                    ),
                });
            }
        }
        Ok(scene)
    }

    /// Write the cameras table of this scene atomically.
    pub fn save(&self, provenance: &Provenance) -> tables::Result<()> {
        tables::cameras::write(&Self::cameras_path(&self.dir), &self.cameras, provenance)
    }

    /// Training cameras (the monocular video), in table order.
    pub fn train(&self) -> impl Iterator<Item = &Camera> {
        self.cameras.iter().filter(|c| c.split == Split::Train)
    }

    /// Training cameras sorted by frame: index t is frame t.
    pub fn train_by_frame(&self) -> Vec<&Camera> {
        let mut v: Vec<&Camera> = self.train().collect();
        v.sort_by_key(|c| c.frame);
        v
    }

    /// Evaluation cameras, in table order.
    pub fn eval(&self) -> impl Iterator<Item = &Camera> {
        self.cameras.iter().filter(|c| c.split == Split::Eval)
    }

    /// Number of training frames T.
    pub fn num_frames(&self) -> usize {
        self.train().count()
    }

    /// Absolute path of a file named relative to the scene directory.
    pub fn resolve(&self, rel: &str) -> PathBuf {
        self.dir.join(rel)
    }

    /// Path of the priors manifest inside a scene directory.
    pub fn priors_path(dir: &Path) -> PathBuf {
        dir.join("priors.json")
    }

    /// What a monocular pipeline sees of this scene: the files `priors.json` names, or,
    /// without a manifest (DyCheck imports, older scenes), the scene's own depth maps and
    /// `tracks_2d.parquet`.
    pub fn monocular_inputs(&self) -> tables::Result<MonocularInputs> {
        let path = Self::priors_path(&self.dir);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(MonocularInputs {
                    depth_prefix: String::new(),
                    tracks_2d: "tracks_2d.parquet".into(),
                });
            }
            Err(cause) => return Err(tables::Error::Io { path, cause }),
        };
        let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
            tables::Error::Mismatch { path: path.clone(), msg: format!("not valid JSON: {e}") }
        })?;
        let key = |k: &str| -> tables::Result<String> {
            json.pointer(&format!("/monocular_inputs/{k}"))
                .and_then(|v| v.as_str())
                .map(String::from)
                .ok_or_else(|| tables::Error::Mismatch {
                    path: path.clone(),
                    msg: format!("key 'monocular_inputs.{k}' is missing or not a string"),
                })
        };
        Ok(MonocularInputs { depth_prefix: key("depth_prefix")?, tracks_2d: key("tracks_2d")? })
    }
}

/// The priors of a scene: the files a monocular pipeline (`init`) may read besides the
/// training cameras, their RGB images and their foreground masks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MonocularInputs {
    /// Prefix of the depth prior of a training camera: its depth is
    /// `SCENE_DIR/<depth_prefix><camera depth_path>` (empty: the scene's own depth).
    pub depth_prefix: String,
    /// The 2D tracks prior, relative to the scene directory.
    pub tracks_2d: String,
}

impl MonocularInputs {
    /// The depth prior of training camera `cam`, if it has a depth path.
    pub fn depth_path(&self, scene: &Scene, cam: &Camera) -> Option<PathBuf> {
        cam.depth_path.as_ref().map(|d| scene.resolve(&format!("{}{d}", self.depth_prefix)))
    }
}
