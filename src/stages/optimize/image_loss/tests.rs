//! Tests of [`rgb_loss`]: every image cotangent against central differences of the summed
//! terms, for both profiles, and which terms appear when.

use super::fd::{Check, noise};
use super::*;
use crate::render::RenderCamera;

const W: usize = 12;
const H: usize = 11;

/// A plausible render `[H, W]`: colour, alpha in [0.3, 1], expected depth α·z with z in
/// [1, 3], and one feature block of camera-space positions (Z in [2, 3]).
fn render() -> RenderOutput {
    let n = W * H;
    let alpha: Vec<f32> = noise(n, 81).iter().map(|v| 0.25 + 0.75 * v).collect();
    let depth = noise(n, 82).iter().zip(&alpha).map(|(z, a)| (1.0 + 2.0 * z) * a).collect();
    let features = noise(3 * n, 83)
        .chunks_exact(3)
        .flat_map(|c| [c[0] - 0.5, c[1] - 0.5, 2.0 + c[2]])
        .collect();
    RenderOutput {
        width: W,
        height: H,
        color: noise(3 * n, 84),
        features,
        alpha,
        depth,
        aux: Default::default(),
    }
}

fn camera() -> RenderCamera {
    RenderCamera {
        fx: 15.0,
        fy: 15.0,
        cx: W as f32 / 2.0,
        cy: H as f32 / 2.0,
        w2c: glam::Mat4::IDENTITY,
        width: W as u32,
        height: H as u32,
        near: 0.01,
        far: 100.0,
    }
}

struct Truth {
    rgb: Vec<f32>,
    mask: Vec<f32>,
    depth: Vec<f32>,
    tracks: Vec<Track>,
}

fn truth(out: &RenderOutput) -> Truth {
    let n = W * H;
    // Colour differences kept away from the |·| kink (≥ 4 steps of 1/1024).
    let rgb = noise(3 * n, 85)
        .iter()
        .zip(&out.color)
        .map(|(q, p)| if (q - p).abs() < 4.0 / 1024.0 { (p + 0.25) % 1.0 } else { *q })
        .collect();
    let mask = (0..n).map(|i| if (i % W) < 8 { 1.0 } else { 0.0 }).collect();
    let depth = noise(n, 86)
        .iter()
        .enumerate()
        .map(|(i, v)| if i % 13 == 0 { 0.0 } else { 1.0 + v })
        .collect();
    let tracks = noise(5 * 15, 87)
        .chunks_exact(5)
        .map(|c| Track {
            source: [c[0] * W as f32, c[1] * H as f32],
            target: [c[2] * W as f32, c[3] * H as f32],
            weight: 0.5 + c[4],
        })
        .collect();
    Truth { rgb, mask, depth, tracks }
}

#[test]
fn every_image_cotangent_matches_finite_differences() {
    let out = render();
    let t = truth(&out);
    let cam = camera();
    let sets = [TrackSet { block: 0, camera: &cam, tracks: &t.tracks }];
    let targets = FrameTargets {
        rgb: &t.rgb,
        valid: None,
        mask: Some(&t.mask),
        depth: Some(&t.depth),
        tracks: &sets,
    };
    let mut check = Check::new("rgb_loss", 2e-6, 3e-3);
    for profile in [Profile::Paper, Profile::Release] {
        let mut weights = ImageLossWeights::defaults(profile);
        // The release's mask weight is 0; turn it on to check its cotangent in both forms.
        weights.mask = 0.7;
        let (terms, g) = rgb_loss(&out, &targets, &weights).unwrap();
        assert_eq!(terms.iter().map(|t| t.0).collect::<Vec<_>>(), TERMS);
        let total = |o: &RenderOutput| -> f64 {
            rgb_loss(o, &targets, &weights).unwrap().0.iter().map(|t| t.1).sum()
        };
        let eps = 1.0 / (1 << 14) as f32;
        let cotangents = [&g.color, &g.alpha, &g.depth, &g.features];
        for (k, grad) in cotangents.into_iter().enumerate() {
            let loss = |v: &[f32]| {
                let mut p = out.clone();
                *image(&mut p, k) = v.to_vec();
                total(&p)
            };
            let x = image(&mut out.clone(), k).clone();
            check.image(&format!("{profile:?} {}", NAMES[k]), &x, grad, eps, loss, 3);
        }
    }
    check.finish();
}

/// The images of a render, in [`image`]'s order.
const NAMES: [&str; 4] = ["color", "alpha", "depth", "features"];

/// Image `k` of `o` (order of [`NAMES`]).
fn image(o: &mut RenderOutput, k: usize) -> &mut Vec<f32> {
    match k {
        0 => &mut o.color,
        1 => &mut o.alpha,
        2 => &mut o.depth,
        _ => &mut o.features,
    }
}

#[test]
fn terms_appear_only_with_their_prior_and_weight() {
    let out = render();
    let t = truth(&out);
    let bare = FrameTargets { rgb: &t.rgb, valid: None, mask: None, depth: None, tracks: &[] };
    let release = ImageLossWeights::defaults(Profile::Release);
    let (terms, g) = rgb_loss(&out, &bare, &release).unwrap();
    assert_eq!(terms.iter().map(|t| t.0).collect::<Vec<_>>(), ["rgb"]);
    assert!(g.alpha.is_empty() && g.depth.is_empty() && g.features.is_empty());
    // A mask but weight 0 (release): no mask term.
    let masked = FrameTargets { mask: Some(&t.mask), ..bare };
    let (terms, _) = rgb_loss(&out, &masked, &release).unwrap();
    assert_eq!(terms.len(), 1);
    let (terms, g) = rgb_loss(&out, &masked, &ImageLossWeights::defaults(Profile::Paper)).unwrap();
    assert_eq!(terms.iter().map(|t| t.0).collect::<Vec<_>>(), ["rgb", "mask"]);
    assert!(!g.alpha.is_empty() && g.depth.is_empty());
}

#[test]
fn mismatched_inputs_are_errors() {
    let out = render();
    let t = truth(&out);
    let short = &t.mask[1..];
    let bad =
        FrameTargets { rgb: &t.rgb, valid: None, mask: Some(short), depth: None, tracks: &[] };
    let e = rgb_loss(&out, &bad, &ImageLossWeights::defaults(Profile::Paper)).unwrap_err();
    assert_eq!(e.to_string(), "image loss: 'mask' has 131 values, expected 132 (render is 12x11)");
    let cam = camera();
    let sets = [TrackSet { block: 1, camera: &cam, tracks: &t.tracks }];
    let bad = FrameTargets { rgb: &t.rgb, valid: None, mask: None, depth: None, tracks: &sets };
    let e = rgb_loss(&out, &bad, &ImageLossWeights::defaults(Profile::Paper)).unwrap_err();
    assert_eq!(e.to_string(), "image loss: track feature block 1 needs 6 channels, render has 3");
}
