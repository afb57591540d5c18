//! End-to-end tests of the CPU renderer: finite-difference gradients of every parameter
//! group, per-Gaussian statistics against a tile-free brute-force reference, fuzzed inputs,
//! thread-count determinism, invariance to culled and hidden Gaussians, and convergence.

use super::constants::T_THRESHOLD;
use super::cpu::blend::eval_alpha;
use super::cpu::project::{CameraConsts, project};
use super::synthetic::{camera, cloud};
use super::test_scene::{Scene, settings, tilted};
use super::*;
use crate::util::rng::Rng;

/// A small hand-tuned scene kept away from discontinuities: distinct depths, opacities
/// ≤ 0.7 (no alpha clamp, no termination), positive colours, all inside the view.
fn fd_scene(frame: Option<ShFrame>) -> Scene {
    let mut rng = Rng::from_state(7);
    let n = 5;
    let mut s = Scene {
        means: Vec::new(),
        quats: Vec::new(),
        scales: Vec::new(),
        opacities: Vec::new(),
        dc: Vec::new(),
        rest: Vec::new(),
        degree: 3,
        frame,
        features: Vec::new(),
        nf: 2,
    };
    for i in 0..n {
        let z = 2.0 + 0.5 * i as f32;
        s.means.push([rng.range_f32(-0.4, 0.4) * z / 2.0, rng.range_f32(-0.3, 0.3) * z / 2.0, z]);
        s.quats.push([
            rng.range_f32(0.5, 1.0),
            rng.range_f32(-0.5, 0.5),
            rng.range_f32(-0.5, 0.5),
            rng.range_f32(-0.5, 0.5),
        ]);
        s.scales.push([
            rng.range_f32(0.08, 0.2),
            rng.range_f32(0.08, 0.2),
            rng.range_f32(0.05, 0.2),
        ]);
        s.opacities.push(rng.range_f32(0.3, 0.7));
        s.dc.push([rng.range_f32(1.2, 1.6), rng.range_f32(1.2, 1.6), rng.range_f32(1.2, 1.6)]);
        s.rest.extend((0..45).map(|_| rng.range_f32(-0.25, 0.25)));
        s.features.extend([rng.range_f32(-1.0, 1.0), rng.range_f32(-1.0, 1.0)]);
    }
    s
}

/// L = Σ v·image over colour, alpha, depth and features, accumulated in f64.
fn loss(cam: &RenderCamera, s: &Scene, v: &ImageGrads) -> f64 {
    let (out, _) =
        CpuRenderer.render_with_saved(cam, &s.inputs(), &settings(), Cutoff::Smooth).unwrap();
    let dot =
        |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
    dot(&out.color, &v.color)
        + dot(&out.alpha, &v.alpha)
        + dot(&out.depth, &v.depth)
        + dot(&out.features, &v.features)
}

/// Both convergence indicators of one render against `pixel_pass`: `(all covered pixels
/// pass and the Gaussian is seen, the centre pixel passes)`.
fn convergence(
    cam: &RenderCamera,
    inputs: &SplatInputs,
    pixel_pass: &[bool],
) -> Result<(Vec<bool>, Vec<bool>), Error> {
    let (out, saved) = CpuRenderer.render_with_saved(cam, inputs, &settings(), Cutoff::Hard)?;
    let test = |t| CpuRenderer.convergence_saved(cam, &settings(), &saved, pixel_pass, t);
    let all = test(ConvergenceTest::AllCoveredPixels)?;
    let seen = all.iter().zip(&out.aux.n_pixels).map(|(a, n)| *a && *n > 0).collect();
    Ok((seen, test(ConvergenceTest::CentrePixel)?))
}

