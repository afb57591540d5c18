//! A DyCheck sequence's image list: `splits/{train,val}.json` with the camera file of every
//! image, `scene.json` and `extra.json`, and the camera path in our conventions
//! ([`read_camera_path`]).
//!
//! Frames: the training split must name one camera; its time ids, sorted, give frames
//! 0..T-1 (frame = rank of the time id). A validation image takes the frame of the training
//! image with the same time id. Every (camera, frame) must be unique across both splits.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::camera_json::DycheckCamera;
use super::json::Obj;
use super::{Error, Result, World};
use crate::scene::{Camera, Split};

/// One split file `{frame_names, time_ids, camera_ids}` (equal lengths).
#[derive(Debug, Clone, Default, PartialEq)]
pub(super) struct SplitFile {
    pub frame_names: Vec<String>,
    pub time_ids: Vec<u32>,
    pub camera_ids: Vec<u32>,
}

impl SplitFile {
    fn read(path: &Path) -> Result<Self> {
        let value = super::read_json(path, None)?;
        let o = Obj::new(path, &value)?;
        let s = SplitFile {
            frame_names: o.strings("frame_names")?,
            time_ids: o.u32s("time_ids")?,
            camera_ids: o.u32s("camera_ids")?,
        };
        let n = s.frame_names.len();
        for (key, len) in [("time_ids", s.time_ids.len()), ("camera_ids", s.camera_ids.len())] {
            if len != n {
                return Err(o.err(key, format!("has {len} entries but 'frame_names' has {n}")));
            }
        }
        Ok(s)
    }

    /// The JSON object of this split.
    pub(super) fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "frame_names": self.frame_names,
            "time_ids": self.time_ids,
            "camera_ids": self.camera_ids,
        })
    }
}

/// `scene.json`: DyCheck's normalisation `pos' = (pos − center)·scale` and near/far in the
/// normalised frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct SceneInfo {
    pub center: [f64; 3],
    pub scale: f64,
    pub near: f64,
    pub far: f64,
}

impl SceneInfo {
    /// Read `path`; `Ok(None)` when it does not exist.
    pub(super) fn read(path: &Path) -> Result<Option<Self>> {
        if !path.exists() {
            return Ok(None);
        }
        let value = super::read_json(path, None)?;
        let o = Obj::new(path, &value)?;
        let c = o.vec("center", 3)?;
        let scale = o.f64("scale")?;
        if scale <= 0.0 {
            return Err(o.err("scale", format!("must be positive, got {scale}")));
        }
        Ok(Some(SceneInfo {
            center: [c[0], c[1], c[2]],
            scale,
            near: o.f64("near")?,
            far: o.f64("far")?,
        }))
    }
}

/// One image of the sequence.
#[derive(Debug, Clone)]
pub struct Entry {
    /// DyCheck frame name, e.g. `1_00005` (file stem of its camera, rgb, depth, ...).
    pub name: String,
    /// DyCheck time id.
    pub time_id: u32,
    /// DyCheck camera id.
    pub camera_id: u32,
    /// Train (from `splits/train.json`) or eval (`splits/val.json`).
    pub split: Split,
    /// Our frame index 0..T-1.
    pub frame: u32,
    /// The camera file's contents.
    pub camera: DycheckCamera,
}

/// The images of a DyCheck sequence: training images by frame, then validation images in
/// split order.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The sequence directory.
    pub dir: PathBuf,
    /// Every image.
    pub entries: Vec<Entry>,
}

