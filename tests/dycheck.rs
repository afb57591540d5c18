//! `usplat4d import dycheck` end to end: the real paper-windmill camera files, a round trip
//! through `write_layout`, a bad-input corpus made by breaking one windmill file at a
//! time (exact error text pinned), and PCK-T: `synth --layout dycheck` along a hand-made
//! DyCheck camera arc → `import dycheck` → `evaluate --model` of the oracle and of a
//! shifted model. Tests needing shared/data skip with a note without it; the PCK-T test
//! needs none. Not validated here: agreement with DyCheck's own PCK-T code on real
//! keypoints (the shared paper-windmill files have none).

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::util::copy_dir;
use usplat4d::context::Context;
use usplat4d::datasets::dycheck::{DycheckCamera, over_white, read_camera_path, write_layout};
use usplat4d::formats::{self, png::Image};
use usplat4d::scene::{Camera, Scene, Split};

use crate::util::code_and_stderr as usplat4d;

/// The paper-windmill camera files, if shared/data is reachable.
fn windmill() -> Option<PathBuf> {
    let found = crate::util::shared_data("real/dycheck-paper-windmill-cameras")
        .filter(|p| p.join("splits/train.json").exists());
    if found.is_none() {
        eprintln!("SKIP: ../shared/data/real/dycheck-paper-windmill-cameras not found");
    }
    found
}

#[test]
fn windmill_camera_path_at_factor_2() {
    let Some(dir) = windmill() else { return };
    let cams = read_camera_path(&dir, 2).unwrap();
    let train: Vec<&Camera> = cams.iter().filter(|c| c.split == Split::Train).collect();
    let eval: Vec<&Camera> = cams.iter().filter(|c| c.split == Split::Eval).collect();
    assert_eq!((train.len(), eval.len()), (277, 419));
    assert_eq!(eval.iter().filter(|c| c.camera == "1").count(), 219);
    assert_eq!(eval.iter().filter(|c| c.camera == "2").count(), 200);
    for (t, c) in train.iter().enumerate() {
        assert_eq!((c.frame, c.camera.as_str()), (t as u32, "0"));
    }
    let c2 = cams.iter().find(|c| c.camera == "2" && c.frame == 77).unwrap();
    assert_eq!(c2.image_path, "rgb/2/00077.png");
    assert_eq!(c2.mask_path.as_deref(), Some("mask/2/00077.png"));
    assert_eq!(train[3].depth_path.as_deref(), Some("depth/0/00003.npy"));
    for c in &cams {
        assert_eq!((c.pinhole.width, c.pinhole.height), (360, 480));
        assert_eq!(c.distortion, None);
        let r = c.rotation();
        let dev = (r * r.transpose() - glam::DMat3::IDENTITY).to_cols_array();
        assert!(dev.iter().all(|x| x.abs() < 1e-6), "{dev:?}");
        assert!((r.determinant() - 1.0).abs() < 1e-6);
    }
    let raw = DycheckCamera::read(&dir.join("camera/1_00000.json"), None).unwrap();
    let c1 = cams.iter().find(|c| c.camera == "1" && c.frame == 0).unwrap();
    assert_eq!((c1.pinhole.fx, c1.pinhole.fy), (raw.focal_length / 2.0, raw.focal_length / 2.0));
    assert_eq!(
        (c1.pinhole.cx, c1.pinhole.cy),
        (raw.principal_point[0] / 2.0, raw.principal_point[1] / 2.0)
    );
    assert!((c1.center() - glam::DVec3::from_array(raw.position)).length() < 1e-9);
}

#[test]
fn factor_too_large_for_the_image_is_an_error() {
    let Some(dir) = windmill() else { return };
    let err = read_camera_path(&dir, 2000).unwrap_err();
    let want = format!(
        "{}: key 'image_size': [720, 960] at factor 2000 rounds to an empty image",
        dir.join("camera/0_00000.json").display()
    );
    assert_eq!(err.to_string(), want);
}

fn import(data: &Path, out: &Path, extra: &[&str]) -> (i32, String) {
    let mut args =
        vec!["import", "dycheck", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    usplat4d(&args)
}

fn read_json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_vec_pretty(v).unwrap()).unwrap();
}

