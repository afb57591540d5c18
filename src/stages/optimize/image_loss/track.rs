//! The 2D track term of L_rgb, as Shape of Motion and MoSca train it: render the source
//! frame with each Gaussian's TARGET-frame position in the target camera's coordinates as
//! three feature channels ([`write_target_features`]), read the rendered feature at each
//! tracked source pixel, project it with the target camera's intrinsics and compare with
//! the tracked target pixel. Gradients go to the feature image, and from the renderer's
//! per-Gaussian feature gradient back to the target-frame positions
//! ([`add_target_position_grads`]).
//!
//! Why 3D camera-space features and not projected 2D ones (both base models do this): the
//! renderer blends features without normalising by alpha, and the projection
//! `u = fx·X/Z + cx` is invariant to scaling (X, Y, Z), so partially covered pixels need no
//! division by alpha; the per-pixel projection is part of this loss and the per-Gaussian
//! chain rule is only the target camera's rotation Rᵀ.
//!
//! Read-out: the pixel that contains the source position (nearest pixel: floor of the
//! coordinates, pixel centres at +0.5), as both base models fetch one pixel (SoM's query
//! pixels are on the grid, MoSca truncates); tracks outside the image are skipped, as are
//! pixels whose rendered Z is ≤ 1e-4 (MoSca's filter; SoM clamps Z at 1e-6 and its trimming
//! drops those outliers).
//!
//! Error per track ([`TrackForm`]): Shape of Motion's L1 (mean over u, v), weighted
//! (confidence × exp(−2|s − t|/T)), trimmed at the 0.98 quantile and divided by max(H, W);
//! or MoSca's Euclidean pixel error clamped at 100 px, averaged.

use glam::{Mat3, Vec3};

use crate::render::RenderCamera;
use crate::stages::optimize::sign;
use crate::tables::tracks_2d::Tracks2dFrame;

/// Rendered camera-space Z at or below which a track is skipped.
pub const MIN_Z: f32 = 1e-4;

/// One 2D track between the rendered (source) frame and a target frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Track {
    /// Pixel position in the source frame (pixel centres at +0.5).
    pub source: [f32; 2],
    /// Pixel position in the target frame.
    pub target: [f32; 2],
    /// Weight (confidence × interval weight for Shape of Motion; 1 for MoSca).
    pub weight: f32,
}

/// The tracks from the rendered frame to one target frame, whose camera-space positions
/// are feature block `block` (channels `3·block .. 3·block + 3`).
#[derive(Debug, Clone, Copy)]
pub struct TrackSet<'a> {
    /// Feature block of this target frame.
    pub block: usize,
    /// The target frame's camera (its intrinsics project the rendered positions).
    pub camera: &'a RenderCamera,
    /// The tracks.
    pub tracks: &'a [Track],
}

/// How per-track errors become the loss.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrackForm {
    /// Shape of Motion: `mean(|Δu|, |Δv|)` per track, weighted mean over the tracks below
    /// the `trim_quantile` quantile of the errors (0.98; 1 keeps all), divided by max(H, W).
    Som {
        /// Quantile above which errors are dropped (torch.quantile, linear).
        trim_quantile: f64,
    },
    /// MoSca: `min(‖Δ‖₂, clamp_px)` per track, weighted mean (weights 1 in MoSca).
    Mosca {
        /// Clamp of the pixel error (100).
        clamp_px: f64,
    },
}

/// Shape of Motion's weight of a track between frames `s` and `t` of `T`: exp(−2|s − t|/T).
pub fn interval_weight(s: usize, t: usize, num_frames: usize) -> f32 {
    (-2.0 * s.abs_diff(t) as f64 / num_frames.max(1) as f64).exp() as f32
}

/// The tracks visible in both `source` and `target` (rows of the `tracks_2d` table with the
/// same `track_id`), each with weight `weight`.
pub fn tracks_between(source: &Tracks2dFrame, target: &Tracks2dFrame, weight: f32) -> Vec<Track> {
    source
        .xy
        .iter()
        .zip(&source.visible)
        .zip(target.xy.iter().zip(&target.visible))
        .filter(|((_, vs), (_, vt))| **vs && **vt)
        .map(|((s, _), (t, _))| Track { source: *s, target: *t, weight })
        .collect()
}

/// Write the target frame's positions `positions` `[N, 3]` (world) in the coordinates of
/// `target` (its w2c) into block `block` of `features` `[N, F]`.
pub fn write_target_features(
    features: &mut [f32],
    num_features: usize,
    block: usize,
    positions: &[[f32; 3]],
    target: &RenderCamera,
) {
    assert!(3 * block + 3 <= num_features, "block {block} does not fit in {num_features}");
    assert_eq!(features.len(), positions.len() * num_features, "features are [N, F]");
    for (f, p) in features.chunks_exact_mut(num_features).zip(positions) {
        let c = target.w2c.transform_point3(Vec3::from_array(*p));
        f[3 * block..3 * block + 3].copy_from_slice(&c.to_array());
    }
}