impl Sequence {
    /// Read the splits and camera files of sequence `dir`.
    pub fn read(dir: &Path) -> Result<Self> {
        let train_path = dir.join("splits").join("train.json");
        let val_path = dir.join("splits").join("val.json");
        let train = SplitFile::read(&train_path)?;
        let val = SplitFile::read(&val_path)?;
        if train.frame_names.is_empty() {
            return Err(Error::File {
                path: train_path,
                msg: "the training split is empty".into(),
            });
        }
        if let Some(i) = train.camera_ids.iter().position(|c| *c != train.camera_ids[0]) {
            return Err(Error::Key {
                path: train_path,
                key: format!("camera_ids[{i}]"),
                msg: format!(
                    "camera {} differs from camera {} of entry 0; the training split must be one \
                     camera (a monocular video)",
                    train.camera_ids[i], train.camera_ids[0]
                ),
            });
        }
        let mut order: Vec<usize> = (0..train.time_ids.len()).collect();
        order.sort_by_key(|&i| train.time_ids[i]);
        let mut frame_of_time = HashMap::new();
        for (frame, &i) in order.iter().enumerate() {
            if let Some(j) = frame_of_time.insert(train.time_ids[i], (frame as u32, i)) {
                return Err(Error::Key {
                    path: train_path,
                    key: format!("time_ids[{i}]"),
                    msg: format!("time id {} repeats entry {}", train.time_ids[i], j.1),
                });
            }
        }
        let mut entries = Vec::with_capacity(train.frame_names.len() + val.frame_names.len());
        let mut seen: HashMap<(u32, u32), (&Path, usize)> = HashMap::new();
        let items = order
            .iter()
            .map(|&i| (&train, &train_path, Split::Train, i))
            .chain((0..val.frame_names.len()).map(|i| (&val, &val_path, Split::Eval, i)));
        for (s, path, split, i) in items {
            let time_id = s.time_ids[i];
            let camera_id = s.camera_ids[i];
            let frame = match frame_of_time.get(&time_id) {
                Some(&(f, _)) => f,
                None => {
                    return Err(Error::Key {
                        path: path.clone(),
                        key: format!("time_ids[{i}]"),
                        msg: format!("time id {time_id} has no training image"),
                    });
                }
            };
            if let Some((p, j)) = seen.insert((camera_id, frame), (path, i)) {
                return Err(Error::Key {
                    path: path.clone(),
                    key: format!("frame_names[{i}]"),
                    msg: format!(
                        "camera {camera_id} at time id {time_id} is also entry {j} of {}",
                        p.display()
                    ),
                });
            }
            let name = &s.frame_names[i];
            if name.is_empty() || name.contains(['/', '\\']) || name.starts_with('.') {
                return Err(Error::Key {
                    path: path.clone(),
                    key: format!("frame_names[{i}]"),
                    msg: format!("'{name}' is not a file name"),
                });
            }
            let cam_path = dir.join("camera").join(format!("{name}.json"));
            let file =
                path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
            let needed_by = format!("splits/{file} entry {i}");
            let camera = DycheckCamera::read(&cam_path, Some(&needed_by))?;
            entries.push(Entry { name: name.clone(), time_id, camera_id, split, frame, camera });
        }
        Ok(Sequence { dir: dir.to_path_buf(), entries })
    }

    /// Our cameras at downscale `factor` in `world`, in entry order, with the scene layout's
    /// paths: `rgb/<cam>/<frame:05>.png` for every image, `depth/<cam>/<frame:05>.npy` for
    /// training images, `mask/<cam>/<frame:05>.png` (covisibility) for validation images.
    pub fn cameras(&self, factor: u32, world: World) -> Result<Vec<Camera>> {
        if factor == 0 {
            return Err(Error::Factor(factor));
        }
        let transform = match world {
            World::Source => None,
            World::Dycheck => {
                let path = self.dir.join("scene.json");
                let info = SceneInfo::read(&path)?
                    .ok_or(Error::Missing { path, needed_by: Some("--world dycheck".into()) })?;
                Some((info.center, info.scale))
            }
        };
        self.entries
            .iter()
            .map(|e| {
                let cam_name = e.camera_id.to_string();
                let mut c = e.camera.to_camera(factor, transform, e.frame, &cam_name, e.split);
                if c.pinhole.width == 0 || c.pinhole.height == 0 {
                    return Err(Error::Key {
                        path: self.dir.join("camera").join(format!("{}.json", e.name)),
                        key: "image_size".into(),
                        msg: format!(
                            "{:?} at factor {factor} rounds to an empty image",
                            e.camera.image_size
                        ),
                    });
                }
                c.image_path = format!("rgb/{cam_name}/{:05}.png", e.frame);
                match e.split {
                    Split::Train => {
                        c.depth_path = Some(format!("depth/{cam_name}/{:05}.npy", e.frame))
                    }
                    Split::Eval => {
                        c.mask_path = Some(format!("mask/{cam_name}/{:05}.png", e.frame))
                    }
                }
                Ok(c)
            })
            .collect()
    }
}

/// The cameras of DyCheck sequence `dir` at downscale `factor` in the source world frame:
/// the training camera (split train, frames 0..T-1 by time id) then the validation cameras
/// (split eval, frame = the training frame at the same time id), with image, depth (train)
/// and covisibility mask (eval) paths in the scene layout. See the module docs for the
/// intrinsics, pixel-centre and distortion conventions.
pub fn read_camera_path(dir: &Path, factor: u32) -> Result<Vec<Camera>> {
    if factor == 0 {
        return Err(Error::Factor(factor));
    }
    Sequence::read(dir)?.cameras(factor, World::Source)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn factor_zero_is_an_error() {
        let err = read_camera_path(Path::new("nowhere"), 0).unwrap_err();
        assert_eq!(err.to_string(), "factor must be at least 1, got 0");
    }
}
