//! DyCheck's keypoint annotations, the ground truth of PCK-T (formats-and-protocols.md §3.3):
//! reading and writing `keypoint/2x/train/<frame_name>.json`, their pixel convention, and
//! the keypoint → frame mapping that `import dycheck` records in the scene's `scene.json`.
//!
//! A keypoint file is a JSON list of J rows `[x, y, v]`, one file per keyframe (DyCheck
//! annotates the 10 keyframes `linspace(0, T, 10, endpoint=False)` of the training split),
//! named after the training image (`0_00027.json`), next to `skeleton.json`. `x`, `y` are
//! integer pixel indices at DyCheck's 2x resolution; a keypoint is visible when `v == 1`
//! (DyCheck's test, exactly); invisible rows are `[0, 0, 0]`.
//!
//! Pixel convention: DyCheck's loader adds 0.5 (`use_center`), so the 2x continuous
//! coordinate is `x + 0.5`, and in a scene imported at factor F it is
//! `(x + 0.5)·2/F` ([`to_scene_pixel`]): the continuous image domain scales by 2/F, like
//! the intrinsics. (SoM reads `2·x` at 1x, without the offset: 1 px off at 1x.) The
//! inverse, for writing synthetic keypoints, is the index of the pixel that contains the
//! point, `floor(u·F/2)` ([`to_keypoint_index`]).
//!
//! `scene.json` of an imported scene holds `"keypoints": {"dir": "keypoint/2x/train",
//! "frames": {"<frame_name>": <frame>, ...}}` (frame = our training frame of that image);
//! [`read_scene_keypoints`] reads it with the top-level `"factor"`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::json::Obj;
use super::{Error, Result};
use crate::tables::tracks_2d::Tracks2dReader;
use crate::util::fs::IoError;

/// Keypoint directory of the training split, relative to a sequence or scene directory.
pub const KEYPOINT_DIR: &str = "keypoint/2x/train";
/// DyCheck's downscale factor of the keypoint coordinates (the `2x` of [`KEYPOINT_DIR`]).
pub const KEYPOINT_FACTOR: u32 = 2;
/// The skeleton file next to the keypoint files (not a keyframe).
pub const SKELETON: &str = "skeleton.json";
/// Number of keypoints `write_synthetic` picks from the ground-truth tracks (at most).
pub const SYNTHETIC_KEYPOINTS: usize = 16;

/// One stored keypoint row.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Column index at 2x (integer-valued as DyCheck stores it; not checked).
    pub x: f64,
    /// Row index at 2x.
    pub y: f64,
    /// `v == 1`.
    pub visible: bool,
}

/// Scene pixel coordinates (centres at +0.5) at import factor `factor` of the stored 2x
/// index `(x, y)`: `(x + 0.5)·2/factor`.
pub fn to_scene_pixel(x: f64, y: f64, factor: u32) -> [f64; 2] {
    let s = KEYPOINT_FACTOR as f64 / factor as f64;
    [(x + 0.5) * s, (y + 0.5) * s]
}

/// The 2x pixel index that contains scene point `(u, v)` of a scene at factor `factor`:
/// `floor(u·factor/2)`; [`to_scene_pixel`] of it is that pixel's centre.
pub fn to_keypoint_index(u: f64, v: f64, factor: u32) -> [f64; 2] {
    let s = factor as f64 / KEYPOINT_FACTOR as f64;
    [(u * s).floor(), (v * s).floor()]
}

/// The keypoint files of `dir` (`*.json` except [`SKELETON`]), sorted by name.
pub(super) fn list_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let io = IoError::at(dir);
    let mut files = Vec::new();
    for e in std::fs::read_dir(dir).map_err(io)? {
        let p = e.map_err(io)?.path();
        if p.extension().is_some_and(|x| x == "json")
            && p.file_name().is_some_and(|n| n != SKELETON)
        {
            files.push(p);
        }
    }
    files.sort();
    Ok(files)
}

