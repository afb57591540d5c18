//! `usplat4d --device gpu render`, `uncertainty` (paper profile: covered-pixel floor τ = 0.5)
//! and `optimize` against `--device cpu` through the real binary (lavapipe in CI): render
//! and uncertainty on the hand-made demo scene, optimize on a tiny Fox scene. Tolerances:
//! 8-bit images within one level, depth within 1e-4, uncertainty sums and u within 1e-4
//! relative, pixel counts and convergence flags exact; optimize as its test says. Without
//! a GPU adapter: `SKIP gpu: no adapter`.

use std::path::Path;

use usplat4d::datasets::demo::write_demo_scene;
use usplat4d::tables::uncertainty::UncertaintyReader;

/// Run `usplat4d --quiet --device <device> args...`; `None` (after a SKIP line) when the GPU
/// run fails for want of an adapter.
fn run(device: &str, args: &[&std::ffi::OsStr]) -> Option<()> {
    let out = crate::util::bin().args(["--quiet", "--device", device]).args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    if device == "gpu" && stderr.contains("no GPU adapter found") {
        eprintln!("SKIP gpu: no adapter");
        return None;
    }
    assert!(out.status.success(), "--device {device} {args:?}: {stderr}");
    Some(())
}

fn os(s: &str) -> &std::ffi::OsStr {
    std::ffi::OsStr::new(s)
}

fn render(device: &str, scene: &Path, model: &Path, out: &Path) -> Option<()> {
    let a = [
        os("render"),
        os("--split"),
        os("all"),
        os("--depth"),
        os("--model"),
        model.as_os_str(),
        os("--scene"),
        scene.as_os_str(),
        os("--out"),
        out.as_os_str(),
    ];
    run(device, &a)
}

#[test]
fn gpu_render_matches_the_cpu_render() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, model) = write_demo_scene(dir.path(), 2).unwrap();
    let (cpu, gpu) = (dir.path().join("cpu"), dir.path().join("gpu"));
    render("cpu", &scene, &model, &cpu).unwrap();
    let Some(()) = render("gpu", &scene, &model, &gpu) else { return };
    let (mut max_level, mut max_depth) = (0.0f32, 0.0f32);
    for cam in ["cam00", "cam01"] {
        for t in 0..2 {
            let rel = format!("rgb/{cam}/{t:05}.png");
            let a = usplat4d::formats::png::read_png(&cpu.join(&rel)).unwrap();
            let b = usplat4d::formats::png::read_png(&gpu.join(&rel)).unwrap();
            assert_eq!((a.width, a.height, a.channels), (b.width, b.height, b.channels));
            for (x, y) in a.data.iter().zip(&b.data) {
                max_level = max_level.max((x - y).abs() * 255.0);
            }
            let rel = format!("depth/{cam}/{t:05}.npy");
            let (_, a) = usplat4d::formats::npy::read_npy_f32(&cpu.join(&rel)).unwrap();
            let (_, b) = usplat4d::formats::npy::read_npy_f32(&gpu.join(&rel)).unwrap();
            for (x, y) in a.iter().zip(&b) {
                max_depth = max_depth.max((x - y).abs());
            }
        }
    }
    eprintln!("gpu render: max 8-bit difference {max_level}, max depth difference {max_depth:e}");
    assert!(max_level <= 1.0 + 1e-3, "8-bit images differ by {max_level} levels");
    assert!(max_depth <= 1e-4, "depth differs by {max_depth}");
}

#[test]
fn gpu_uncertainty_matches_the_cpu_uncertainty() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, model) = write_demo_scene(dir.path(), 3).unwrap();
    // Ground truth: the model rendered on the CPU with another alpha clamp, so that the
    // convergence test has passing and failing pixels.
    let truth = [
        os("render"),
        os("--split"),
        os("all"),
        os("--alpha-max"),
        os("0.5"),
        os("--model"),
        model.as_os_str(),
        os("--scene"),
        scene.as_os_str(),
        os("--out"),
        scene.as_os_str(),
    ];
    run("cpu", &truth).unwrap();
    let (cpu, gpu) = (dir.path().join("ucpu"), dir.path().join("ugpu"));
    let args = |out: &Path| {
        vec![
            os("uncertainty").to_owned(),
            os("--model").to_owned(),
            model.as_os_str().to_owned(),
            os("--scene").to_owned(),
            scene.as_os_str().to_owned(),
            os("--out").to_owned(),
            out.as_os_str().to_owned(),
        ]
    };
    let a = args(&cpu);
    run("cpu", &a.iter().map(|s| s.as_os_str()).collect::<Vec<_>>()).unwrap();
    let b = args(&gpu);
    let Some(()) = run("gpu", &b.iter().map(|s| s.as_os_str()).collect::<Vec<_>>()) else {
        return;
    };
    let (worst, conv) = compare_uncertainty(&cpu, &gpu);
    eprintln!("gpu uncertainty: max relative difference {worst:e}, {conv} converged pairs");
}