/// Add to `grads` `[N, 3]` the gradient w.r.t. the world positions written by
/// [`write_target_features`] into block `block`, from `dfeatures` `[N, F]` (the renderer's
/// `SplatGrads::features`): `Rᵀ·g` with R the rotation of the target's w2c.
pub fn add_target_position_grads(
    grads: &mut [[f32; 3]],
    dfeatures: &[f32],
    num_features: usize,
    block: usize,
    target: &RenderCamera,
) {
    assert_eq!(dfeatures.len(), grads.len() * num_features, "feature gradients are [N, F]");
    let rt = Mat3::from_mat4(target.w2c).transpose();
    for (g, d) in grads.iter_mut().zip(dfeatures.chunks_exact(num_features)) {
        let v = rt * Vec3::from_slice(&d[3 * block..3 * block + 3]);
        for k in 0..3 {
            g[k] += v[k];
        }
    }
}

/// One track's read-out: the pixel's feature index and its projection.
struct Sample {
    /// Index of the block's first channel in the feature image.
    at: usize,
    /// Rendered camera-space position.
    xyz: [f64; 3],
    /// Residual (u, v) − target, pixels.
    res: [f64; 2],
    /// Intrinsics fx, fy of the target camera.
    f: [f64; 2],
    weight: f64,
}

/// The track loss of the feature image `features` `[H, W, F]` (W×H pixels, F =
/// `num_features`) over every set in `sets`, pooled; with `grad = Some((g, scale))` adds
/// `scale · dL/dfeatures` to `g` (`[H, W, F]`). Zero when no track is usable.
pub fn track_with_grad(
    features: &[f32],
    (w, h): (usize, usize),
    num_features: usize,
    sets: &[TrackSet],
    form: TrackForm,
    grad: Option<(&mut [f32], f64)>,
) -> f64 {
    assert_eq!(features.len(), w * h * num_features, "features are [H, W, F]");
    let mut samples = Vec::new();
    for set in sets {
        assert!(3 * set.block + 3 <= num_features, "block {} beyond F", set.block);
        let cam = set.camera;
        for t in set.tracks {
            let (x, y) = (t.source[0].floor(), t.source[1].floor());
            if !(x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h) {
                continue;
            }
            let at = (y as usize * w + x as usize) * num_features + 3 * set.block;
            let xyz = [0, 1, 2].map(|k| features[at + k] as f64);
            if xyz[2] <= MIN_Z as f64 {
                continue;
            }
            let u = cam.fx as f64 * xyz[0] / xyz[2] + cam.cx as f64;
            let v = cam.fy as f64 * xyz[1] / xyz[2] + cam.cy as f64;
            samples.push(Sample {
                at,
                xyz,
                res: [u - t.target[0] as f64, v - t.target[1] as f64],
                f: [cam.fx as f64, cam.fy as f64],
                weight: t.weight as f64,
            });
        }
    }
    // Per track: error and d error / d residual.
    let per: Vec<(f64, [f64; 2])> = samples
        .iter()
        .map(|s| match form {
            TrackForm::Som { .. } => {
                (0.5 * (s.res[0].abs() + s.res[1].abs()), s.res.map(|r| 0.5 * sign(r)))
            }
            TrackForm::Mosca { clamp_px } => {
                let n = s.res[0].hypot(s.res[1]);
                if n < clamp_px && n > 0.0 {
                    (n, s.res.map(|r| r / n))
                } else {
                    (n.min(clamp_px), [0.0; 2])
                }
            }
        })
        .collect();
    let keep: Vec<bool> = match form {
        TrackForm::Som { trim_quantile } if trim_quantile < 1.0 && !per.is_empty() => {
            let q = quantile(per.iter().map(|p| p.0).collect(), trim_quantile);
            per.iter().map(|p| p.0 < q).collect()
        }
        _ => vec![true; per.len()],
    };
    let total_w: f64 = samples.iter().zip(&keep).filter(|(_, k)| **k).map(|(s, _)| s.weight).sum();
    let (denom, norm) = match form {
        // SoM: Σ w·e / (Σ w + 1e-8) / max(H, W).
        TrackForm::Som { .. } => (total_w + 1e-8, 1.0 / w.max(h) as f64),
        TrackForm::Mosca { .. } if total_w > 0.0 => (total_w, 1.0),
        TrackForm::Mosca { .. } => return 0.0,
    };
    let k = norm / denom;
    let loss: f64 = samples
        .iter()
        .zip(&per)
        .zip(&keep)
        .filter(|(_, k)| **k)
        .map(|((s, p), _)| s.weight * p.0)
        .sum::<f64>()
        * k;
    if let Some((g, scale)) = grad {
        for ((s, p), _) in samples.iter().zip(&per).zip(&keep).filter(|(_, k)| **k) {
            let c = scale * k * s.weight;
            let [x, y, z] = s.xyz;
            let (du, dv) = (c * p.1[0], c * p.1[1]);
            // u = fx·X/Z + cx, v = fy·Y/Z + cy.
            g[s.at] += (du * s.f[0] / z) as f32;
            g[s.at + 1] += (dv * s.f[1] / z) as f32;
            g[s.at + 2] -= ((du * s.f[0] * x + dv * s.f[1] * y) / (z * z)) as f32;
        }
    }
    loss
}

