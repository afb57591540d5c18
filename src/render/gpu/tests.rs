//! Parity of the GPU rasterizer with the CPU reference on seeded scenes (random clouds with
//! RGB, SH in the world and local frames and feature channels; the CPU tests' fuzzed inputs;
//! a scene whose intersection list overflows the first pair buffer), every frame's buffers
//! filled with junk first. Tolerances: images 1e-4 absolute; statistics 1e-4 relative;
//! gradients 1e-3 relative to the largest magnitude of their group (see `grad_err`);
//! convergence flags (all covered pixels, the centre pixel, and the covered-pixel floor τ
//! of `--cover-min-weight`) exact: the GPU blends with the CPU's arithmetic, so T·α >= τ
//! is decided alike. Without any adapter the tests print `SKIP gpu: no adapter` and return.

use super::super::synthetic::camera;
use super::super::test_scene::{Scene, settings, tilted};
use super::super::*;
use super::GpuRenderer;
use crate::util::rng::Rng;

/// The GPU under test (software adapters allowed: lavapipe in CI), or `None` with a SKIP.
fn gpu() -> Option<GpuRenderer> {
    match GpuRenderer::new(true) {
        Ok(Some(r)) => {
            eprintln!("gpu: {}", r.adapter());
            Some(r.with_junk())
        }
        Ok(None) => {
            eprintln!("SKIP gpu: no adapter");
            None
        }
        Err(e) => panic!("GPU adapter present but unusable: {e}"),
    }
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Largest relative error of per-Gaussian sums (relative to the CPU value, with a floor of
/// 1e-6 of the array's largest value for sums that are nearly zero).
fn max_rel(gpu: &[f32], cpu: &[f32]) -> f32 {
    let scale = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    gpu.iter()
        .zip(cpu)
        .map(|(g, c)| (g - c).abs() / c.abs().max(1e-6 * scale).max(f32::MIN_POSITIVE))
        .fold(0.0, f32::max)
}

/// Compare one forward render; returns (image error, statistics error).
fn check_forward(g: &RenderOutput, c: &RenderOutput, what: &str) -> (f32, f32) {
    let img = [
        max_abs(&g.color, &c.color),
        max_abs(&g.alpha, &c.alpha),
        max_abs(&g.depth, &c.depth),
        max_abs(&g.features, &c.features),
    ]
    .into_iter()
    .fold(0.0, f32::max);
    let differ = |a: &[u32], b: &[u32]| a.iter().zip(b).filter(|(x, y)| x != y).count();
    let vis: Vec<u32> =
        g.aux.visible.iter().zip(&c.aux.visible).map(|(a, b)| (a != b) as u32).collect();
    let n_vis = vis.iter().sum::<u32>();
    let n_px = differ(&g.aux.n_pixels, &c.aux.n_pixels);
    eprintln!(
        "{what}: image error {img:e}, {n_vis} visible flags and {n_px} pixel counts differ (Σ gpu {} cpu {})",
        g.aux.n_pixels.iter().sum::<u32>(),
        c.aux.n_pixels.iter().sum::<u32>()
    );
    assert_eq!(n_vis, 0, "{what}: visible");
    assert_eq!(n_px, 0, "{what}: n_pixels");
    let stats = [
        max_rel(&g.aux.sum_w2, &c.aux.sum_w2),
        max_rel(&g.aux.sum_w, &c.aux.sum_w),
        max_rel(&g.aux.radius_px, &c.aux.radius_px),
    ]
    .into_iter()
    .fold(0.0, f32::max);
    assert!(img <= 1e-4, "{what}: image error {img}");
    assert!(stats <= 1e-4, "{what}: statistics error {stats}");
    (img, stats)
}

/// Largest error of a gradient group relative to the group's largest CPU magnitude.
fn grad_err(g: &[f32], c: &[f32]) -> f32 {
    let scale = c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    if scale == 0.0 {
        return max_abs(g, c);
    }
    max_abs(g, c) / scale
}

fn check_grads(g: &SplatGrads, c: &SplatGrads, what: &str) -> f32 {
    let flat3 = |v: &[[f32; 3]]| v.concat();
    let groups = [
        ("means", grad_err(&flat3(&g.means), &flat3(&c.means))),
        ("quats", grad_err(&g.quats.concat(), &c.quats.concat())),
        ("scales", grad_err(&flat3(&g.scales), &flat3(&c.scales))),
        ("opacities", grad_err(&g.opacities, &c.opacities)),
        ("colors", grad_err(&flat3(&g.colors), &flat3(&c.colors))),
        ("sh_rest", grad_err(&g.sh_rest, &c.sh_rest)),
        ("features", grad_err(&g.features, &c.features)),
        ("means2d", grad_err(&g.means2d.concat(), &c.means2d.concat())),
    ];
    let mut worst = 0.0f32;
    for (name, e) in groups {
        assert!(e <= 1e-3, "{what}: {name} gradient error {e}");
        worst = worst.max(e);
    }
    worst
}

fn cotangents(w: usize, h: usize, nf: usize, seed: u64) -> ImageGrads {
    let mut rng = Rng::from_state(seed);
    let mut v = |n: usize| (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect::<Vec<f32>>();
    ImageGrads { color: v(w * h * 3), alpha: v(w * h), depth: v(w * h), features: v(w * h * nf) }
}

#[test]
fn forward_and_statistics_match_the_cpu_on_random_clouds() {
    let Some(gpu) = gpu() else { return };
    let mut worst = (0.0f32, 0.0f32);
    for (seed, frame) in [(1, None), (2, Some(ShFrame::World)), (3, Some(ShFrame::Local))] {
        let cam = tilted(64, 48);
        let s = Scene::new(&cam, 300, 6.0, seed, frame);
        let c = CpuRenderer.render(&cam, &s.inputs(), &settings()).unwrap();
        let g = gpu.render(&cam, &s.inputs(), &settings()).unwrap();
        let (i, st) = check_forward(&g, &c, &format!("seed {seed} {frame:?}"));
        worst = (worst.0.max(i), worst.1.max(st));
        // A second render reuses the frame's buffers.
        let again = gpu.render(&cam, &s.inputs(), &settings()).unwrap();
        check_forward(&again, &c, "reused buffers");
    }
    eprintln!("max image error {:e}, max statistics error {:e}", worst.0, worst.1);
}

#[test]
fn overflowing_intersection_list_grows_and_rerenders() {
    let Some(gpu) = gpu() else { return };
    // 2000 large Gaussians over 12 tiles: about 20k pairs > the first buffer's 16k.
    let cam = camera(64, 48);
    let s = Scene::new(&cam, 2000, 200.0, 9, None);
    let c = CpuRenderer.render(&cam, &s.inputs(), &settings()).unwrap();
    let g = gpu.render(&cam, &s.inputs(), &settings()).unwrap();
    let (i, st) = check_forward(&g, &c, "large list");
    eprintln!("large list: image error {i:e}, statistics error {st:e}");
}

#[test]
fn fuzzed_inputs_are_culled_as_on_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let (cam, s) = Scene::fuzzed();
    let (c, cs) =
        CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    let (g, gs) = gpu.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    check_forward(&g, &c, "fuzzed");
    assert!(!g.aux.visible[..10].iter().any(|v| *v), "poisoned Gaussians must be culled");
    let v = cotangents(32, 24, 0, 4);
    let cg = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &cs, &v).unwrap();
    let gg = gpu.backward(&cam, &s.inputs(), &settings(), &gs, &v).unwrap();
    check_grads(&gg, &cg, "fuzzed");
    let mut short = s.clone();
    short.opacities.pop();
    let err = gpu.render(&cam, &short.inputs(), &settings()).unwrap_err();
    assert_eq!(err.to_string(), "input 'opacities' has 19 entries, expected 20");
}

#[test]
fn gradients_match_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let mut worst = 0.0f32;
    for (seed, frame, cutoff) in [
        (11, None, Cutoff::Hard),
        (12, Some(ShFrame::World), Cutoff::Hard),
        (13, Some(ShFrame::Local), Cutoff::Smooth),
    ] {
        let cam = tilted(48, 40);
        let s = Scene::new(&cam, 200, 4.0, seed, frame);
        let what = format!("seed {seed} {frame:?} {cutoff:?}");
        let (c, cs) =
            CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), cutoff).unwrap();
        let (g, gs) = gpu.render_with_saved(&cam, &s.inputs(), &settings(), cutoff).unwrap();
        check_forward(&g, &c, &what);
        let v = cotangents(48, 40, s.nf, seed);
        let cg = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &cs, &v).unwrap();
        let gg = gpu.backward(&cam, &s.inputs(), &settings(), &gs, &v).unwrap();
        worst = worst.max(check_grads(&gg, &cg, &what));
    }
    eprintln!("max gradient error (relative to group max) {worst:e}");
}