#[test]
fn gradients_match_finite_differences_for_every_parameter_group() {
    let cam = tilted(48, 40);
    let (w, h) = (48usize, 40usize);
    let mut rng = Rng::from_state(11);
    let mut cot = |len: usize| (0..len).map(|_| rng.range_f32(-1.0, 1.0)).collect::<Vec<f32>>();
    let v = ImageGrads {
        color: cot(w * h * 3),
        alpha: cot(w * h),
        depth: cot(w * h),
        features: cot(w * h * 2),
    };
    let mut failures = Vec::new();
    let mut checked = 0;
    for frame in [None, Some(ShFrame::World), Some(ShFrame::Local)] {
        let s = fd_scene(frame);
        let (_, saved) =
            CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Smooth).unwrap();
        let g = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &saved, &v).unwrap();
        // Case table: (param, gaussian, component, analytic, step); steps in the parameter's
        // own units, small for scale/rotation because σ at the rim moves ∝ 1/scale².
        let mut cases: Vec<(&str, usize, usize, f32, f32)> = Vec::new();
        for i in 0..s.means.len() {
            for k in 0..3 {
                cases.push(("mean", i, k, g.means[i][k], 1e-3));
                cases.push(("scale", i, k, g.scales[i][k], 2e-4));
                cases.push(("color", i, k, g.colors[i][k], 1e-3));
            }
            for k in 0..4 {
                cases.push(("quat", i, k, g.quats[i][k], 5e-4));
            }
            cases.push(("opacity", i, 0, g.opacities[i], 1e-3));
            for k in 0..2 {
                cases.push(("feature", i, k, g.features[i * 2 + k], 1e-3));
            }
            if frame.is_some() {
                for k in (0..45).step_by(4) {
                    cases.push(("sh_rest", i, k, g.sh_rest[i * 45 + k], 1e-3));
                }
            }
        }
        for (param, i, k, analytic, step) in cases {
            let bump = |d: f32| {
                let mut t = s.clone();
                match param {
                    "mean" => t.means[i][k] += d,
                    "scale" => t.scales[i][k] += d,
                    "color" => t.dc[i][k] += d,
                    "quat" => t.quats[i][k] += d,
                    "opacity" => t.opacities[i] += d,
                    "feature" => t.features[i * 2 + k] += d,
                    _ => t.rest[i * 45 + k] += d,
                }
                loss(&cam, &t, &v)
            };
            let fd = (bump(step) - bump(-step)) / (2.0 * step as f64);
            checked += 1;
            if (fd - analytic as f64).abs() > 2e-2 + 2e-2 * fd.abs() {
                failures.push(format!(
                    "{frame:?} {param}[{i}][{k}]: fd {fd:.5} vs analytic {analytic:.5}"
                ));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {checked} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The screen-space position gradient (`SplatGrads::means2d`, what density control
/// accumulates): moving the principal point by d moves every projected mean by d and
/// changes nothing else, so dL/dcx = Σ_i dL/dmean2d_x[i] (and likewise for y).
#[test]
fn screen_space_gradients_match_finite_differences_of_the_principal_point() {
    let cam = tilted(48, 40);
    let (w, h) = (48usize, 40usize);
    let mut rng = Rng::from_state(13);
    let mut cot = |len: usize| (0..len).map(|_| rng.range_f32(-1.0, 1.0)).collect::<Vec<f32>>();
    let v = ImageGrads { color: cot(w * h * 3), alpha: cot(w * h), ..ImageGrads::default() };
    let s = fd_scene(Some(ShFrame::World));
    let (_, saved) =
        CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Smooth).unwrap();
    let g = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &saved, &v).unwrap();
    assert_eq!(g.means2d.len(), s.means.len());
    for axis in 0..2 {
        let analytic: f64 = g.means2d.iter().map(|m| m[axis] as f64).sum();
        let step = 1e-2f32;
        let bump = |d: f32| {
            let mut c = cam;
            if axis == 0 {
                c.cx += d
            } else {
                c.cy += d
            }
            loss(&c, &s, &v)
        };
        let fd = (bump(step) - bump(-step)) / (2.0 * step as f64);
        assert!(
            (fd - analytic).abs() <= 1e-2 + 1e-2 * fd.abs(),
            "axis {axis}: fd {fd:.5} vs Σ means2d {analytic:.5}"
        );
        assert!(analytic.abs() > 1e-3, "axis {axis}: a vacuous check ({analytic})");
    }
}

/// Per-pixel reference without tiles: every valid splat, sorted by (depth, index).
#[test]
fn statistics_and_images_match_a_brute_force_per_pixel_reference() {
    let cam = camera(40, 30);
    let s = Scene::from_cloud(cloud(&cam, 60, 8.0, 3));
    let out = CpuRenderer.render(&cam, &s.inputs(), &settings()).unwrap();
    out.validate_counts(0, 60).unwrap();
    let splats = project(&CameraConsts::new(&cam), &s.inputs());
    let mut order: Vec<usize> = (0..60).filter(|&i| splats[i].valid).collect();
    order.sort_by(|&a, &b| splats[a].depth.total_cmp(&splats[b].depth).then(a.cmp(&b)));
    let (mut w2, mut w1, mut np) = (vec![0.0f64; 60], vec![0.0f64; 60], vec![0u32; 60]);
    for y in 0..30 {
        for x in 0..40 {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let mut t = 1.0f32;
            let mut rgb = [0.0f32; 3];
            for &g in &order {
                let Some(e) = eval_alpha(&splats[g], px, py, 0.99, Cutoff::Hard) else { continue };
                if t * (1.0 - e.alpha) <= T_THRESHOLD {
                    break;
                }
                let wgt = e.alpha * t;
                w2[g] += (wgt * wgt) as f64;
                w1[g] += wgt as f64;
                np[g] += 1;
                for c in 0..3 {
                    rgb[c] += wgt * s.dc[g][c];
                }
                t *= 1.0 - e.alpha;
            }
            let p = y * 40 + x;
            assert!((out.alpha[p] - (1.0 - t)).abs() < 1e-5);
            for c in 0..3 {
                let want = rgb[c] + t * settings().background[c];
                assert!((out.color[p * 3 + c] - want).abs() < 1e-5, "pixel ({x}, {y})");
            }
        }
    }
    assert!(np.iter().filter(|&&n| n > 0).count() > 30, "the scene must exercise many Gaussians");
    for g in 0..60 {
        assert_eq!(out.aux.n_pixels[g], np[g], "n_pixels of {g}");
        assert!((out.aux.sum_w2[g] as f64 - w2[g]).abs() < 1e-4 * (1.0 + w2[g]), "sum_w2 of {g}");
        assert!((out.aux.sum_w[g] as f64 - w1[g]).abs() < 1e-4 * (1.0 + w1[g]), "sum_w of {g}");
        assert_eq!(out.aux.visible[g], splats[g].valid);
    }
}

#[test]
fn fuzzed_inputs_are_culled_never_panic_and_leave_outputs_finite() {
    let (cam, s) = Scene::fuzzed();
    let poison: Vec<(usize, &str)> = vec![
        (0, "nan mean"),
        (1, "inf mean"),
        (2, "zero quat"),
        (3, "nan quat"),
        (4, "huge scale"),
        (5, "inf scale"),
        (6, "behind camera"),
        (7, "nan opacity"),
        (8, "huge position"),
        (9, "negative opacity"),
    ];
    let (out, saved) =
        CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    for (i, what) in &poison {
        assert!(!out.aux.visible[*i], "{what} must be culled");
        assert_eq!((out.aux.sum_w2[*i], out.aux.n_pixels[*i]), (0.0, 0), "{what}");
    }
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    assert!(
        finite(&out.color) && finite(&out.alpha) && finite(&out.depth) && finite(&out.aux.sum_w2)
    );
    let v = ImageGrads {
        color: vec![1.0; 32 * 24 * 3],
        alpha: vec![1.0; 32 * 24],
        ..ImageGrads::default()
    };
    let g = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &saved, &v).unwrap();
    assert!(g.means.iter().flatten().all(|x| x.is_finite()));
    assert!(g.quats.iter().flatten().all(|x| x.is_finite()));
    assert!(g.scales.iter().flatten().all(|x| x.is_finite()));
    assert!(finite(&g.opacities) && g.colors.iter().flatten().all(|x| x.is_finite()));
    for (i, _) in &poison {
        assert_eq!((g.means[*i], g.opacities[*i]), ([0.0; 3], 0.0));
    }
    // Bad shapes and settings are errors, not panics.
    let mut short = s.clone();
    short.opacities.pop();
    let err = CpuRenderer.render(&cam, &short.inputs(), &settings()).unwrap_err();
    assert_eq!(err.to_string(), "input 'opacities' has 19 entries, expected 20");
    let bad = RenderSettings { alpha_max: 1.0, ..settings() };
    assert!(CpuRenderer.render(&cam, &s.inputs(), &bad).is_err());
    let bad_cam = RenderCamera { fx: f32::NAN, ..cam };
    assert!(CpuRenderer.render(&bad_cam, &s.inputs(), &settings()).is_err());
}

