//! End-to-end tests of `usplat4d evaluate` on a hand-made scene directory: ground-truth
//! PNGs and a cameras table written with `Scene::save`, and "renders" made by perturbing
//! the ground truth; and of `evaluate --model` (3D tracking) on a tiny `synth` scene with
//! its oracle model and a model whose trajectories are offset. Not validated here: LPIPS
//! values (unit-tested against golden values in `metrics::lpips`).

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::util::bin;

use usplat4d::formats::png::{Image, read_png, write_png};
use usplat4d::scene::{Camera, Pinhole, Scene, Split};
use usplat4d::tables::Provenance;

const W: usize = 40;
const H: usize = 36;

fn run(args: &[&str]) -> Output {
    bin().arg("--quiet").args(args).output().expect("run usplat4d")
}

/// `usplat4d --quiet evaluate --renders R --scene S --out O --lpips off EXTRA...`.
fn evaluate(renders: &Path, scene: &Path, out: &Path, extra: &[&str]) -> Output {
    let args = ["evaluate", "--renders", s(renders), "--scene", s(scene), "--out", s(out)];
    run(&[&args[..], &["--lpips", "off"], extra].concat())
}

fn camera(name: &str, frame: u32, split: Split, angle: Option<f32>, mask: bool) -> Camera {
    let w2c = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0];
    Camera {
        mask_path: mask.then(|| format!("mask/{name}/{frame:05}.png")),
        angle_offset_deg: angle,
        ..Camera::new(frame, name, split, Pinhole::centred(50.0, W as u32, H as u32, w2c))
    }
}

/// A smooth RGBA test pattern that differs per camera and frame.
fn pattern(seed: usize) -> Image {
    let mut data = Vec::with_capacity(W * H * 4);
    for y in 0..H {
        for x in 0..W {
            let t = (x * 3 + y * 5 + seed * 17) as f32;
            data.extend_from_slice(&[
                (t * 0.05).sin() * 0.5 + 0.5,
                (y as f32) / H as f32,
                (x as f32) / W as f32,
                1.0,
            ]);
        }
    }
    Image { width: W, height: H, channels: 4, data }
}

/// Write a scene with one training camera and eval cameras `(name, angle, with mask)`
/// over 2 frames; returns the scene's eval cameras.
fn make_scene(dir: &Path, evals: &[(&str, Option<f32>, bool)]) -> Vec<Camera> {
    let mut cams = Vec::new();
    for f in 0..2 {
        cams.push(camera("cam00", f, Split::Train, None, false));
        for (name, angle, mask) in evals {
            cams.push(camera(name, f, Split::Eval, *angle, *mask));
        }
    }
    for (i, c) in cams.iter().enumerate() {
        write_png(&dir.join(&c.image_path), &pattern(i)).unwrap();
        if let Some(m) = &c.mask_path {
            let data = (0..W * H).map(|p| if p % W < W / 2 { 1.0 } else { 0.0 }).collect();
            write_png(&dir.join(m), &Image { width: W, height: H, channels: 1, data }).unwrap();
        }
    }
    Scene { dir: dir.to_path_buf(), cameras: cams.clone() }.save(&Provenance::default()).unwrap();
    cams.into_iter().filter(|c| c.split == Split::Eval).collect()
}