/// Compare two `uncertainty` outputs: the same Gaussians and frames, pixel counts and
/// convergence flags exact, sums and u within 1e-4 relative. Returns (largest relative
/// difference, converged pairs).
fn compare_uncertainty(cpu: &Path, gpu: &Path) -> (f32, usize) {
    let a = UncertaintyReader::open(&cpu.join("uncertainty.parquet")).unwrap();
    let b = UncertaintyReader::open(&gpu.join("uncertainty.parquet")).unwrap();
    assert_eq!(a.ids(), b.ids());
    assert_eq!(a.num_frames(), b.num_frames());
    let rel = |x: f32, y: f32| (x - y).abs() / x.abs().max(y.abs()).max(1e-30);
    let (mut worst, mut conv) = (0.0f32, 0);
    for t in 0..a.num_frames() {
        let (fa, fb) = (a.frame(t).unwrap(), b.frame(t).unwrap());
        assert_eq!(fa.n_pixels, fb.n_pixels, "frame {t}: pixel counts");
        assert_eq!(fa.converged, fb.converged, "frame {t}: convergence");
        conv += fa.converged.iter().filter(|c| **c).count();
        let sums = fa.sum_w2.iter().zip(&fb.sum_w2).chain(fa.sum_w.iter().zip(&fb.sum_w));
        for (x, y) in sums.chain(fa.u.iter().zip(&fb.u)) {
            worst = worst.max(rel(*x, *y));
        }
    }
    assert!(worst <= 1e-4, "uncertainty differs by {worst} (relative)");
    (worst, conv)
}

/// Converged (frame, Gaussian) flags of an `uncertainty` output, all frames.
fn converged(dir: &Path) -> Vec<bool> {
    let r = UncertaintyReader::open(&dir.join("uncertainty.parquet")).unwrap();
    (0..r.num_frames()).flat_map(|t| r.frame(t).unwrap().converged).collect()
}

/// The paper profile's covered-pixel floor (τ = 0.5) on the Fox scene's oracle, where it
/// matters: the GPU's table equals the CPU's (flags exact, sums within 1e-4), and the CPU's
/// flags with τ = 0.5 differ from those with τ = 0.
#[test]
fn gpu_uncertainty_with_the_cover_floor_matches_the_cpu() {
    let dir = crate::util::Dir::new();
    grey_fox(&dir);
    let args = ["uncertainty", "--model", "S/oracle", "--scene", "S", "--out"];
    let run = |device: &str, out: &str, extra: &[&str]| {
        let d = ["--quiet", "--device", device];
        dir.run(&[&d[..], &args[..], &[out], extra].concat())
    };
    let cpu = run("cpu", "C", &[]);
    assert!(cpu.status.success(), "{}", String::from_utf8_lossy(&cpu.stderr));
    let gpu = run("gpu", "G", &[]);
    let stderr = String::from_utf8_lossy(&gpu.stderr);
    if stderr.contains("no GPU adapter found") {
        eprintln!("SKIP gpu: no adapter");
        return;
    }
    assert!(gpu.status.success(), "{stderr}");
    let (worst, conv) = compare_uncertainty(&dir.join("C"), &dir.join("G"));
    let all = run("cpu", "C0", &["--cover-min-weight", "0"]);
    assert!(all.status.success(), "{}", String::from_utf8_lossy(&all.stderr));
    let (tau, zero) = (converged(&dir.join("C")), converged(&dir.join("C0")));
    let changed = tau.iter().zip(&zero).filter(|(a, b)| a != b).count();
    eprintln!(
        "gpu uncertainty (tau 0.5, Fox): max relative difference {worst:e}, {conv} converged \
         pairs; tau changes {changed} of {} flags",
        tau.len()
    );
    assert!(changed > 0, "the floor changes no flag: the test would not see it");
}

/// The tiny Fox scene of `tests/optimize.rs` (4 frames at 64x64, 800 oracle Gaussians) in
/// `dir/S`, and a start model `dir/grey`: the oracle with every colour mid-grey.
fn grey_fox(dir: &crate::util::Dir) {
    let gltf = crate::util::repo().join("pipelines/data/Fox.glb");
    let args = ["synth", "--gltf", gltf.to_str().unwrap(), "--animation", "Walk", "--out", "S"];
    let size = ["--frames", "4", "--width", "64", "--height", "64", "--gaussians", "800"];
    dir.ok(&[&args[..], &size[..]].concat());
    let m = usplat4d::model::Model::load(&dir.join("S/oracle")).unwrap();
    let mut g = m.gaussians.clone();
    g.color.iter_mut().for_each(|c| *c = [0.5; 3]);
    let frames: Vec<_> = (0..m.num_frames()).map(|t| m.frame(t)).collect();
    let prov = usplat4d::tables::Provenance::default();
    usplat4d::model::Model::save(&dir.join("grey"), &g, frames, &prov).unwrap();
}