fn to_bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn output_and_gradients_are_bit_identical_across_thread_counts() {
    let cam = camera(90, 70);
    let mut s = Scene::from_cloud(cloud(&cam, 1500, 15.0, 9));
    s.frame = Some(ShFrame::World);
    s.degree = 2;
    let mut rng = Rng::from_state(2);
    s.rest = (0..1500 * 24).map(|_| rng.range_f32(-0.1, 0.1)).collect();
    let v = ImageGrads {
        color: (0..90 * 70 * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect(),
        alpha: (0..90 * 70).map(|_| rng.range_f32(-1.0, 1.0)).collect(),
        depth: (0..90 * 70).map(|_| rng.range_f32(-1.0, 1.0)).collect(),
        features: Vec::new(),
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let (out, saved) = CpuRenderer
                .render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard)
                .unwrap();
            let g = CpuRenderer.backward(&cam, &s.inputs(), &settings(), &saved, &v).unwrap();
            let mut bits = [
                to_bits(&out.color),
                to_bits(&out.alpha),
                to_bits(&out.depth),
                to_bits(&out.aux.sum_w2),
            ]
            .concat();
            bits.extend(to_bits(&out.aux.sum_w));
            bits.extend(to_bits(&g.means.concat()));
            bits.extend(to_bits(&g.quats.concat()));
            bits.extend(to_bits(&g.scales.concat()));
            bits.extend(to_bits(&g.opacities));
            bits.extend(to_bits(&g.colors.concat()));
            bits.extend(to_bits(&g.sh_rest));
            bits
        })
    };
    let one = run(1);
    assert!(one.iter().any(|b| *b != 0));
    assert_eq!(one, run(3));
}

