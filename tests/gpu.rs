//! `usplat4d --device gpu render` and `uncertainty` against `--device cpu` through the real
//! binary on the hand-made demo scene (lavapipe in CI). Tolerances: 8-bit images within one
//! level, depth within 1e-4, uncertainty sums and u within 1e-4 relative, pixel counts and
//! convergence flags exact. Without a GPU adapter: `SKIP gpu: no adapter`.

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
    let a = UncertaintyReader::open(&cpu.join("uncertainty.parquet")).unwrap();
    let b = UncertaintyReader::open(&gpu.join("uncertainty.parquet")).unwrap();
    assert_eq!(a.ids(), b.ids());
    assert_eq!(a.num_frames(), b.num_frames());
    let rel = |x: f32, y: f32| (x - y).abs() / x.abs().max(y.abs()).max(1e-30);
    let mut worst = 0.0f32;
    for t in 0..a.num_frames() {
        let (fa, fb) = (a.frame(t).unwrap(), b.frame(t).unwrap());
        assert_eq!(fa.n_pixels, fb.n_pixels, "frame {t}: pixel counts");
        assert_eq!(fa.converged, fb.converged, "frame {t}: convergence");
        for (x, y) in fa.sum_w2.iter().zip(&fb.sum_w2).chain(fa.sum_w.iter().zip(&fb.sum_w)) {
            worst = worst.max(rel(*x, *y));
        }
        for (x, y) in fa.u.iter().zip(&fb.u) {
            worst = worst.max(rel(*x, *y));
        }
    }
    let conv: usize = (0..a.num_frames())
        .map(|t| a.frame(t).unwrap().converged.iter().filter(|c| **c).count())
        .sum();
    eprintln!("gpu uncertainty: max relative difference {worst:e}, {conv} converged pairs");
    assert!(worst <= 1e-4, "uncertainty differs by {worst} (relative)");
}