#[test]
fn windmill_cameras_only_import() {
    let Some(data) = windmill() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("scene");
    let (code, err) = import(&data, &out, &["--cameras-only", "--quiet"]);
    assert_eq!((code, err.as_str()), (0, ""));
    let scene = Scene::load(&out).unwrap();
    assert_eq!((scene.train().count(), scene.eval().count()), (277, 419));
    let raw = read_json(&data.join("camera/0_00010.json"));
    let c = scene.train_by_frame()[10];
    assert_eq!((c.pinhole.width, c.pinhole.height), (360, 480));
    assert_eq!(c.pinhole.fx, raw["focal_length"].as_f64().unwrap() / 2.0);
    assert_eq!(c.pinhole.cy, raw["principal_point"][1].as_f64().unwrap() / 2.0);
    let pos: Vec<f64> =
        raw["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert!((c.center() - glam::DVec3::new(pos[0], pos[1], pos[2])).length() < 1e-9);
    assert!(scene.cameras.iter().all(|c| c.depth_path.is_none() && c.mask_path.is_none()));
    let meta = read_json(&out.join("scene.json"));
    assert_eq!(meta["factor"], 2);
    assert_eq!(meta["world"], "source");
    assert_eq!(meta["fps"], 30.0);
    let (near, scale) = (
        meta["dycheck_scene"]["near"].as_f64().unwrap(),
        meta["dycheck_scene"]["scale"].as_f64().unwrap(),
    );
    assert_eq!(meta["near"].as_f64().unwrap(), near / scale);

    let out2 = tmp.path().join("scene-normalised");
    let (code, _) =
        import(&data, &out2, &["--cameras-only", "--quiet", "--world", "dycheck", "--factor", "4"]);
    assert_eq!(code, 0);
    let norm = Scene::load(&out2).unwrap();
    let c2 = norm.train_by_frame()[10];
    assert_eq!((c2.pinhole.width, c2.pinhole.height), (180, 240));
    let center: Vec<f64> = meta["dycheck_scene"]["center"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let want = (c.center() - glam::DVec3::new(center[0], center[1], center[2])) * scale;
    assert!((c2.center() - want).length() < 1e-9);
}

/// A tiny RGBA test pattern, different per (camera, frame).
fn pattern(w: usize, h: usize, seed: usize, channels: usize) -> Image {
    let data = (0..w * h * channels).map(|i| ((i * 7 + seed * 13) % 256) as f32 / 255.0).collect();
    Image { width: w, height: h, channels, data }
}

/// A scene built by hand along the windmill path at factor 8 (90x120): training frames
/// 0..3 of camera 0 (with depth) and camera 1 at the same times (with binary masks).
fn hand_made_scene(data: &Path, dir: &Path) -> Scene {
    let cams: Vec<Camera> = read_camera_path(data, 8)
        .unwrap()
        .into_iter()
        .filter(|c| c.frame < 4 && (c.camera == "0" || c.camera == "1"))
        .collect();
    assert_eq!(cams.len(), 8);
    for (k, c) in cams.iter().enumerate() {
        let (w, h) = c.pinhole.size();
        formats::png::write_png(&dir.join(&c.image_path), &pattern(w, h, k, 4)).unwrap();
        if let Some(d) = &c.depth_path {
            let depth: Vec<f32> = (0..w * h)
                .map(|i| if i % 11 == 0 { 0.0 } else { 0.5 + (i % 97) as f32 * 0.01 })
                .collect();
            formats::npy::write_npy_f32(&dir.join(d), &[h, w], &depth).unwrap();
        }
        if let Some(m) = &c.mask_path {
            let mask: Vec<f32> = (0..w * h).map(|i| ((i / 5 + k) % 2) as f32).collect();
            formats::png::write_png(
                &dir.join(m),
                &Image { width: w, height: h, channels: 1, data: mask },
            )
            .unwrap();
        }
    }
    std::fs::write(dir.join("scene.json"), r#"{"fps": 24.0}"#).unwrap();
    Scene { dir: dir.to_path_buf(), cameras: cams }
}

#[test]
fn layout_round_trip() {
    let Some(data) = windmill() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let scene = hand_made_scene(&data, &tmp.path().join("scene"));
    let layout = tmp.path().join("layout");
    write_layout(&scene, &layout, &Context::quiet()).unwrap();

    let cam_json = read_json(&layout.join("camera/1_00002.json"));
    assert_eq!(cam_json["image_size"], serde_json::json!([180, 240]));
    assert_eq!(formats::png::read_png(&layout.join("rgb/1x/0_00003.png")).unwrap().width, 180);
    let (shape, _) = formats::npy::read_npy_f32(&layout.join("depth/2x/0_00001.npy")).unwrap();
    assert_eq!(shape, vec![120, 90, 1]);
    let val = read_json(&layout.join("splits/val.json"));
    assert_eq!(val["frame_names"], serde_json::json!(["1_00000", "1_00001", "1_00002", "1_00003"]));
    assert_eq!(read_json(&layout.join("extra.json"))["fps"], 24.0);
    assert_eq!(read_json(&layout.join("dataset.json"))["num_exemplars"], 4);
    let info = read_json(&layout.join("scene.json"));
    assert!(
        info["near"].as_f64().unwrap() > 0.0
            && info["far"].as_f64().unwrap() > info["near"].as_f64().unwrap()
    );

    let back_dir = tmp.path().join("back");
    let (code, err) = import(&layout, &back_dir, &["--quiet"]);
    assert_eq!((code, err.as_str()), (0, ""));
    let back = Scene::load(&back_dir).unwrap();
    assert_eq!(back.cameras.len(), scene.cameras.len());
    for (a, b) in scene.cameras.iter().zip(&back.cameras) {
        assert_eq!((&a.camera, a.frame, a.split), (&b.camera, b.frame, b.split));
        assert_eq!(
            (
                a.pinhole.fx,
                a.pinhole.fy,
                a.pinhole.cx,
                a.pinhole.cy,
                a.pinhole.width,
                a.pinhole.height
            ),
            (
                b.pinhole.fx,
                b.pinhole.fy,
                b.pinhole.cx,
                b.pinhole.cy,
                b.pinhole.width,
                b.pinhole.height
            )
        );
        assert!(
            a.pinhole.w2c.iter().zip(&b.pinhole.w2c).all(|(x, y)| (x - y).abs() < 1e-12),
            "{:?} vs {:?}",
            a.pinhole.w2c,
            b.pinhole.w2c
        );
        assert_eq!(
            (&a.image_path, &a.depth_path, &a.mask_path),
            (&b.image_path, &b.depth_path, &b.mask_path)
        );
        let img =
            |s: &Scene, c: &Camera| formats::png::read_png(&s.resolve(&c.image_path)).unwrap();
        // over white, then 8-bit quantised by the PNG
        let (want, got) = (over_white(img(&scene, a)), img(&back, b));
        assert_eq!((want.width, want.height, want.channels), (got.width, got.height, got.channels));
        assert!(want.data.iter().zip(&got.data).all(|(x, y)| (x - y).abs() <= 0.5 / 255.0 + 1e-6));
        if let Some(d) = &a.depth_path {
            assert_eq!(
                formats::npy::read_npy_f32(&scene.resolve(d)).unwrap(),
                formats::npy::read_npy_f32(&back.resolve(d)).unwrap()
            );
        }
        if let Some(m) = &a.mask_path {
            assert_eq!(
                formats::png::read_png(&scene.resolve(m)).unwrap(),
                formats::png::read_png(&back.resolve(m)).unwrap()
            );
        }
    }

    let kp = layout.join("keypoint/2x/train");
    std::fs::create_dir_all(&kp).unwrap();
    std::fs::write(kp.join("0_00002.json"), "[[10.0, 20.0, 1.0]]").unwrap();
    std::fs::write(kp.join("skeleton.json"), r#"{"parents": [null]}"#).unwrap();
    let norm_dir = tmp.path().join("normalised");
    let (code, _) = import(&layout, &norm_dir, &["--quiet", "--world", "dycheck"]);
    assert_eq!(code, 0);
    let meta = read_json(&norm_dir.join("scene.json"));
    assert_eq!(
        meta["keypoints"],
        serde_json::json!({"dir": "keypoint/2x/train", "frames": {"0_00002": 2}})
    );
    assert_eq!(
        std::fs::read(norm_dir.join("keypoint/2x/train/0_00002.json")).unwrap(),
        b"[[10.0, 20.0, 1.0]]"
    );
    assert!(norm_dir.join("keypoint/2x/train/skeleton.json").exists());
    let scale = info["scale"].as_f64().unwrap();
    assert_eq!(meta["dycheck_scene"]["scale"], scale);
    let rel = scene.cameras[0].depth_path.as_ref().unwrap();
    let (_, d0) = formats::npy::read_npy_f32(&scene.resolve(rel)).unwrap();
    let (_, d1) = formats::npy::read_npy_f32(&norm_dir.join(rel)).unwrap();
    assert!(d0.iter().zip(&d1).all(|(a, b)| *b == (*a as f64 * scale) as f32));

    let full_dir = tmp.path().join("full");
    let (code, _) = import(&layout, &full_dir, &["--quiet", "--factor", "1"]);
    assert_eq!(code, 0);
    let full = Scene::load(&full_dir).unwrap();
    let (a, b) = (&scene.cameras[5], &full.cameras[5]);
    assert_eq!(
        (b.pinhole.width, b.pinhole.height, b.pinhole.fx),
        (2 * a.pinhole.width, 2 * a.pinhole.height, 2.0 * a.pinhole.fx)
    );
    let m = formats::png::read_png(&full.resolve(b.mask_path.as_ref().unwrap())).unwrap();
    assert_eq!((m.width, m.height), (180, 240));
}

/// One broken copy of the windmill files: the file that is broken and named by the error
/// (`""`: none), how it is broken, and the exact stderr that follows the warnings of a full
/// import (`warned`): `error: <dir>/<file>: <error>`.
struct Case {
    name: &'static str,
    args: &'static [&'static str],
    file: &'static str,
    breaks: fn(&Path),
    warned: bool,
    error: &'static str,
}

impl Case {
    /// A `--cameras-only` import of a copy whose `file` is broken by `breaks`.
    fn cameras(
        name: &'static str,
        file: &'static str,
        breaks: fn(&Path),
        error: &'static str,
    ) -> Case {
        Case { name, args: &["--cameras-only"], file, breaks, warned: false, error }
    }

    /// A full import of a copy whose `file` is broken by `breaks` (or not at all).
    fn full(
        name: &'static str,
        file: &'static str,
        breaks: fn(&Path),
        error: &'static str,
    ) -> Case {
        Case { name, args: &[], file, breaks, warned: true, error }
    }

    /// The exact stderr of the import of copy `d`.
    fn stderr(&self, d: &Path) -> String {
        let warnings = if self.warned { no_depth_no_masks(d) } else { String::new() };
        match self.file {
            "" => format!("{warnings}error: {}\n", self.error),
            f => format!("{warnings}error: {}: {}\n", d.join(f).display(), self.error),
        }
    }
}

fn edit(path: &Path, f: impl FnOnce(&mut Value)) {
    let mut v = read_json(path);
    f(&mut v);
    write_json(path, &v);
}

fn remove(path: &Path) {
    std::fs::remove_file(path).unwrap()
}

fn cases() -> Vec<Case> {
    vec![
        Case::cameras(
            "missing camera file",
            "camera/0_00005.json",
            remove,
            "file not found (needed by splits/train.json entry 5)",
        ),
        Case::cameras("missing split", "splits/val.json", remove, "file not found"),
        Case::cameras(
            "malformed JSON",
            "camera/1_00003.json",
            |f| std::fs::write(f, "{\"focal_length\": 719.9,").unwrap(),
            "malformed JSON: EOF while parsing a value at line 1 column 23",
        ),
        Case::cameras(
            "missing key",
            "camera/0_00002.json",
            |f| {
                edit(f, |v| {
                    v.as_object_mut().unwrap().remove("focal_length");
                })
            },
            "key 'focal_length': missing",
        ),
        Case::cameras(
            "orientation with two rows",
            "camera/2_00100.json",
            |f| edit(f, |v| v["orientation"].as_array_mut().unwrap().truncate(2)),
            "key 'orientation': expected 3 rows of 3 numbers, got 2 rows",
        ),
        Case::cameras(
            "orientation row of two",
            "camera/0_00000.json",
            |f| edit(f, |v| v["orientation"][1].as_array_mut().unwrap().truncate(2)),
            "key 'orientation[1]': expected 3 numbers, got 2",
        ),
        Case::cameras(
            "orientation not a rotation",
            "camera/0_00000.json",
            |f| edit(f, |v| v["orientation"][0][0] = 2.0.into()),
            "key 'orientation': not a rotation matrix \
             (max |O*O^T - I| = 3.000e0, det = 2.0000)",
        ),
        Case::cameras(
            "position not a list",
            "camera/0_00001.json",
            |f| edit(f, |v| v["position"] = "abc".into()),
            "key 'position': expected a list of 3 numbers, got \"abc\"",
        ),
        Case::cameras(
            "split lists of different lengths",
            "splits/train.json",
            |f| edit(f, |v| v["time_ids"].as_array_mut().unwrap().truncate(276)),
            "key 'time_ids': has 276 entries but 'frame_names' has 277",
        ),
        Case::cameras(
            "validation time without a training image",
            "splits/val.json",
            |f| edit(f, |v| v["time_ids"][0] = 999.into()),
            "key 'time_ids[0]': time id 999 has no training image",
        ),
        Case {
            name: "factor zero",
            args: &["--cameras-only", "--factor", "0"],
            file: "",
            breaks: |_| {},
            warned: false,
            error: "factor must be at least 1, got 0",
        },
        Case::full(
            "images missing without --cameras-only",
            "rgb/2x/0_00000.png",
            |_| {},
            "file not found (needed by '0_00000' of splits/train.json)",
        ),
        Case::full(
            "corrupt image",
            "rgb/2x/0_00000.png",
            |f| {
                std::fs::create_dir_all(f.parent().unwrap()).unwrap();
                std::fs::write(f, "garbage").unwrap();
            },
            "Format error decoding Png: Invalid PNG signature.",
        ),
        Case::full(
            "image of the wrong size",
            "rgb/2x/0_00000.png",
            |f| formats::png::write_png(f, &pattern(4, 3, 0, 4)).unwrap(),
            "image is 4x3 but its camera at factor 2 is 360x480 (W x H)",
        ),
    ]
}

/// The warnings of a full import of a sequence without depth and covisibility folders.
fn no_depth_no_masks(d: &Path) -> String {
    format!(
        "warning: {} not found: training images get no depth\n\
         warning: {} not found: evaluation images get no covisibility mask\n",
        d.join("depth/2x").display(),
        d.join("covisible/2x/val").display()
    )
}

#[test]
fn bad_inputs_give_exact_errors() {
    let Some(data) = windmill() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    for (i, case) in cases().into_iter().enumerate() {
        let dir = tmp.path().join(format!("seq{i}"));
        copy_dir(&data, &dir);
        (case.breaks)(&dir.join(case.file));
        let (code, err) = import(&dir, &tmp.path().join(format!("out{i}")), case.args);
        let want = case.stderr(&dir);
        if code != 2 || err != want {
            failures.push(format!("{}: exit {code}\n got: {err}\nwant: {want}", case.name));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A DyCheck camera file looking from `position` at the origin (1x size 180x240, f = 200).
fn look_at_camera(position: [f64; 3]) -> Value {
    let p = glam::DVec3::from_array(position);
    let z = (-p).normalize();
    let x = z.cross(glam::DVec3::Y).normalize();
    let y = z.cross(x);
    serde_json::json!({
        "orientation": [x.to_array(), y.to_array(), z.to_array()],
        "position": position,
        "focal_length": 200.0,
        "principal_point": [90.0, 120.0],
        "skew": 0.0,
        "pixel_aspect_ratio": 1.0,
        "radial_distortion": [0.0, 0.0, 0.0],
        "tangential_distortion": [0.0, 0.0],
        "image_size": [180, 240],
    })
}

/// A DyCheck camera path without images: camera 0 on an arc around the origin for frames
/// 0..t (training), camera 1 fixed at frames 0 and t/2 (validation).
fn arc_trajectory(dir: &Path, t: u32) {
    std::fs::create_dir_all(dir.join("camera")).unwrap();
    std::fs::create_dir_all(dir.join("splits")).unwrap();
    let mut train = Vec::new();
    for f in 0..t {
        let a = (-30.0 + 5.0 * f as f64).to_radians();
        let name = format!("0_{f:05}");
        write_json(
            &dir.join(format!("camera/{name}.json")),
            &look_at_camera([2.0 * a.sin(), -0.6, -2.0 * a.cos()]),
        );
        train.push(name);
    }
    let val_times = [0, t / 2];
    for f in val_times {
        write_json(&dir.join(format!("camera/1_{f:05}.json")), &look_at_camera([1.6, -0.6, -1.2]));
    }
    write_json(
        &dir.join("splits/train.json"),
        &serde_json::json!({"frame_names": train, "time_ids": (0..t).collect::<Vec<_>>(), "camera_ids": vec![0; t as usize]}),
    );
    write_json(
        &dir.join("splits/val.json"),
        &serde_json::json!({
            "frame_names": val_times.map(|f| format!("1_{f:05}")),
            "time_ids": val_times,
            "camera_ids": [1, 1],
        }),
    );
}

/// `evaluate --model` scores of `model` on `scene` (renders of its eval views in `renders`):
/// the `pck_t` entry of summary.json, and stdout.
fn pck_t(scene: &Path, renders: &Path, model: &Path, out: &Path) -> (Value, String) {
    let o = crate::util::bin()
        .args(["evaluate", "--lpips", "off", "--renders", s(renders), "--scene", s(scene)])
        .args(["--model", s(model), "--out", s(out)])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (
        read_json(&out.join("summary.json"))["pck_t"].clone(),
        String::from_utf8_lossy(&o.stdout).into(),
    )
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// See: issue 6. synth → DyCheck layout with keypoints → import → PCK-T near 1 for the
/// oracle, clearly lower for the oracle shifted sideways; malformed keypoints name the file
/// and row, and keypoint files that are not training images are rejected at import.
#[test]
fn pck_t_of_synthetic_dycheck_keypoints() {
    use usplat4d::model::{FrameState, Model};
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    arc_trajectory(&d.join("traj"), 12);
    let fox = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/data/Fox.glb");
    let synth = d.join("S");
    let traj = format!("dycheck:{}", d.join("traj").display());
    let (code, err) = usplat4d(&[
        "synth",
        "--gltf",
        s(&fox),
        "--out",
        s(&synth),
        "--trajectory",
        &traj,
        "--layout",
        "dycheck",
        "--gaussians",
        "1500",
        "--tracks",
        "128",
        "--quiet",
    ]);
    assert_eq!((code, err.as_str()), (0, ""));

    // Keypoints on keyframes(12, 10), J = 16, DyCheck's 2x integer format.
    let kp = synth.join("dycheck/keypoint/2x/train");
    let mut names: Vec<String> = std::fs::read_dir(&kp)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let keyframes = [0, 1, 2, 3, 4, 6, 7, 8, 9, 10];
    let mut want: Vec<String> = keyframes.iter().map(|f| format!("0_{f:05}.json")).collect();
    want.push("skeleton.json".into());
    assert_eq!(names, want);
    let rows = read_json(&kp.join("0_00004.json"));
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 16);
    for r in rows {
        let v: Vec<f64> = r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        assert!(v.iter().all(|x| x.fract() == 0.0) && (v[2] == 0.0 || v[2] == 1.0), "{r}");
        assert!((0.0..90.0).contains(&v[0]) && (0.0..120.0).contains(&v[1]), "{r}");
    }
    assert_eq!(read_json(&kp.join("skeleton.json"))["parents"].as_array().unwrap().len(), 16);

    let scene = d.join("I");
    let (code, err) = import(&synth.join("dycheck"), &scene, &["--quiet"]);
    assert_eq!((code, err.as_str()), (0, ""));
    let frames = &read_json(&scene.join("scene.json"))["keypoints"]["frames"];
    assert_eq!(frames["0_00006"], 6);
    let renders = d.join("R");
    let oracle = synth.join("oracle");
    let render = crate::util::render_eval_args(&oracle, &scene, &renders);
    let (code, err) = usplat4d(&[&render[..], &["--quiet"]].concat());
    assert_eq!((code, err.as_str()), (0, ""));
    let (good, stdout) = pck_t(&scene, &renders, &oracle, &d.join("E"));
    assert!(
        stdout.contains("## PCK-T of oracle (16 keypoints, 10 keyframes, 90 pairs"),
        "{stdout}"
    );
    assert_eq!(good["keyframes"], serde_json::json!(keyframes));
    assert_eq!((good["pairs"].as_u64(), good["threshold_px"].as_f64()), (Some(90), Some(6.0)));
    let (score, points) = (good["pck_t"].as_f64().unwrap(), good["points"].as_u64().unwrap());
    // Not 1: the SoM read-out at keypoints near silhouettes mixes surfaces (the 3D tracking
    // of the same oracle has the same ceiling).
    assert!(score > 0.9 && points > 90 * 8, "oracle: {good}");

    // The oracle shifted by 0.1 world units along world x (about 8 px in these views).
    let m = Model::load(&oracle).unwrap();
    let frames = (0..m.num_frames()).map(|t| {
        m.frame(t).map(|f| FrameState {
            position: f.position.iter().map(|p| [p[0] + 0.1, p[1], p[2]]).collect(),
            ..f
        })
    });
    let shifted = d.join("shifted");
    Model::save(&shifted, &m.gaussians, frames, &usplat4d::tables::Provenance::default()).unwrap();
    let (bad, _) = pck_t(&scene, &renders, &shifted, &d.join("E2"));
    eprintln!("PCK-T: oracle {good}\nshifted {bad}");
    assert!(bad["pck_t"].as_f64().unwrap() < score - 0.3, "shifted: {bad} oracle: {good}");

    // A malformed keypoint file names the file and the row.
    let broken = scene.join("keypoint/2x/train/0_00003.json");
    std::fs::write(&broken, "[[1, 2, 1], [3, 4]]").unwrap();
    let (code, err) = usplat4d(&[
        "evaluate",
        "--lpips",
        "off",
        "--renders",
        s(&renders),
        "--scene",
        s(&scene),
        "--model",
        s(&oracle),
        "--out",
        s(&d.join("E3")),
    ]);
    let want = format!(
        "error: {}: row 1: expected [x, y, visible] numbers, got [3,4]\n",
        broken.display()
    );
    assert_eq!((code, err), (2, want));

    // A keypoint file that is not a training image of the sequence.
    let stray = synth.join("dycheck/keypoint/2x/train/1_00000.json");
    std::fs::write(&stray, "[[1, 2, 1]]").unwrap();
    let (code, err) = import(&synth.join("dycheck"), &d.join("I2"), &["--quiet"]);
    let want = format!(
        "error: {}: '1_00000' is not a training image of splits/train.json\n",
        stray.display()
    );
    assert_eq!((code, err), (2, want));

    // Keypoint files of different J.
    std::fs::remove_file(&stray).unwrap();
    let short = synth.join("dycheck/keypoint/2x/train/0_00003.json");
    std::fs::write(&short, "[[1, 2, 1]]").unwrap();
    let (code, err) = import(&synth.join("dycheck"), &d.join("I3"), &["--quiet"]);
    let want = format!(
        "error: {}: has 1 keypoints but {} has 16\n",
        short.display(),
        synth.join("dycheck/keypoint/2x/train/0_00000.json").display()
    );
    assert_eq!((code, err), (2, want));
}