fn push(s: &mut Scene, mean: [f32; 3], scale: [f32; 3], opacity: f32) {
    s.means.push(mean);
    s.quats.push([0.9, 0.1, 0.2, 0.3]);
    s.scales.push(scale);
    s.opacities.push(opacity);
    s.dc.push([1.0, 0.0, 1.0]);
}

fn assert_same_images(a: &RenderOutput, b: &RenderOutput) {
    assert_eq!(to_bits(&a.color), to_bits(&b.color));
    assert_eq!(to_bits(&a.alpha), to_bits(&b.alpha));
    assert_eq!(to_bits(&a.depth), to_bits(&b.depth));
}

#[test]
fn culled_and_hidden_gaussians_do_not_change_the_image() {
    let cam = camera(48, 32);
    let base = Scene::from_cloud(cloud(&cam, 80, 6.0, 21));
    let mut culled = base.clone();
    push(&mut culled, [0.0, 0.0, -2.0], [0.2; 3], 0.9); // behind the camera
    push(&mut culled, [50.0, 0.0, 3.0], [0.2; 3], 0.9); // off-screen
    push(&mut culled, [f32::NAN, 0.0, 3.0], [0.2; 3], 0.9); // poisoned
    push(&mut culled, [0.0, 0.1, 3.0], [0.2; 3], 0.0); // transparent
    let a = CpuRenderer.render(&cam, &base.inputs(), &settings()).unwrap();
    let b = CpuRenderer.render(&cam, &culled.inputs(), &settings()).unwrap();
    assert_same_images(&a, &b);
    assert_eq!(a.aux.sum_w2[..], b.aux.sum_w2[..80]);
    assert!(b.aux.visible[80..].iter().all(|v| !v));

    // Two opaque walls in front: after them T <= 1e-4 and blending stops, so a Gaussian
    // behind them changes nothing although it is on screen.
    let mut walled = base.clone();
    push(&mut walled, [0.0, 0.0, 0.5], [50.0, 50.0, 0.01], 1.0);
    push(&mut walled, [0.0, 0.0, 0.6], [50.0, 50.0, 0.01], 1.0);
    let mut hidden = walled.clone();
    push(&mut hidden, [0.05, -0.05, 2.0], [0.2, 0.1, 0.3], 0.95);
    let c = CpuRenderer.render(&cam, &walled.inputs(), &settings()).unwrap();
    let d = CpuRenderer.render(&cam, &hidden.inputs(), &settings()).unwrap();
    assert_same_images(&c, &d);
    assert!(d.aux.visible[82] && d.aux.sum_w2[82] == 0.0, "on screen, only occluded");
    assert_ne!(to_bits(&a.color), to_bits(&c.color), "the walls do change the image");
}