/// Read and check one keypoint file: a non-empty list of `[x, y, v]` rows of finite
/// numbers. Errors name the file and the row.
pub fn read_keypoints(path: &Path) -> Result<Vec<Keypoint>> {
    let value = super::read_json(path, None)?;
    let file_err = |msg: String| Error::File { path: path.into(), msg };
    let rows = value.as_array().ok_or_else(|| {
        file_err("expected a list of [x, y, visible] rows, got a non-list value".into())
    })?;
    if rows.is_empty() {
        return Err(file_err("the file has no keypoints".into()));
    }
    rows.iter()
        .enumerate()
        .map(|(i, row)| {
            let bad = || file_err(format!("row {i}: expected [x, y, visible] numbers, got {row}"));
            let r = row.as_array().filter(|r| r.len() == 3).ok_or_else(bad)?;
            let v: Vec<f64> = r.iter().filter_map(Value::as_f64).collect();
            if v.len() != 3 || v.iter().any(|x| !x.is_finite()) {
                return Err(bad());
            }
            Ok(Keypoint { x: v[0], y: v[1], visible: v[2] == 1.0 })
        })
        .collect()
}

/// The JSON rows of `points` (`[x, y, 1]` visible, `[0, 0, 0]` invisible).
fn keypoints_json(points: &[Keypoint]) -> Value {
    Value::Array(
        points
            .iter()
            .map(|k| if k.visible { json!([k.x, k.y, 1.0]) } else { json!([0.0, 0.0, 0.0]) })
            .collect(),
    )
}

/// Ground-truth keypoints of a scene, by keyframe (sorted by frame).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneKeypoints {
    /// DyCheck frame name of each keyframe's file, `[K]`.
    pub names: Vec<String>,
    /// Our training frame of each keyframe, `[K]`, increasing.
    pub frames: Vec<usize>,
    /// Scene pixel coordinates (centres at +0.5) per keyframe, `[K][J, 2]`.
    pub pixels: Vec<Vec<[f32; 2]>>,
    /// Visibility per keyframe, `[K][J]`.
    pub visible: Vec<Vec<bool>>,
}

/// The keypoints that `scene.json` of `scene_dir` records, converted to scene pixels at
/// its `factor`; `Ok(None)` when it records none.
pub fn read_scene_keypoints(scene_dir: &Path) -> Result<Option<SceneKeypoints>> {
    let path = scene_dir.join("scene.json");
    if !path.is_file() {
        return Ok(None);
    }
    let value = super::read_json(&path, None)?;
    let o = Obj::new(&path, &value)?;
    let Some(kp) = o.opt("keypoints") else { return Ok(None) };
    let factor = o.f64("factor")?;
    if !(factor >= 1.0 && factor.fract() == 0.0 && factor <= u32::MAX as f64) {
        return Err(o.err("factor", format!("expected a positive integer, got {factor}")));
    }
    let kp = Obj::new(&path, kp).map_err(|_| o.err("keypoints", "expected an object"))?;
    let dir = kp
        .opt("dir")
        .and_then(Value::as_str)
        .filter(|d| !d.is_empty() && !Path::new(d).is_absolute() && !d.contains(".."))
        .ok_or_else(|| o.err("keypoints.dir", "expected a relative directory name"))?;
    let frames = kp
        .opt("frames")
        .and_then(Value::as_object)
        .ok_or_else(|| o.err("keypoints.frames", "expected an object {frame_name: frame}"))?;
    let mut by_frame: BTreeMap<u64, &str> = BTreeMap::new();
    for (name, f) in frames {
        let key = format!("keypoints.frames.{name}");
        let f =
            f.as_u64().ok_or_else(|| o.err(&key, format!("expected a frame index, got {f}")))?;
        if name.is_empty() || name.contains(['/', '\\']) || name.starts_with('.') {
            return Err(o.err(&key, "not a file name"));
        }
        if let Some(other) = by_frame.insert(f, name) {
            return Err(o.err(&key, format!("frame {f} is also the frame of '{other}'")));
        }
    }
    let mut out = SceneKeypoints {
        names: Vec::new(),
        frames: Vec::new(),
        pixels: Vec::new(),
        visible: Vec::new(),
    };
    for (frame, name) in by_frame {
        let file = scene_dir.join(dir).join(format!("{name}.json"));
        let points = read_keypoints(&file)?;
        if let Some(first) = out.pixels.first()
            && first.len() != points.len()
        {
            return Err(Error::File {
                path: file,
                msg: format!(
                    "has {} keypoints but {}.json has {}",
                    points.len(),
                    out.names[0],
                    first.len()
                ),
            });
        }
        out.names.push(name.to_string());
        out.frames.push(frame as usize);
        out.pixels.push(
            points
                .iter()
                .map(|k| to_scene_pixel(k.x, k.y, factor as u32).map(|c| c as f32))
                .collect(),
        );
        out.visible.push(points.iter().map(|k| k.visible).collect());
    }
    Ok(Some(out))
}

