//! A scene: the cameras and images of one dataset (synthetic benchmark or DyCheck), as
//! stored in a scene directory.
//!
//! Layout of `SCENE_DIR`: `cameras.parquet` (all train and eval images), the image, depth
//! and mask files it names (paths relative to `SCENE_DIR`), and optionally
//! `tracks_3d.parquet` / `tracks_2d.parquet` (ground-truth or prior tracks), and optionally
//! `priors.json`, the manifest that says which files a monocular pipeline sees (the priors)
//! and which are ground truth kept for evaluation ([`MonocularInputs`]).
//! [`Scene::ground_truth`] reads one image's references for the stages that compare with it;
//! what the images' alpha channel means ([`GtAlpha`]) is a scene property recorded in the
//! cameras table's metadata under [`GT_ALPHA_KEY`].

use std::path::{Path, PathBuf};

use crate::tables::{self, Provenance, Table};

use crate::formats::png::Image;
use crate::formats::{npy, png};
use crate::render::RenderCamera;
pub use crate::tables::cameras::{Camera, Pinhole, Split};
use crate::util::fs::IoError;

/// The render camera of a scene camera (distortion is not rendered; near 0.01, far 1e10).
impl From<&Camera> for RenderCamera {
    fn from(c: &Camera) -> Self {
        RenderCamera {
            fx: c.pinhole.fx as f32,
            fy: c.pinhole.fy as f32,
            cx: c.pinhole.cx as f32,
            cy: c.pinhole.cy as f32,
            w2c: c.w2c_mat().as_mat4(),
            width: c.pinhole.width,
            height: c.pinhole.height,
            near: 0.01,
            far: 1e10,
        }
    }
}

/// Key of the cameras table's metadata that records the scene's [`GtAlpha`]
/// (`coverage` or `ignore`).
pub const GT_ALPHA_KEY: &str = "usplat4d.gt_alpha";

/// What the alpha channel of a scene's images means, hence how every stage that compares
/// with the ground truth reads its colour (issue 15 item 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum GtAlpha {
    /// Alpha is the object's coverage (synthetic scenes): the colour is composited over the
    /// render background, as the render it is compared with.
    Coverage,
    /// Alpha is not coverage (DyCheck: 0 where the LiDAR depth is missing, over valid
    /// colour): the colour is the plain RGB, alpha is ignored.
    Ignore,
}

impl GtAlpha {
    /// The spelling stored under [`GT_ALPHA_KEY`].
    pub fn as_str(self) -> &'static str {
        match self {
            GtAlpha::Coverage => "coverage",
            GtAlpha::Ignore => "ignore",
        }
    }

    /// The colour `[H, W, 3]` of `img` read as this mode says.
    pub fn rgb(self, img: &Image, background: [f32; 3]) -> Image {
        match self {
            GtAlpha::Coverage => img.rgb_over(background),
            GtAlpha::Ignore if img.channels == 4 => {
                let data = img.data.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
                Image { width: img.width, height: img.height, channels: 3, data }
            }
            GtAlpha::Ignore => img.rgb_over(background),
        }
    }
}

/// The references of one camera image, read from the scene directory.
#[derive(Debug, Clone)]
pub struct GroundTruth {
    /// `[H, W, 3]` colour composited over the requested background.
    pub rgb: Image,
    /// `[H, W, 1]` mask (channel 0 of the mask PNG), when asked for and the camera has one.
    pub mask: Option<Image>,
    /// `[H, W]` z-depth (0 = invalid), when asked for and the camera has one.
    pub depth: Option<Vec<f32>>,
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

    /// Write the cameras table of this scene atomically, recording `gt_alpha`.
    pub fn save_with(&self, provenance: &Provenance, gt_alpha: GtAlpha) -> tables::Result<()> {
        let prov = provenance.clone().with_metadata(GT_ALPHA_KEY, gt_alpha.as_str());
        tables::cameras::write(&Self::cameras_path(&self.dir), &self.cameras, &prov)
    }

    /// Write the cameras table of this scene atomically (alpha is coverage).
    pub fn save(&self, provenance: &Provenance) -> tables::Result<()> {
        self.save_with(provenance, GtAlpha::Coverage)
    }

    /// What the alpha of this scene's images means: the cameras table's [`GT_ALPHA_KEY`];
    /// without one, `ignore` for tables written by `import dycheck` (before the key existed)
    /// and `coverage` otherwise (also when the scene has no cameras table on disk).
    pub fn gt_alpha(&self) -> tables::Result<GtAlpha> {
        let path = Self::cameras_path(&self.dir);
        if !path.exists() {
            return Ok(GtAlpha::Coverage);
        }
        let r = tables::TableReader::open::<tables::cameras::CamerasTable>(&path)?;
        match r.metadata_value(GT_ALPHA_KEY).as_deref() {
            Some("coverage") => Ok(GtAlpha::Coverage),
            Some("ignore") => Ok(GtAlpha::Ignore),
            None if r.metadata_value(tables::io::KEY_STAGE).as_deref()
                == Some("import dycheck") =>
            {
                Ok(GtAlpha::Ignore)
            }
            None => Ok(GtAlpha::Coverage),
            Some(other) => Err(tables::Error::Mismatch {
                path,
                msg: format!("metadata {GT_ALPHA_KEY} is '{other}', expected coverage or ignore"),
            }),
        }
    }

    /// The ground-truth colour `[H, W, 3]` of `cam`'s image as [`Scene::gt_alpha`] says
    /// (over `background` for coverage alpha); errors name the file.
    pub fn ground_truth_rgb(&self, cam: &Camera, background: [f32; 3]) -> anyhow::Result<Image> {
        let img = png::read_png(&self.resolve(&cam.image_path))?;
        Ok(self.gt_alpha()?.rgb(&img, background))
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
            Err(cause) => return Err(IoError { path, cause }.into()),
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

    /// Read the colour of `cam`'s image ([`Scene::ground_truth_rgb`]), and its mask and
    /// depth map when asked for (and the camera has them); they must match the image's size.
    /// Errors name the file.
    pub fn ground_truth(
        &self,
        cam: &Camera,
        background: [f32; 3],
        with_mask: bool,
        with_depth: bool,
    ) -> anyhow::Result<GroundTruth> {
        let rgb = self.ground_truth_rgb(cam, background)?;
        let (w, h) = (rgb.width, rgb.height);
        let mask = match (&cam.mask_path, with_mask) {
            (Some(m), true) => {
                let path = self.resolve(m);
                let img = png::read_png(&path)?;
                if (img.width, img.height) != (w, h) {
                    anyhow::bail!(
                        "{}: mask is {}x{}, the image is {w}x{h}",
                        path.display(),
                        img.width,
                        img.height
                    );
                }
                Some(img.channel(0))
            }
            _ => None,
        };
        let depth = match (&cam.depth_path, with_depth) {
            (Some(d), true) => {
                let path = self.resolve(d);
                let depth = npy::read_npy_f32(&path)?.1;
                if depth.len() != w * h {
                    anyhow::bail!("{}: depth map is not {w}x{h}", path.display());
                }
                Some(depth)
            }
            _ => None,
        };
        Ok(GroundTruth { rgb, mask, depth })
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