/// `[H, W]` pixel pass map with about `fail` of the pixels failing.
fn pass_map(w: usize, h: usize, fail: f32, seed: u64) -> Vec<bool> {
    let mut rng = Rng::from_state(seed);
    (0..w * h).map(|_| rng.uniform_f32() >= fail).collect()
}

/// The covered-pixel floor τ (`--cover-min-weight`): the GPU's `fail_pairs` with
/// `min_weight` > 0 against the CPU's `failing_pairs_weighted`, exactly, on random clouds
/// (RGB and SH, hard and smooth cutoff, several failing fractions, τ from 1e-3 to 0.9), the
/// fuzzed inputs, and a frame rendered twice (reused, junk-filled convergence buffers).
#[test]
fn weighted_convergence_matches_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let taus = [1e-3, 0.05, 0.2, 0.5, 0.9];
    let mut differ_from_all = 0;
    let mut cases = Vec::new();
    for (seed, frame, cutoff, complexity) in [
        (31, None, Cutoff::Hard, 6.0),
        (32, Some(ShFrame::World), Cutoff::Hard, 12.0),
        (33, Some(ShFrame::Local), Cutoff::Smooth, 3.0),
    ] {
        let cam = tilted(72, 40);
        cases.push((cam, Scene::new(&cam, 400, complexity, seed, frame), cutoff, seed));
    }
    let (fcam, fscene) = Scene::fuzzed();
    cases.push((fcam, fscene, Cutoff::Hard, 34));
    for (cam, s, cutoff, seed) in &cases {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let (c, cs) =
            CpuRenderer.render_with_saved(cam, &s.inputs(), &settings(), *cutoff).unwrap();
        let (g, gs) = gpu.render_with_saved(cam, &s.inputs(), &settings(), *cutoff).unwrap();
        check_forward(&g, &c, &format!("weighted convergence seed {seed}"));
        for (k, fail) in [0.03, 0.3, 1.0].into_iter().enumerate() {
            let pass = pass_map(w, h, fail, seed * 10 + k as u64);
            let all = ConvergenceTest::AllCoveredPixels;
            let want_all =
                CpuRenderer.convergence_saved(cam, &settings(), &cs, &pass, all).unwrap();
            for tau in taus {
                let test = ConvergenceTest::WeightedPixels(tau);
                let want =
                    CpuRenderer.convergence_saved(cam, &settings(), &cs, &pass, test).unwrap();
                let got = gpu.convergence_saved(cam, &settings(), &gs, &pass, test).unwrap();
                let n_diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
                assert_eq!(
                    n_diff, 0,
                    "seed {seed}, failing {fail}, τ {tau}: {n_diff} flags differ"
                );
                differ_from_all += want.iter().zip(&want_all).filter(|(a, b)| a != b).count();
                // Monotone: a higher floor tests fewer pixels, so nothing that passed fails.
                assert!(want.iter().zip(&want_all).all(|(wt, wa)| *wt || !*wa));
            }
        }
    }
    eprintln!("weighted convergence: {differ_from_all} flags differ from the unweighted test");
    assert!(differ_from_all > 0, "the floor never mattered: the test is trivial");
}

#[test]
fn convergence_matches_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let cam = tilted(64, 48);
    let s = Scene::new(&cam, 300, 6.0, 21, None);
    let mut rng = Rng::from_state(3);
    let pass: Vec<bool> = (0..64 * 48).map(|_| rng.uniform_f32() < 0.97).collect();
    let (c, cs) =
        CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    let (_, gs) = gpu.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    for test in [ConvergenceTest::AllCoveredPixels, ConvergenceTest::CentrePixel] {
        let want = CpuRenderer.convergence_saved(&cam, &settings(), &cs, &pass, test).unwrap();
        let got = gpu.convergence_saved(&cam, &settings(), &gs, &pass, test).unwrap();
        assert_eq!(got, want, "{test:?}");
        let seen: Vec<bool> = want.iter().zip(&c.aux.n_pixels).map(|(p, n)| *p && *n > 0).collect();
        assert!(seen.iter().any(|p| *p) && seen.iter().any(|p| !*p), "{test:?} is trivial");
    }
}