#[test]
fn convergence_checks_all_covered_pixels_and_the_centre_pixel() {
    let cam = camera(64, 32);
    let consts = CameraConsts::new(&cam);
    let s = Scene {
        means: vec![[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.0, -1.0], [1.3, 0.0, 2.0]],
        quats: vec![[1.0, 0.0, 0.0, 0.0]; 4],
        scales: vec![[0.08; 3]; 4],
        opacities: vec![0.8; 4],
        dc: vec![[0.5; 3]; 4],
        rest: Vec::new(),
        degree: 0,
        frame: None,
        features: Vec::new(),
        nf: 0,
    };
    let splats = project(&consts, &s.inputs());
    assert!(
        splats[3].valid && splats[3].mean2d[0] > 64.0,
        "Gaussian 3 is centred off-screen but visible"
    );
    let mut pass = vec![true; 64 * 32];
    // Fail one pixel inside Gaussian 0's footprint, 3 px from its centre.
    let (cx, cy) = (splats[0].mean2d[0] as usize, splats[0].mean2d[1] as usize);
    pass[cy * 64 + cx + 3] = false;
    let conv = convergence(&cam, &s.inputs(), &pass).unwrap();
    assert_eq!(conv.0, vec![false, true, false, true]);
    assert_eq!(conv.1, vec![true, true, false, false]);
    pass[cy * 64 + cx] = false;
    let conv = convergence(&cam, &s.inputs(), &pass).unwrap();
    assert_eq!(conv.1, vec![false, true, false, false]);
    assert!(convergence(&cam, &s.inputs(), &pass[1..]).is_err());
}

/// The all-covered-pixels indicator computed from a finished render ([`failing_pairs`]
/// visits failing pixels only) against a per-pixel walk of the sorted Gaussians.
///
/// [`failing_pairs`]: super::cpu::forward::failing_pairs
#[test]
fn convergence_from_the_saved_render_matches_a_per_pixel_walk() {
    let (w, h) = (48usize, 36usize);
    let cam = camera(w as u32, h as u32);
    let s = Scene::from_cloud(cloud(&cam, 120, 10.0, 11));
    let mut rng = Rng::from_state(4);
    let pass: Vec<bool> = (0..w * h).map(|_| rng.uniform_f32() > 0.005).collect();
    let (out, saved) =
        CpuRenderer.render_with_saved(&cam, &s.inputs(), &settings(), Cutoff::Hard).unwrap();
    let all = CpuRenderer
        .convergence_saved(&cam, &settings(), &saved, &pass, ConvergenceTest::AllCoveredPixels)
        .unwrap();
    let splats = &saved.splats;
    let mut order: Vec<usize> = (0..120).filter(|&i| splats[i].valid).collect();
    order.sort_by(|&a, &b| splats[a].depth.total_cmp(&splats[b].depth).then(a.cmp(&b)));
    let mut want = vec![true; 120];
    for p in (0..w * h).filter(|&p| !pass[p]) {
        let (px, py) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
        let mut t = 1.0f32;
        for &g in &order {
            let Some(e) = eval_alpha(&splats[g], px, py, 0.99, Cutoff::Hard) else { continue };
            if t * (1.0 - e.alpha) <= T_THRESHOLD {
                break;
            }
            want[g] = false;
            t *= 1.0 - e.alpha;
        }
    }
    assert_eq!(all, want);
    let count =
        |ok: bool| want.iter().zip(&out.aux.n_pixels).filter(|(o, n)| **o == ok && **n > 0).count();
    let (failing, passing) = (count(false), count(true));
    assert!(failing > 5 && passing > 5, "{failing} failing, {passing} passing: weak test");
    let conv = convergence(&cam, &s.inputs(), &pass).unwrap();
    let seen: Vec<bool> = want.iter().zip(&out.aux.n_pixels).map(|(ok, n)| *ok && *n > 0).collect();
    assert_eq!(conv.0, seen);
}
