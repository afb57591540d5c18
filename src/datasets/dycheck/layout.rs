//! Write a scene in the DyCheck iPhone folder layout, so DyCheck-format tools (DyCheck, SoM,
//! MoSca loaders) can read scenes rendered along a DyCheck camera path.
//!
//! Resolution: the scene's images are DyCheck's **2x** (the benchmark factor that
//! `extra.json` names), written unchanged to `rgb/2x`, `depth/2x` and `covisible/2x/val`.
//! The camera files describe the 1x domain (focal length, principal point and image size
//! times 2), and `rgb/1x`, `depth/1x` are 2x nearest-neighbour upsamples (pixel
//! replication: they carry no extra detail, and box-downsampling them gives the 2x files
//! back). So `import dycheck --factor 2` of the written layout returns the scene's cameras
//! (to rounding of `−O·position`) and its exact images, depth and binary masks.
//!
//! Files: `camera/<cam>_<t:05d>.json` (t = our frame = DyCheck time id),
//! `rgb/{1x,2x}/<name>.png` (colour composited over white, alpha kept: see [`over_white`]),
//! `depth/{1x,2x}/<name>.npy` `(H, W, 1)` (training images),
//! `covisible/2x/val/<name>.png` (evaluation images, first channel of their mask),
//! `splits/{train,val}.json`, `dataset.json`, `metadata.json`, `scene.json`, `extra.json`.
//! Camera names must be DyCheck camera ids (non-negative integers); the training images
//! must be one camera with frames 0..T-1, each with depth; evaluation images need a mask.
//! Training masks and evaluation depth are not written (DyCheck has neither), nor is
//! `points.npy`. When the scene has ground-truth `tracks_2d.parquet` (a `synth` scene),
//! `keypoint/2x/train/` gets PCK-T keypoints picked from those tracks on DyCheck's 10
//! keyframes, with a `skeleton.json` (see `write_synthetic` in the `keypoints` module).
//!
//! `scene.json`: `center` = middle of the axis-aligned box around every valid training
//! depth pixel unprojected (pinhole, distortion ignored) and every camera centre; `scale` =
//! 1 / its longest side; `near`/`far` = min/max valid depth × scale. `extra.json`:
//! `factor` 2; `fps` from the scene's own `scene.json` (30 when absent); `bbox` (that box)
//! and `lookat` (least-squares closest point to all optical axes, like DyCheck's
//! `tringulate_rays`), both in the normalised frame `(x − center)·scale` as DyCheck stores
//! them; `up` = mean of the cameras' up axes (−row 1 of O), normalised.

use std::collections::HashSet;
use std::path::Path;

use glam::{DMat3, DVec3};
use rayon::prelude::*;
use serde_json::json;

use super::camera_json::DycheckCamera;
use super::keypoints;
use super::sequence::SplitFile;
use super::{Error, Result};
use crate::context::Context;
use crate::formats::{self, png::Image};
use crate::scene::{Camera, Scene, Split};

/// The scene's ground-truth 2D tracks (written by `synth`), the source of the keypoints.
const TRACKS_2D: &str = "tracks_2d.parquet";

/// DyCheck's factor of the scene's images.
const FACTOR: u32 = 2;

/// Frames per second recorded when the scene's `scene.json` names none (the iPhone rate).
const DEFAULT_FPS: f64 = 30.0;

/// One image to write: its camera, DyCheck name and camera id.
struct Job<'a> {
    cam: &'a Camera,
    name: String,
    camera_id: u32,
}

/// Box of world points and depth range seen by one training image.
#[derive(Clone, Copy)]
struct Extent {
    lo: DVec3,
    hi: DVec3,
    near: f64,
    far: f64,
}

impl Extent {
    const EMPTY: Extent = Extent {
        lo: DVec3::splat(f64::INFINITY),
        hi: DVec3::splat(f64::NEG_INFINITY),
        near: f64::INFINITY,
        far: f64::NEG_INFINITY,
    };

    fn merge(self, o: Extent) -> Extent {
        Extent {
            lo: self.lo.min(o.lo),
            hi: self.hi.max(o.hi),
            near: self.near.min(o.near),
            far: self.far.max(o.far),
        }
    }
}