/// Renders: the ground truth, with `noise` added to every 7th value of each camera except
/// the first when `keep_first` (which then stays identical).
fn make_renders(scene: &Path, out: &Path, cams: &[Camera], noise: f32, keep_first: bool) {
    for (i, c) in cams.iter().enumerate() {
        let mut img = read_png(&scene.join(&c.image_path)).unwrap();
        if i > 0 || !keep_first {
            for (k, v) in img.data.iter_mut().enumerate() {
                if k % 7 == 0 && k % 4 != 3 {
                    *v = (*v + noise).min(1.0);
                }
            }
        }
        write_png(&out.join(&c.image_path), &img).unwrap();
    }
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

struct Setup {
    _tmp: tempfile::TempDir,
    scene: PathBuf,
    renders: PathBuf,
    out: PathBuf,
    cams: Vec<Camera>,
}

fn synthetic() -> Setup {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    let renders = tmp.path().join("renders");
    let cams = make_scene(
        &scene,
        &[("cam01", Some(30.0), false), ("cam03", Some(90.0), false), ("cam07", Some(210.0), true)],
    );
    make_renders(&scene, &renders, &cams, 0.2, true);
    let out = tmp.path().join("eval");
    Setup { _tmp: tmp, scene, renders, out, cams }
}

#[test]
fn evaluate_prints_view_ranges_and_writes_outputs() {
    let t = synthetic();
    let o = evaluate(&t.renders, &t.scene, &t.out, &["--method", "perturbed"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8(o.stdout).unwrap();
    assert!(
        stdout.starts_with("# perturbed on scene\n\n| views | images | PSNR | SSIM | LPIPS |\n"),
        "{stdout}"
    );
    for label in ["| (0°, 60°] | 2 |", "| (60°, 120°] | 2 |", "| (120°, 180°] | 2 |", "| all | 6 |"]
    {
        assert!(stdout.contains(label), "{label} in {stdout}");
    }
    let rows = usplat4d::tables::metrics::read(&t.out.join("metrics.parquet")).unwrap();
    assert_eq!(rows.len(), 6);
    let order: Vec<(String, u32)> = rows.iter().map(|r| (r.camera.clone(), r.frame)).collect();
    let want: Vec<(String, u32)> = t.cams.iter().map(|c| (c.camera.clone(), c.frame)).collect();
    assert_eq!(order, want);
    // The first eval image is the ground truth itself; the others are perturbed.
    assert_eq!(rows[0].psnr, f64::INFINITY);
    assert!((rows[0].ssim - 1.0).abs() < 1e-12);
    for r in &rows[1..] {
        assert!(r.psnr > 10.0 && r.psnr < 40.0 && r.ssim < 1.0, "{r:?}");
        // Synthetic cameras (with an angle offset) are scored on the full image even
        // when they have a mask.
        assert!(!r.masked && r.lpips.is_none());
    }
    assert_eq!(std::fs::read_to_string(t.out.join("summary.md")).unwrap(), stdout);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(t.out.join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(json["groups"][3]["images"], 6);

    // Same inputs, one thread: identical bytes.
    let before = std::fs::read(t.out.join("metrics.parquet")).unwrap();
    let o = bin()
        .args([
            "--quiet",
            "--threads",
            "1",
            "evaluate",
            "--renders",
            s(&t.renders),
            "--scene",
            s(&t.scene),
        ])
        .args(["--out", s(&t.out), "--method", "perturbed", "--lpips", "off"])
        .output()
        .unwrap();
    assert!(o.status.success());
    assert_eq!(std::fs::read(t.out.join("metrics.parquet")).unwrap(), before);
}

#[test]
fn missing_render_names_the_file() {
    let t = synthetic();
    let missing = t.renders.join("rgb/cam03/00001.png");
    std::fs::remove_file(&missing).unwrap();
    let o = evaluate(&t.renders, &t.scene, &t.out, &[]);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(
        String::from_utf8(o.stderr).unwrap(),
        format!("error: missing render for camera 'cam03' frame 1: {}\n", missing.display())
    );
    assert!(!t.out.exists());
}

#[test]
fn fail_below_exits_1_and_compare_prints_differences() {
    let t = synthetic();
    let o = evaluate(&t.renders, &t.scene, &t.out, &["--method", "a"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Worse renders (every image perturbed) as method b.
    let renders_b = t.renders.with_file_name("renders_b");
    make_renders(&t.scene, &renders_b, &t.cams, 0.4, false);
    let out_b = t.out.with_file_name("eval_b");
    let eval_b = |extra: &[&str]| {
        evaluate(&renders_b, &t.scene, &out_b, &[&["--method", "b"], extra].concat())
    };
    let o = eval_b(&["--fail-below", "100"]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8(o.stderr).unwrap();
    assert!(
        err.starts_with("check failed: mean PSNR ")
            && err.ends_with(" dB of 'b' on 'scene' is below --fail-below 100\n"),
        "{err}"
    );
    let o = eval_b(&["--fail-below", "5"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = run(&["evaluate", "--compare", s(&t.out), s(&out_b.join("metrics.parquet"))]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8(o.stdout).unwrap();
    assert!(stdout.starts_with("# a vs b on scene (Δ against a)\n"), "{stdout}");
    let cell = |method: &str, k: usize| -> f64 {
        let line =
            stdout.lines().find(|l| l.starts_with(&format!("| (60°, 120°] | {method} |"))).unwrap();
        line.split('|').map(str::trim).nth(k).unwrap().parse().unwrap()
    };
    let (pa, pb, d) = (cell("a", 4), cell("b", 4), cell("b", 5));
    assert!(pb < pa && d < 0.0 && (pb - pa - d).abs() < 0.011, "{stdout}");
    assert_eq!(cell("a", 5), 0.0);
}

#[test]
fn masked_protocol_for_cameras_without_offsets() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("dy");
    let renders = tmp.path().join("r");
    let cams = make_scene(&scene, &[("1", None, true), ("2", None, true)]);
    // Perturb only the right half, which the masks exclude: masked metrics are perfect.
    for c in &cams {
        let mut img = read_png(&scene.join(&c.image_path)).unwrap();
        for (p, px) in img.data.chunks_exact_mut(4).enumerate() {
            if p % W >= W / 2 {
                px[0] = 1.0 - px[0];
            }
        }
        write_png(&renders.join(&c.image_path), &img).unwrap();
    }
    let out = tmp.path().join("e");
    let o = evaluate(&renders, &scene, &out, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8(o.stdout).unwrap();
    assert!(stdout.contains("| views | images | mPSNR | mSSIM | mLPIPS |"), "{stdout}");
    assert!(!stdout.contains("60°"), "{stdout}");
    let rows = usplat4d::tables::metrics::read(&out.join("metrics.parquet")).unwrap();
    assert!(rows.iter().all(|r| r.masked && r.psnr == f64::INFINITY), "{rows:?}");
    // Without masks the same renders are imperfect.
    let o = evaluate(&renders, &scene, &out, &["--masks", "never"]);
    assert!(o.status.success());
    let rows = usplat4d::tables::metrics::read(&out.join("metrics.parquet")).unwrap();
    assert!(rows.iter().all(|r| !r.masked && r.psnr < 20.0), "{rows:?}");
}

/// `evaluate --model`: the synth oracle tracks the ground truth closely; the same model
/// with every position offset by 0.3 of the bbox diagonal scores clearly worse.
#[test]
fn tracking_scores_oracle_and_offset_model() {
    use usplat4d::model::{FrameState, Model};
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let fox = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/data/Fox.glb");
    let (scene, oracle) = (d.join("S"), d.join("S/oracle"));
    let ok = |o: Output| assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    ok(run(&[
        "synth",
        "--gltf",
        s(&fox),
        "--out",
        s(&scene),
        "--frames",
        "6",
        "--cameras",
        "2",
        "--width",
        "128",
        "--height",
        "128",
        "--gaussians",
        "800",
        "--tracks",
        "64",
    ]));
    let renders = d.join("R");
    ok(run(&crate::util::render_eval_args(&oracle, &scene, &renders)));
    let score = |model: &Path, out: &Path| -> serde_json::Value {
        let o = evaluate(&renders, &scene, out, &["--model", s(model)]);
        let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(stdout.contains("| EPE | PCK@5% | PCK@10% |"), "{stdout}");
        let md = std::fs::read_to_string(out.join("summary.md")).unwrap();
        assert_eq!(md, stdout);
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap();
        json["tracking"].clone()
    };
    let good = score(&oracle, &d.join("E"));
    let diag = good["bbox_diagonal"].as_f64().unwrap();
    assert_eq!(good["keyframes"], serde_json::json!([0, 1, 2, 3, 4, 5]));
    assert_eq!(good["pairs"], 36);
    let (epe, pck10) = (good["epe"].as_f64().unwrap(), good["pck_10"].as_f64().unwrap());
    assert!(epe < 0.05 * diag && pck10 > 0.9, "oracle: {good}");

    let m = Model::load(&oracle).unwrap();
    let offset = (0.3 * diag / 3f64.sqrt()) as f32;
    let frames = (0..m.num_frames()).map(|t| {
        m.frame(t).map(|f| FrameState {
            position: f.position.iter().map(|p| p.map(|v| v + offset)).collect(),
            ..f
        })
    });
    let moved = d.join("moved");
    Model::save(&moved, &m.gaussians, frames, &Provenance::default()).unwrap();
    let bad = score(&moved, &d.join("E2"));
    let (bad_epe, bad_pck10) = (bad["epe"].as_f64().unwrap(), bad["pck_10"].as_f64().unwrap());
    eprintln!("tracking scores: oracle {good}\noffset {bad}");
    assert!(bad_epe > epe + 0.2 * diag && bad_pck10 < 0.2, "offset: {bad} oracle: {good}");

    // The training split scores its images and tracks the same way.
    let train_renders = d.join("RT");
    let mut args = crate::util::render_eval_args(&oracle, &scene, &train_renders);
    args[6] = "train"; // the value of --split
    ok(run(&args));
    let out = d.join("ET");
    ok(evaluate(&train_renders, &scene, &out, &["--split", "train", "--model", s(&oracle)]));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(json["tracking"], good, "{json}");

    // Without --model the summary has no tracking entry.
    ok(evaluate(&renders, &scene, &d.join("E3"), &[]));
    let plain = std::fs::read_to_string(d.join("E3/summary.json")).unwrap();
    assert!(!plain.contains("tracking"), "{plain}");
}