/// The `q` quantile of `v` with linear interpolation (torch.quantile's default).
fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    v[lo] + (pos - lo as f64) * (v[hi] - v[lo])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::optimize::image_loss::fd::{Check, noise};
    use glam::{Mat4, Quat};

    fn camera(w: u32, h: u32) -> RenderCamera {
        let w2c = Mat4::from_rotation_translation(
            Quat::from_euler(glam::EulerRot::XYZ, 0.2, -0.3, 0.1),
            Vec3::new(0.1, -0.2, 3.0),
        );
        RenderCamera {
            fx: 20.0,
            fy: 22.0,
            cx: w as f32 / 2.0,
            cy: h as f32 / 2.0,
            w2c,
            width: w,
            height: h,
            near: 0.01,
            far: 100.0,
        }
    }

    /// A feature image `[H, W, 6]` of two blocks of plausible camera-space positions.
    fn feature_image(w: usize, h: usize) -> Vec<f32> {
        let r = noise(w * h * 6, 61);
        r.chunks_exact(3).flat_map(|c| [c[0] - 0.5, c[1] - 0.5, 2.0 + c[2]]).collect()
    }

    fn tracks(n: usize, w: usize, h: usize, seed: u64) -> Vec<Track> {
        let r = noise(5 * n, seed);
        r.chunks_exact(5)
            .map(|c| Track {
                source: [c[0] * w as f32, c[1] * h as f32],
                target: [c[2] * w as f32, c[3] * h as f32],
                weight: 0.25 + c[4],
            })
            .collect()
    }

    #[test]
    fn feature_image_gradient_matches_finite_differences() {
        let (w, h) = (8, 7);
        let feats = feature_image(w, h);
        let cams = [camera(w as u32, h as u32), camera(w as u32, h as u32)];
        let (t0, t1) = (tracks(12, w, h, 62), tracks(9, w, h, 63));
        let sets = [
            TrackSet { block: 0, camera: &cams[0], tracks: &t0 },
            TrackSet { block: 1, camera: &cams[1], tracks: &t1 },
        ];
        let mut check = Check::new("track features", 1e-6, 2e-3);
        for form in [TrackForm::Som { trim_quantile: 0.9 }, TrackForm::Mosca { clamp_px: 3.0 }] {
            let mut g = vec![0.0f32; feats.len()];
            let l = track_with_grad(&feats, (w, h), 6, &sets, form, Some((&mut g, 1.0)));
            assert!(l > 0.0);
            let loss = |f: &[f32]| track_with_grad(f, (w, h), 6, &sets, form, None);
            check.image(&format!("{form:?}"), &feats, &g, 1.0 / 4096.0, loss, 1);
            // Some tracks were clamped or trimmed, so both branches are exercised.
            assert!(g.iter().any(|v| *v != 0.0));
        }
        check.finish();
    }

    /// The chain from world positions through the per-Gaussian features to the loss: a
    /// stand-in "renderer" puts Gaussian i's features at pixel i, so dL/dfeatures `[N, F]`
    /// is the feature image's gradient, which [`add_target_position_grads`] maps back.
    #[test]
    fn position_chain_matches_finite_differences() {
        let (w, h) = (5, 4);
        let n = w * h;
        let cam = camera(w as u32, h as u32);
        let positions: Vec<[f32; 3]> = noise(3 * n, 71)
            .chunks_exact(3)
            .map(|c| [c[0] - 0.5, c[1] - 0.5, c[2] - 0.5])
            .collect();
        let tr: Vec<Track> = (0..n)
            .map(|i| Track {
                source: [(i % w) as f32 + 0.5, (i / w) as f32 + 0.5],
                target: [(i * 7 % w) as f32, (i * 3 % h) as f32 + 1.0],
                weight: 1.0,
            })
            .collect();
        let form = TrackForm::Som { trim_quantile: 1.0 };
        let loss = |p: &[[f32; 3]]| -> (f64, Vec<f32>) {
            let mut f = vec![0.0f32; n * 3];
            write_target_features(&mut f, 3, 0, p, &cam);
            let sets = [TrackSet { block: 0, camera: &cam, tracks: &tr }];
            let mut g = vec![0.0f32; n * 3];
            let l = track_with_grad(&f, (w, h), 3, &sets, form, Some((&mut g, 1.0)));
            (l, g)
        };
        let (_, dfeat) = loss(&positions);
        let mut grads = vec![[0.0f32; 3]; n];
        add_target_position_grads(&mut grads, &dfeat, 3, 0, &cam);
        // Features are f32 (camera-space transform rounding ~1e-7 relative): abs 2e-5.
        let mut check = Check::new("track positions", 2e-5, 2e-3);
        let eps = 1.0 / 4096.0;
        for i in 0..n {
            for k in 0..3 {
                let mut p = positions.clone();
                p[i][k] += eps;
                let lp = loss(&p).0;
                p[i][k] -= 2.0 * eps;
                let lm = loss(&p).0;
                check.compare(
                    &format!("gaussian {i} axis {k}"),
                    grads[i][k] as f64,
                    (lp - lm) / (2.0 * eps as f64),
                );
            }
        }
        check.finish();
    }

    #[test]
    fn exact_positions_cost_nothing_and_forms_match_their_definitions() {
        let (w, h) = (6, 5);
        let cam = camera(w as u32, h as u32);
        // One Gaussian per pixel whose target projection is known.
        let feats = feature_image(w, h);
        let f3: Vec<f32> = feats.chunks_exact(6).flat_map(|c| [c[0], c[1], c[2]]).collect();
        let project = |i: usize| {
            let c = &f3[3 * i..3 * i + 3];
            [cam.fx * c[0] / c[2] + cam.cx, cam.fy * c[1] / c[2] + cam.cy]
        };
        let exact: Vec<Track> = (0..w * h)
            .map(|i| Track {
                source: [(i % w) as f32 + 0.3, (i / w) as f32 + 0.9],
                target: project(i),
                weight: 1.0,
            })
            .collect();
        let set = [TrackSet { block: 0, camera: &cam, tracks: &exact }];
        let som = TrackForm::Som { trim_quantile: 0.98 };
        assert!(track_with_grad(&f3, (w, h), 3, &set, som, None) < 1e-5);
        // Shift every target by (3, 4) px: SoM 3.5/max(H, W); MoSca 5 (clamped at 4.5).
        let shifted: Vec<Track> = exact
            .iter()
            .map(|t| Track { target: [t.target[0] - 3.0, t.target[1] - 4.0], ..*t })
            .collect();
        let set = [TrackSet { block: 0, camera: &cam, tracks: &shifted }];
        let all = TrackForm::Som { trim_quantile: 1.0 };
        let s = track_with_grad(&f3, (w, h), 3, &set, all, None);
        assert!((s - 3.5 / 6.0).abs() < 1e-4, "{s}");
        let m = track_with_grad(&f3, (w, h), 3, &set, TrackForm::Mosca { clamp_px: 100.0 }, None);
        assert!((m - 5.0).abs() < 1e-4, "{m}");
        let c = track_with_grad(&f3, (w, h), 3, &set, TrackForm::Mosca { clamp_px: 4.5 }, None);
        assert!((c - 4.5).abs() < 1e-9, "{c}");
    }

    #[test]
    fn tracks_between_keeps_tracks_visible_in_both_frames() {
        let s = Tracks2dFrame {
            xy: vec![[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]],
            visible: vec![true, true, false],
        };
        let t = Tracks2dFrame {
            xy: vec![[7.0, 8.0], [9.0, 1.0], [2.0, 3.0]],
            visible: vec![false, true, true],
        };
        let w = interval_weight(3, 13, 20);
        assert!((w - (-1.0f32).exp()).abs() < 1e-7);
        assert_eq!(
            tracks_between(&s, &t, w),
            vec![Track { source: [3.0, 4.0], target: [9.0, 1.0], weight: w }]
        );
    }

    #[test]
    fn quantile_interpolates_like_torch() {
        assert_eq!(quantile(vec![4.0, 1.0, 3.0, 2.0], 0.5), 2.5);
        assert_eq!(quantile(vec![0.0, 10.0], 0.98), 9.8);
        assert_eq!(quantile(vec![7.0], 0.98), 7.0);
    }
}