/// Write `scene` (rendered along a DyCheck camera path; eval masks = covisibility, train
/// images with depth) in the DyCheck iPhone folder layout under `out`. See the module docs.
pub fn write_layout(scene: &Scene, out: &Path, ctx: &Context) -> Result<()> {
    let _span = tracing::info_span!("dycheck_layout").entered();
    let jobs = plan(scene)?;
    let train_len = scene.train_by_frame().len();
    let bar = ctx.progress(jobs.len() as u64, "dycheck layout");
    let results: Vec<Result<Option<Extent>>> = jobs
        .par_iter()
        .map(|j| {
            let r = write_image(scene, out, j);
            bar.inc(1);
            r
        })
        .collect();
    bar.finish_and_clear();
    let mut extent = Extent::EMPTY;
    for r in results {
        if let Some(e) = r? {
            extent = extent.merge(e);
        }
    }
    if !extent.near.is_finite() {
        return Err(Error::Scene(
            "no valid depth in the training images: scene.json needs near/far".into(),
        ));
    }
    for c in &scene.cameras {
        let p = c.center();
        extent.lo = extent.lo.min(p);
        extent.hi = extent.hi.max(p);
    }
    write_metadata(scene, out, &jobs, extent)?;
    let tracks = scene.dir.join(TRACKS_2D);
    if tracks.is_file() {
        let names: Vec<String> = jobs[..train_len].iter().map(|j| j.name.clone()).collect();
        keypoints::write_synthetic(&tracks, out, &names)?;
    }
    Ok(())
}

/// Check the scene and list its images: training by frame, then evaluation in table order.
fn plan(scene: &Scene) -> Result<Vec<Job<'_>>> {
    let train = scene.train_by_frame();
    if train.is_empty() {
        return Err(Error::Scene("the scene has no training images".into()));
    }
    let camera_id = |c: &Camera| {
        c.camera.parse::<u32>().map_err(|_| {
            Error::Scene(format!(
                "camera name '{}' is not a DyCheck camera id (a non-negative integer)",
                c.camera
            ))
        })
    };
    let mut jobs = Vec::with_capacity(scene.cameras.len());
    let mut seen = HashSet::new();
    for (t, c) in train.iter().enumerate() {
        if c.camera != train[0].camera {
            return Err(Error::Scene(format!(
                "training images come from cameras '{}' and '{}'; DyCheck's training split is one camera",
                train[0].camera, c.camera
            )));
        }
        if c.frame as usize != t {
            return Err(Error::Scene(format!(
                "training frames must be 0..T-1; frame {} is at position {t}",
                c.frame
            )));
        }
        if c.depth_path.is_none() {
            return Err(Error::Scene(format!(
                "training camera '{}' frame {} has no depth",
                c.camera, c.frame
            )));
        }
    }
    for c in train.iter().copied().chain(scene.eval()) {
        let id = camera_id(c)?;
        if c.split == Split::Eval {
            if c.frame as usize >= train.len() {
                return Err(Error::Scene(format!(
                    "evaluation camera '{}' frame {} is past the last training frame {}",
                    c.camera,
                    c.frame,
                    train.len() - 1
                )));
            }
            if c.mask_path.is_none() {
                return Err(Error::Scene(format!(
                    "evaluation camera '{}' frame {} has no covisibility mask",
                    c.camera, c.frame
                )));
            }
        }
        let name = format!("{id}_{:05}", c.frame);
        if !seen.insert(name.clone()) {
            return Err(Error::Scene(format!(
                "camera '{}' frame {} appears twice",
                c.camera, c.frame
            )));
        }
        jobs.push(Job { cam: c, name, camera_id: id });
    }
    Ok(jobs)
}

/// Write one image's camera, rgb, depth or covisibility files; training images return the
/// extent of their depth.
/// DyCheck's colour is opaque (its alpha marks LiDAR depth, which readers ignore), so a
/// synthetic image's straight-alpha colour is composited over white, the renderer's
/// default background; its alpha (the coverage) is kept.
pub fn over_white(mut img: Image) -> Image {
    if img.channels == 4 {
        for px in img.data.chunks_exact_mut(4) {
            let a = px[3];
            for c in &mut px[..3] {
                *c = *c * a + (1.0 - a);
            }
        }
    }
    img
}