/// Largest difference of two parameter arrays relative to the CPU run's largest change
/// from the start model (how far training moved the group).
fn rel_to_change(gpu: &[f32], cpu: &[f32], start: &[f32]) -> f32 {
    let moved = cpu.iter().zip(start).map(|(c, s)| (c - s).abs()).fold(0.0f32, f32::max);
    let d = gpu.iter().zip(cpu).map(|(g, c)| (g - c).abs()).fold(0.0f32, f32::max);
    d / moved.max(f32::MIN_POSITIVE)
}

/// `optimize --device gpu` against `--device cpu`: 8 vanilla steps from grey colours. The
/// GPU's gradients match the CPU's to a few 1e-6 of their group's largest magnitude
/// (`render::gpu::tests`), but are summed in another order, and Adam (ε = 1e-15) divides
/// each gradient by its own running RMS: a parameter whose gradient is nearly zero can step
/// by up to the learning rate in either direction. So the runs are compared on what
/// training does, not bit for bit: per-step losses within 1e-3 relative, and every
/// parameter group within 5% of how far the CPU run moved it (lavapipe: 1e-7 and 7e-5; a
/// wrong gradient moves a group by its whole change). `bench optimize --device gpu` runs
/// on the same scene and names the GPU in its row.
#[test]
fn gpu_optimize_trains_like_the_cpu() {
    let dir = crate::util::Dir::new();
    grey_fox(&dir);
    let base = ["optimize", "--model", "grey", "--scene", "S", "--recipe", "vanilla"];
    let common = ["--steps", "8", "--batch-frames", "2", "--lr-color", "0.05"];
    let run = |device: &str, out: &str| {
        let d = ["--quiet", "--device", device];
        dir.run(&[&d[..], &base[..], &["--out", out], &common[..]].concat())
    };
    let cpu = run("cpu", "C");
    assert!(cpu.status.success(), "{}", String::from_utf8_lossy(&cpu.stderr));
    let gpu = run("gpu", "G");
    let stderr = String::from_utf8_lossy(&gpu.stderr);
    if stderr.contains("no GPU adapter found") {
        eprintln!("SKIP gpu: no adapter");
        return;
    }
    assert!(gpu.status.success(), "{stderr}");
    let log =
        |d: &str| usplat4d::tables::training_log::read(&dir.join(d).join("training_log.parquet"));
    let (lc, lg) = (log("C").unwrap(), log("G").unwrap());
    assert_eq!(lc.len(), lg.len());
    let mut loss_err = 0.0f64;
    for (c, g) in lc.iter().zip(&lg) {
        loss_err = loss_err.max((c.loss - g.loss).abs() / c.loss.abs());
    }
    let load = |d: &str| usplat4d::model::Model::load(&dir.join(d)).unwrap();
    let (start, mc, mg) = (load("grey"), load("C"), load("G"));
    let flat3 = |v: &[[f32; 3]]| v.concat();
    let (s, c, g) = (&start.gaussians, &mc.gaussians, &mg.gaussians);
    assert_eq!(c.id, g.id);
    let mut groups = vec![
        ("colour", rel_to_change(&flat3(&g.color), &flat3(&c.color), &flat3(&s.color))),
        ("opacity", rel_to_change(&g.opacity, &c.opacity, &s.opacity)),
        ("scale", rel_to_change(&flat3(&g.scale), &flat3(&c.scale), &flat3(&s.scale))),
    ];
    let (mut pc, mut pg, mut ps) = (Vec::new(), Vec::new(), Vec::new());
    for t in 0..mc.num_frames() {
        pc.extend(flat3(&mc.frame(t).unwrap().position));
        pg.extend(flat3(&mg.frame(t).unwrap().position));
        ps.extend(flat3(&start.frame(t).unwrap().position));
    }
    groups.push(("position", rel_to_change(&pg, &pc, &ps)));
    let rgb = |r: &usplat4d::tables::training_log::LogRow| {
        r.terms.iter().find(|(k, _)| k == "rgb").expect("rgb term").1
    };
    let (first, last) = (rgb(&lc[0]), rgb(lc.last().unwrap()));
    eprintln!(
        "gpu optimize: L_rgb {first:.5} -> {last:.5} (cpu), max relative loss difference \
         {loss_err:e}; parameter differences relative to the cpu run's change: {groups:?}"
    );
    assert!(last < 0.8 * first, "the CPU run must train: L_rgb {first} -> {last}");
    assert!(loss_err <= 1e-3, "losses differ by {loss_err} (relative)");
    for (name, e) in groups {
        assert!(e <= 0.05, "{name}: GPU and CPU runs differ by {e} of the CPU run's change");
    }
    let bench = ["--quiet", "--device", "gpu", "bench", "optimize", "--model", "grey"];
    let row =
        dir.ok(&[&bench[..], &["--scene", "S", "--steps", "2", "--batch-frames", "2"]].concat());
    eprintln!("{row}");
    assert!(row.contains("| gpu:"), "bench optimize --device gpu: {row}");
}
