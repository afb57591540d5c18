//! Parity of the GPU rasterizer with the CPU reference on seeded scenes (random clouds with
//! RGB, SH in the world and local frames and feature channels; the CPU tests' fuzzed inputs;
//! a scene whose intersection list overflows the first pair buffer), every frame's buffers
//! filled with junk first. Tolerances: images 1e-4 absolute; statistics 1e-4 relative;
//! gradients 1e-3 relative to the largest magnitude of their group (see `grad_err`).
//! Without any adapter the tests print `SKIP gpu: no adapter` and return.

use glam::Mat4;

use super::super::synthetic::{camera, cloud};
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

#[derive(Debug, Clone)]
struct Scene {
    means: Vec<[f32; 3]>,
    quats: Vec<[f32; 4]>,
    scales: Vec<[f32; 3]>,
    opacities: Vec<f32>,
    dc: Vec<[f32; 3]>,
    rest: Vec<f32>,
    degree: u8,
    frame: Option<ShFrame>,
    features: Vec<f32>,
    nf: usize,
}

impl Scene {
    fn new(
        cam: &RenderCamera,
        n: usize,
        complexity: f32,
        seed: u64,
        frame: Option<ShFrame>,
    ) -> Scene {
        let c = cloud(cam, n, complexity, seed);
        let mut rng = Rng::from_state(seed ^ 0x5eed);
        let (degree, nf) = if frame.is_some() { (3, 2) } else { (0, 0) };
        let k3 = 3 * (sh::num_basis(degree) - 1);
        Scene {
            rest: (0..n * k3).map(|_| rng.range_f32(-0.3, 0.3)).collect(),
            features: (0..n * nf).map(|_| rng.range_f32(-1.0, 1.0)).collect(),
            means: c.means,
            quats: c.quats,
            scales: c.scales,
            opacities: c.opacities,
            dc: c.colors,
            degree,
            frame,
            nf,
        }
    }

    fn inputs(&self) -> SplatInputs<'_> {
        let colors = match self.frame {
            None => ColorSource::Rgb(&self.dc),
            Some(frame) => {
                ColorSource::Sh { degree: self.degree, dc: &self.dc, rest: &self.rest, frame }
            }
        };
        SplatInputs {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
            colors,
            features: &self.features,
            num_features: self.nf,
        }
    }
}

fn settings() -> RenderSettings {
    RenderSettings { background: [0.2, 0.5, 0.9], alpha_max: 0.99 }
}

fn tilted(w: u32, h: u32) -> RenderCamera {
    let w2c =
        Mat4::from_rotation_y(0.1) * Mat4::from_translation(glam::Vec3::new(0.05, -0.02, 0.1));
    RenderCamera { w2c, ..camera(w, h) }
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

/// The CPU tests' poisoned inputs (NaN, Inf, zero quaternion, huge scales, behind the camera).
fn fuzzed() -> (RenderCamera, Scene) {
    let cam = camera(32, 24);
    let mut s = Scene::new(&cam, 20, 5.0, 5, None);
    let (nan, inf) = (f32::NAN, f32::INFINITY);
    s.means[0][1] = nan;
    s.means[1][2] = inf;
    s.quats[2] = [0.0; 4];
    s.quats[3][2] = nan;
    s.scales[4] = [1e25; 3];
    s.scales[5][0] = inf;
    s.means[6][2] = -3.0;
    s.opacities[7] = nan;
    s.means[8] = [1e30, -1e30, 1e30];
    s.opacities[9] = -0.5;
    s.scales[10] = [0.0; 3];
    s.dc[11] = [nan, inf, -inf];
    s.scales[12] = [1e5; 3];
    (cam, s)
}

#[test]
fn fuzzed_inputs_are_culled_as_on_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let (cam, s) = fuzzed();
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