fn write_image(scene: &Scene, out: &Path, j: &Job) -> Result<Option<Extent>> {
    let cam = j.cam;
    let (w, h) = cam.pinhole.size();
    let f = FACTOR as usize;
    super::write_json(
        &out.join("camera").join(format!("{}.json", j.name)),
        &DycheckCamera::from_camera(cam, FACTOR)?.to_json(),
    )?;
    let src = scene.resolve(&cam.image_path);
    let img = formats::png::read_png(&src)?;
    if (img.width, img.height) != (w, h) {
        return Err(Error::File {
            path: src,
            msg: format!("image is {}x{} but its camera is {w}x{h}", img.width, img.height),
        });
    }
    let img = over_white(img);
    let png = format!("{}.png", j.name);
    formats::png::write_png(&out.join("rgb/2x").join(&png), &img)?;
    let up = super::resize_nearest(&img.data, w, h, img.channels, w * f, h * f);
    formats::png::write_png(
        &out.join("rgb/1x").join(&png),
        &Image { width: w * f, height: h * f, channels: img.channels, data: up },
    )?;
    match cam.split {
        Split::Train => {
            let Some(rel) = &cam.depth_path else { return Ok(None) };
            let src = scene.resolve(rel);
            let (shape, depth) = formats::npy::read_npy_f32(&src)?;
            if shape != [h, w] && shape != [h, w, 1] {
                return Err(Error::File {
                    path: src,
                    msg: format!(
                        "depth shape {shape:?} does not match the camera's image [{h}, {w}]"
                    ),
                });
            }
            let npy = format!("{}.npy", j.name);
            formats::npy::write_npy_f32(&out.join("depth/2x").join(&npy), &[h, w, 1], &depth)?;
            let up = super::resize_nearest(&depth, w, h, 1, w * f, h * f);
            formats::npy::write_npy_f32(&out.join("depth/1x").join(&npy), &[h * f, w * f, 1], &up)?;
            Ok(Some(depth_extent(cam, &depth)))
        }
        Split::Eval => {
            let Some(rel) = &cam.mask_path else { return Ok(None) };
            let src = scene.resolve(rel);
            let m = formats::png::read_png(&src)?;
            if (m.width, m.height) != (w, h) {
                return Err(Error::File {
                    path: src,
                    msg: format!("mask is {}x{} but its camera is {w}x{h}", m.width, m.height),
                });
            }
            formats::png::write_png(&out.join("covisible/2x/val").join(&png), &m.channel(0))?;
            Ok(None)
        }
    }
}

/// World box and depth range of the valid pixels of `depth` `[H, W]` (pinhole unprojection
/// of pixel centres at +0.5).
fn depth_extent(cam: &Camera, depth: &[f32]) -> Extent {
    let c2w = cam.w2c_mat().inverse();
    let w = cam.pinhole.width as usize;
    let mut e = Extent::EMPTY;
    for (i, &z) in depth.iter().enumerate() {
        if !(z > 0.0 && z.is_finite()) {
            continue;
        }
        let z = z as f64;
        let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let pc = DVec3::new(
            (x - cam.pinhole.cx) / cam.pinhole.fx * z,
            (y - cam.pinhole.cy) / cam.pinhole.fy * z,
            z,
        );
        let p = c2w.transform_point3(pc);
        e = e.merge(Extent { lo: p, hi: p, near: z, far: z });
    }
    e
}

/// Least-squares closest point to the optical axes of `cams`; `fallback` when degenerate.
fn triangulate_axes(cams: &[&Camera], fallback: DVec3) -> DVec3 {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for c in cams {
        let d = c.rotation().row(2).normalize();
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * c.center();
    }
    if a.determinant().abs() < 1e-12 { fallback } else { a.inverse() * b }
}