/// Write DyCheck keypoints for a synthetic scene at 2x (the layout's factor) from its
/// `tracks_2d.parquet`: on the keyframes `keyframes(T, min(10, T))` of the T training
/// images named `train_names` (`[T]`, by frame), the [`SYNTHETIC_KEYPOINTS`] tracks visible
/// in the most keyframes (ties: lower track index; kept in track order), each as the 2x
/// index of the pixel that contains it, with its visibility; plus a `skeleton.json` without
/// bones. Returns the number of keypoints J.
pub(super) fn write_synthetic(
    tracks_2d: &Path,
    out: &Path,
    train_names: &[String],
) -> Result<usize> {
    let reader = Tracks2dReader::open(tracks_2d)?;
    let t = train_names.len();
    if reader.num_frames() != t {
        return Err(Error::Scene(format!(
            "{} has {} frames, the scene has {t} training frames",
            tracks_2d.display(),
            reader.num_frames()
        )));
    }
    let keys =
        crate::metrics::tracking::keyframes(t, crate::metrics::tracking::NUM_KEYFRAMES.min(t));
    let frames =
        keys.iter().map(|&k| reader.frame(k)).collect::<crate::tables::Result<Vec<_>>>()?;
    let m = reader.num_tracks();
    let seen = |i: usize| frames.iter().filter(|f| f.visible[i]).count();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(seen(i)), i));
    order.truncate(SYNTHETIC_KEYPOINTS.min(m));
    order.sort_unstable();
    let dir = out.join(KEYPOINT_DIR);
    for (&k, f) in keys.iter().zip(&frames) {
        let points: Vec<Keypoint> = order
            .iter()
            .map(|&i| {
                let [x, y] =
                    to_keypoint_index(f.xy[i][0] as f64, f.xy[i][1] as f64, KEYPOINT_FACTOR);
                Keypoint { x, y, visible: f.visible[i] }
            })
            .collect();
        super::write_json(&dir.join(format!("{}.json", train_names[k])), &keypoints_json(&points))?;
    }
    let parents = vec![Value::Null; order.len()];
    super::write_json(&dir.join(SKELETON), &json!({"name": "unconnected", "parents": parents}))?;
    Ok(order.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_conversion_by_hand() {
        // 2x index 10 is the 2x pixel [10, 11), centre 10.5; at 1x that is 21.0, at 4x 5.25.
        assert_eq!(to_scene_pixel(10.0, 0.0, 2), [10.5, 0.5]);
        assert_eq!(to_scene_pixel(10.0, 0.0, 1), [21.0, 1.0]);
        assert_eq!(to_scene_pixel(10.0, 3.0, 4), [5.25, 1.75]);
        // The containing 2x pixel of a scene point, and back to its centre.
        assert_eq!(to_keypoint_index(10.99, 0.0, 2), [10.0, 0.0]);
        assert_eq!(to_keypoint_index(11.0, 7.5, 2), [11.0, 7.0]);
        assert_eq!(to_keypoint_index(21.9, 1.0, 1), [10.0, 0.0]);
        assert_eq!(to_keypoint_index(5.3, 1.7, 4), [10.0, 3.0]);
        for f in [1, 2, 4, 8] {
            let [u, v] = to_scene_pixel(37.0, 12.0, f);
            assert_eq!(to_keypoint_index(u, v, f), [37.0, 12.0], "factor {f}");
        }
    }

    #[test]
    fn keypoint_files_parse_and_bad_rows_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("0_00000.json");
        std::fs::write(&p, "[[10, 20.0, 1], [0.0, 0.0, 0.0], [3, 4, 0.5]]").unwrap();
        let k = read_keypoints(&p).unwrap();
        assert_eq!(k[0], Keypoint { x: 10.0, y: 20.0, visible: true });
        assert!(!k[1].visible && !k[2].visible);
        let err = |text: &str| {
            std::fs::write(&p, text).unwrap();
            read_keypoints(&p).unwrap_err().to_string()
        };
        let d = p.display();
        assert_eq!(
            err("[[1, 2, 1], [1, 2]]"),
            format!("{d}: row 1: expected [x, y, visible] numbers, got [1,2]")
        );
        assert_eq!(
            err(r#"[[1, 2, 1], [1, "a", 1]]"#),
            format!(r#"{d}: row 1: expected [x, y, visible] numbers, got [1,"a",1]"#)
        );
        assert_eq!(err("[]"), format!("{d}: the file has no keypoints"));
        assert_eq!(
            err(r#"{"a": 1}"#),
            format!("{d}: expected a list of [x, y, visible] rows, got a non-list value")
        );
    }

    #[test]
    fn scene_keypoints_follow_the_recorded_frames() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::create_dir_all(d.join(KEYPOINT_DIR)).unwrap();
        std::fs::write(d.join(KEYPOINT_DIR).join("0_00007.json"), "[[1, 2, 1], [5, 6, 0]]")
            .unwrap();
        std::fs::write(d.join(KEYPOINT_DIR).join("0_00003.json"), "[[3, 4, 1], [0, 0, 0]]")
            .unwrap();
        let meta = |factor: u32, frames: Value| {
            let v = json!({"factor": factor, "keypoints": {"dir": KEYPOINT_DIR, "frames": frames}});
            std::fs::write(d.join("scene.json"), v.to_string()).unwrap();
        };
        meta(4, json!({"0_00007": 2, "0_00003": 1}));
        let k = read_scene_keypoints(d).unwrap().unwrap();
        assert_eq!(k.names, ["0_00003", "0_00007"]);
        assert_eq!(k.frames, [1, 2]);
        assert_eq!(k.pixels[0][0], [1.75, 2.25]);
        assert_eq!(k.pixels[1][0], [0.75, 1.25]);
        assert_eq!(k.visible, [[true, false], [true, false]]);

        let scene_json = d.join("scene.json");
        meta(2, json!({"0_00007": 2, "0_00003": 2}));
        assert_eq!(
            read_scene_keypoints(d).unwrap_err().to_string(),
            format!(
                "{}: key 'keypoints.frames.0_00007': frame 2 is also the frame of '0_00003'",
                scene_json.display()
            )
        );
        std::fs::write(d.join(KEYPOINT_DIR).join("0_00003.json"), "[[3, 4, 1]]").unwrap();
        meta(2, json!({"0_00007": 2, "0_00003": 1}));
        assert_eq!(
            read_scene_keypoints(d).unwrap_err().to_string(),
            format!(
                "{}: has 2 keypoints but 0_00003.json has 1",
                d.join(KEYPOINT_DIR).join("0_00007.json").display()
            )
        );
        std::fs::write(&scene_json, r#"{"factor": 2}"#).unwrap();
        assert_eq!(read_scene_keypoints(d).unwrap(), None);
    }
}