/// `splits/*.json`, `dataset.json`, `metadata.json`, `scene.json`, `extra.json`.
fn write_metadata(scene: &Scene, out: &Path, jobs: &[Job], e: Extent) -> Result<()> {
    let mut train = SplitFile::default();
    let mut val = SplitFile::default();
    let mut metadata = serde_json::Map::new();
    for j in jobs {
        let s = if j.cam.split == Split::Train { &mut train } else { &mut val };
        s.frame_names.push(j.name.clone());
        s.time_ids.push(j.cam.frame);
        s.camera_ids.push(j.camera_id);
        metadata.insert(
            j.name.clone(),
            json!({"warp_id": j.cam.frame, "appearance_id": j.cam.frame, "camera_id": j.camera_id}),
        );
    }
    super::write_json(&out.join("splits/train.json"), &train.to_json())?;
    super::write_json(&out.join("splits/val.json"), &val.to_json())?;
    let ids: Vec<&String> = train.frame_names.iter().chain(&val.frame_names).collect();
    super::write_json(
        &out.join("dataset.json"),
        &json!({
            "count": ids.len(),
            "num_exemplars": train.frame_names.len(),
            "ids": ids,
            "train_ids": train.frame_names,
            "val_ids": val.frame_names,
        }),
    )?;
    super::write_json(&out.join("metadata.json"), &serde_json::Value::Object(metadata))?;
    let center = (e.lo + e.hi) * 0.5;
    let side = (e.hi - e.lo).max_element();
    let scale = if side > 0.0 { 1.0 / side } else { 1.0 };
    super::write_json(
        &out.join("scene.json"),
        &json!({
            "center": center.to_array(),
            "scale": scale,
            "near": e.near * scale,
            "far": e.far * scale,
        }),
    )?;
    let cams: Vec<&Camera> = jobs.iter().map(|j| j.cam).collect();
    let lookat = triangulate_axes(&cams, center);
    let up = cams.iter().fold(DVec3::ZERO, |acc, c| acc - c.rotation().row(1)).normalize_or_zero();
    let norm = |p: DVec3| ((p - center) * scale).to_array();
    super::write_json(
        &out.join("extra.json"),
        &json!({
            "factor": FACTOR,
            "fps": scene_fps(scene),
            "bbox": [norm(e.lo), norm(e.hi)],
            "lookat": norm(lookat),
            "up": up.to_array(),
        }),
    )
}

/// The `fps` of the scene's own `scene.json`, else [`DEFAULT_FPS`].
fn scene_fps(scene: &Scene) -> f64 {
    std::fs::read(scene.dir.join("scene.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v.get("fps").and_then(|f| f.as_f64()))
        .filter(|f| *f > 0.0)
        .unwrap_or(DEFAULT_FPS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Pinhole;

    fn cam(camera: &str, frame: u32, split: Split) -> Camera {
        let pinhole = Pinhole::centred(50.0, 16, 12, Camera::w2c_from_mat(glam::DMat4::IDENTITY));
        Camera {
            depth_path: (split == Split::Train).then(|| format!("depth/{camera}/{frame:05}.npy")),
            mask_path: (split == Split::Eval).then(|| format!("mask/{camera}/{frame:05}.png")),
            ..Camera::new(frame, camera, split, pinhole)
        }
    }

    fn plan_err(cameras: Vec<Camera>) -> String {
        let scene = Scene { dir: "s".into(), cameras };
        plan(&scene).err().map(|e| e.to_string()).unwrap_or_default()
    }

    #[test]
    fn plan_names_images_and_rejects_what_dycheck_cannot_hold() {
        let ok =
            vec![cam("0", 1, Split::Train), cam("0", 0, Split::Train), cam("2", 1, Split::Eval)];
        let scene = Scene { dir: "s".into(), cameras: ok.clone() };
        let names: Vec<String> = plan(&scene).unwrap().into_iter().map(|j| j.name).collect();
        assert_eq!(names, ["0_00000", "0_00001", "2_00001"]);

        let mut named = ok.clone();
        named[2].camera = "cam03".into();
        assert_eq!(
            plan_err(named),
            "camera name 'cam03' is not a DyCheck camera id (a non-negative integer)"
        );
        let mut no_mask = ok.clone();
        no_mask[2].mask_path = None;
        assert_eq!(plan_err(no_mask), "evaluation camera '2' frame 1 has no covisibility mask");
        let mut no_depth = ok.clone();
        no_depth[0].depth_path = None;
        assert_eq!(plan_err(no_depth), "training camera '0' frame 1 has no depth");
        let mut late = ok.clone();
        late[2].frame = 2;
        assert_eq!(
            plan_err(late),
            "evaluation camera '2' frame 2 is past the last training frame 1"
        );
        let mut two = ok.clone();
        two[1].camera = "1".into();
        assert_eq!(
            plan_err(two),
            "training images come from cameras '1' and '0'; DyCheck's training split is one camera"
        );
        let mut twice = ok;
        twice.push(cam("2", 1, Split::Eval));
        assert_eq!(plan_err(twice), "camera '2' frame 1 appears twice");
    }
}
