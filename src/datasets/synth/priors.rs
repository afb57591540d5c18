//! Realistic priors: the depth maps and 2D tracks a monocular pipeline would get from
//! foundation models, made from the exact ones by a seeded error model.
//!
//! Depth (what Depth Anything / UniDepth give after per-frame alignment), per training frame:
//! 1. edge bleeding: a normalised Gaussian blur (σ = `depth_edge_px`) over the valid
//!    foreground pixels, which turns depth discontinuities inside the object into ramps of
//!    flying pixels;
//! 2. noise: `d · (1 + depth_noise · (0.8·n_smooth + 0.6·n_pixel))`, `n_smooth` a standard
//!    normal field on a grid of 1/8 of the image size interpolated bilinearly (the errors of
//!    depth networks are mostly smooth), `n_pixel` i.i.d. per pixel;
//! 3. a per-frame affine error: `s_t · d + b_t · median(d)` with `log s_t ~ N(0,
//!    depth_scale_error²)` and `b_t ~ N(0, depth_shift_error²)` (monocular depth is only
//!    known up to a per-frame scale and shift).
//!
//! Pixels outside the object stay 0 (invalid).
//!
//! Tracks (what TAPIR / CoTracker / BootsTAP give), per track over the video:
//! - visibility: every change between visible and occluded is moved by a uniform shift in
//!   `-visibility_lag..=visibility_lag` frames (trackers are late and early at occlusion
//!   boundaries), then every label flips with probability `visibility_flip`;
//! - position: the true projection plus i.i.d. `N(0, track_noise_px²)` per axis, plus an
//!   offset that random-walks (`track_drift_px` per axis and frame) while the point is
//!   occluded. Most tracks re-lock when the point reappears (the offset resets); a fraction
//!   `track_drift_fraction` of the tracks keep it (they re-attached to the wrong surface)
//!   and drift further at every occlusion;
//! - tracks that are never visible stay invisible (a tracker is only queried on points it
//!   has seen), and a prior position outside the image is not visible.
//!
//! Every random draw comes from a stream keyed by (seed, frame) or (seed, track), so the
//! priors are deterministic whatever the thread count.

use glam::Vec2;

use crate::tables::tracks_2d::Tracks2dFrame;
use crate::util::rng::{Rng, mix as splitmix64};

/// Which priors `synth` writes beside the exact data.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum PriorKind {
    /// The monocular inputs are the exact depth and tracks.
    None,
    /// Depth and tracks with the error model of this module.
    Realistic,
}

/// Error levels of the realistic priors (see the module doc and README for the sources).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Levels {
    /// σ of the log of the per-frame depth scale.
    pub depth_scale_error: f64,
    /// σ of the per-frame depth shift, in units of the frame's median depth.
    pub depth_shift_error: f64,
    /// σ of the relative depth noise.
    pub depth_noise: f64,
    /// σ of the edge-bleeding blur, pixels.
    pub depth_edge_px: f64,
    /// σ of the track position noise per axis, pixels.
    pub track_noise_px: f64,
    /// Fraction of tracks that keep their drift after an occlusion.
    pub track_drift_fraction: f64,
    /// σ per axis and occluded frame of the drift random walk, pixels.
    pub track_drift_px: f64,
    /// Largest shift of a visibility change, frames.
    pub visibility_lag: u32,
    /// Probability that a visibility label flips.
    pub visibility_flip: f64,
}

/// Errors of the written priors against the exact data (recorded in `priors.json`).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Measured {
    /// Mean |d' − d| / d over the valid pixels of all training frames.
    pub depth_abs_rel: f64,
    /// TAP-Vid's < δ^x_avg: the fraction of truly visible points within 1, 2, 4, 8, 16 px
    /// (at 256×256), averaged over the thresholds.
    pub track_delta_avg: f64,
    /// TAP-Vid's occlusion accuracy over the tracks seen at least once.
    pub occlusion_accuracy: f64,
    /// Tracks that keep their drift.
    pub drifting_tracks: usize,
}

fn normal(rng: &mut Rng) -> f64 {
    let u1 = 1.0 - rng.uniform();
    let u2 = rng.uniform();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn stream(seed: u64, kind: u64, index: u64) -> Rng {
    Rng::from_state(splitmix64(splitmix64(seed ^ kind) ^ index))
}

/// The depth prior `[H, W]` of one training frame from its exact depth `[H, W]` (0 = invalid).
pub fn depth_prior(
    depth: &[f32],
    width: usize,
    height: usize,
    frame: u32,
    seed: u64,
    lv: &Levels,
) -> Vec<f32> {
    let mut rng = stream(seed, 0xD3_97, frame as u64);
    let bled = bleed(depth, width, height, lv.depth_edge_px);
    // Smooth noise: a coarse grid of normals, bilinear.
    let cell = (width.max(height) as f64 / 8.0).max(1.0);
    let (gw, gh) =
        ((width as f64 / cell).ceil() as usize + 2, (height as f64 / cell).ceil() as usize + 2);
    let grid: Vec<f64> = (0..gw * gh).map(|_| normal(&mut rng)).collect();
    let s_t = (lv.depth_scale_error * normal(&mut rng)).exp();
    let b_t = lv.depth_shift_error * normal(&mut rng);
    let mut valid: Vec<f32> = depth.iter().copied().filter(|&d| d > 0.0).collect();
    valid.sort_by(f32::total_cmp);
    let median = valid.get(valid.len() / 2).copied().unwrap_or(0.0) as f64;
    let mut out = vec![0.0f32; depth.len()];
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            let pixel_noise = normal(&mut rng);
            if depth[i] <= 0.0 {
                continue;
            }
            let (gx, gy) = ((x as f64 + 0.5) / cell, (y as f64 + 0.5) / cell);
            let (x0, y0) = (gx.floor() as usize, gy.floor() as usize);
            let (fx, fy) = (gx - x0 as f64, gy - y0 as f64);
            let g = |a: usize, b: usize| grid[b.min(gh - 1) * gw + a.min(gw - 1)];
            let smooth = (1.0 - fy) * ((1.0 - fx) * g(x0, y0) + fx * g(x0 + 1, y0))
                + fy * ((1.0 - fx) * g(x0, y0 + 1) + fx * g(x0 + 1, y0 + 1));
            let d = bled[i] as f64 * (1.0 + lv.depth_noise * (0.8 * smooth + 0.6 * pixel_noise));
            out[i] = (s_t * d + b_t * median).max(1e-3 * median) as f32;
        }
    }
    out
}

/// Normalised Gaussian blur of the valid (> 0) values; invalid pixels stay 0.
fn bleed(depth: &[f32], width: usize, height: usize, sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return depth.to_vec();
    }
    let r = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f64> =
        (-r..=r).map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let pass = |src_v: &[f64], src_w: &[f64], horizontal: bool| -> (Vec<f64>, Vec<f64>) {
        let (mut v, mut w) = (vec![0.0; src_v.len()], vec![0.0; src_v.len()]);
        for y in 0..height as isize {
            for x in 0..width as isize {
                let (mut sv, mut sw) = (0.0, 0.0);
                for (j, k) in kernel.iter().enumerate() {
                    let d = j as isize - r;
                    let (xx, yy) = if horizontal { (x + d, y) } else { (x, y + d) };
                    if xx < 0 || yy < 0 || xx >= width as isize || yy >= height as isize {
                        continue;
                    }
                    let i = (yy * width as isize + xx) as usize;
                    sv += k * src_v[i];
                    sw += k * src_w[i];
                }
                let i = (y * width as isize + x) as usize;
                (v[i], w[i]) = (sv, sw);
            }
        }
        (v, w)
    };
    let w0: Vec<f64> = depth.iter().map(|&d| f64::from(u8::from(d > 0.0))).collect();
    let v0: Vec<f64> = depth.iter().map(|&d| if d > 0.0 { d as f64 } else { 0.0 }).collect();
    let (v1, w1) = pass(&v0, &w0, true);
    let (v2, w2) = pass(&v1, &w1, false);
    (0..depth.len())
        .map(|i| if depth[i] > 0.0 && w2[i] > 0.0 { (v2[i] / w2[i]) as f32 } else { 0.0 })
        .collect()
}

/// The tracks prior `[T]` of the exact tracks `[T]` (M tracks each) of a `width`×`height`
/// training video; also the number of drifting tracks.
pub fn track_priors(
    exact: &[Tracks2dFrame],
    width: usize,
    height: usize,
    seed: u64,
    lv: &Levels,
) -> (Vec<Tracks2dFrame>, usize) {
    let tn = exact.len();
    let m = exact.first().map_or(0, |f| f.xy.len());
    let mut out: Vec<Tracks2dFrame> =
        (0..tn).map(|_| Tracks2dFrame { xy: vec![[0.0; 2]; m], visible: vec![false; m] }).collect();
    let mut drifting = 0;
    for j in 0..m {
        let mut rng = stream(seed, 0x7AC5, j as u64);
        let truth: Vec<bool> = (0..tn).map(|t| exact[t].visible[j]).collect();
        let drifts = rng.uniform() < lv.track_drift_fraction;
        let seen = truth.iter().any(|&v| v);
        drifting += usize::from(drifts && seen);
        let vis = if seen { shifted_visibility(&truth, lv, &mut rng) } else { truth.clone() };
        let mut offset = Vec2::ZERO;
        for t in 0..tn {
            let occluded = !truth[t];
            if occluded {
                offset += lv.track_drift_px as f32
                    * Vec2::new(normal(&mut rng) as f32, normal(&mut rng) as f32);
            } else if t > 0 && !truth[t - 1] && !drifts {
                offset = Vec2::ZERO;
            }
            let noise = lv.track_noise_px as f32
                * Vec2::new(normal(&mut rng) as f32, normal(&mut rng) as f32);
            let [x, y] = exact[t].xy[j];
            let p =
                if x < 0.0 && y < 0.0 { Vec2::new(x, y) } else { Vec2::new(x, y) + offset + noise };
            let inside = p.x >= 0.0 && p.y >= 0.0 && p.x < width as f32 && p.y < height as f32;
            out[t].xy[j] = p.to_array();
            out[t].visible[j] = vis[t] && inside && x >= 0.0;
        }
    }
    (out, drifting)
}

/// Visibility `[T]` with every change moved by up to `visibility_lag` frames and labels
/// flipped with probability `visibility_flip`.
fn shifted_visibility(truth: &[bool], lv: &Levels, rng: &mut Rng) -> Vec<bool> {
    let tn = truth.len();
    // Run boundaries: frames where the label changes.
    let bounds: Vec<usize> = (1..tn).filter(|&t| truth[t] != truth[t - 1]).collect();
    let lag = lv.visibility_lag as i64;
    let mut moved = Vec::with_capacity(bounds.len());
    for (i, &b) in bounds.iter().enumerate() {
        let shift = (rng.next_u64() % (2 * lag as u64 + 1)) as i64 - lag;
        let lo = moved.last().map_or(1, |&p: &usize| p + 1) as i64;
        let hi = bounds.get(i + 1).map_or(tn as i64 - 1, |&n| n as i64 - 1);
        moved.push((b as i64 + shift).clamp(lo, hi.max(lo)) as usize);
    }
    let mut vis = Vec::with_capacity(tn);
    let (mut state, mut next) = (truth.first().copied().unwrap_or(false), 0);
    for t in 0..tn {
        while next < moved.len() && moved[next] == t {
            state = !state;
            next += 1;
        }
        let flip = rng.uniform() < lv.visibility_flip;
        vis.push(state ^ flip);
    }
    vis
}

/// TAP-Vid's position accuracy and occlusion accuracy of `prior` against `exact`.
pub fn track_errors(
    exact: &[Tracks2dFrame],
    prior: &[Tracks2dFrame],
    width: usize,
    height: usize,
) -> (f64, f64) {
    let m = exact.first().map_or(0, |f| f.xy.len());
    let seen: Vec<bool> = (0..m).map(|j| exact.iter().any(|f| f.visible[j])).collect();
    let (sx, sy) = (256.0 / width as f64, 256.0 / height as f64);
    let (mut within, mut visible, mut agree, mut labels) = (0.0, 0usize, 0usize, 0usize);
    for (e, p) in exact.iter().zip(prior) {
        for j in 0..m {
            if !seen[j] {
                continue;
            }
            labels += 1;
            agree += usize::from(e.visible[j] == p.visible[j]);
            if e.visible[j] {
                visible += 1;
                let dx = (p.xy[j][0] - e.xy[j][0]) as f64 * sx;
                let dy = (p.xy[j][1] - e.xy[j][1]) as f64 * sy;
                let d = (dx * dx + dy * dy).sqrt();
                within +=
                    [1.0, 2.0, 4.0, 8.0, 16.0].iter().filter(|&&r| d < r).count() as f64 / 5.0;
            }
        }
    }
    (within / visible.max(1) as f64, agree as f64 / labels.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    const LV: Levels = Levels {
        depth_scale_error: 0.0,
        depth_shift_error: 0.0,
        depth_noise: 0.0,
        depth_edge_px: 1.0,
        track_noise_px: 1.0,
        track_drift_fraction: 0.5,
        track_drift_px: 2.0,
        visibility_lag: 2,
        visibility_flip: 0.0,
    };

    #[test]
    fn bleeding_ramps_a_step_and_keeps_the_background() {
        // A 10x1 strip: depth 1 then depth 3, with one invalid pixel at the end.
        let mut d = vec![1.0f32; 5];
        d.extend([3.0, 3.0, 3.0, 3.0, 0.0]);
        let out = depth_prior(&d, 10, 1, 0, 7, &LV);
        assert_eq!(out[9], 0.0, "invalid stays invalid");
        assert!((out[0] - 1.0).abs() < 0.01 && (out[7] - 3.0).abs() < 0.2, "{out:?}");
        assert!(out[4] > 1.2 && out[5] < 2.8, "the step is bled: {out:?}");
        assert_eq!(out, depth_prior(&d, 10, 1, 0, 7, &LV), "deterministic");
    }

    #[test]
    fn visibility_changes_move_by_at_most_the_lag() {
        let truth: Vec<bool> = (0..40).map(|t| (10..25).contains(&t)).collect();
        for s in 0..20 {
            let v = shifted_visibility(&truth, &LV, &mut Rng::from_state(s));
            let on: Vec<usize> = (0..40).filter(|&t| v[t]).collect();
            let (a, b) = (on[0], *on.last().unwrap());
            assert!((8..=12).contains(&a) && (22..=26).contains(&b), "{a}..{b}");
            assert_eq!(on.len(), b - a + 1, "still one visible run");
        }
    }

    #[test]
    fn tracks_keep_never_seen_points_hidden_and_measure_their_error() {
        let exact: Vec<Tracks2dFrame> = (0..30)
            .map(|t| Tracks2dFrame {
                xy: vec![[20.0 + t as f32, 30.0], [5.0, 5.0]],
                visible: vec![!(10..20).contains(&t), false],
            })
            .collect();
        let (prior, drifting) = track_priors(&exact, 64, 64, 3, &LV);
        assert!(prior.iter().all(|f| !f.visible[1]));
        assert!(drifting <= 1);
        let (delta, oa) = track_errors(&exact, &prior, 64, 64);
        assert!(delta > 0.3 && delta < 1.0, "{delta}");
        assert!(oa > 0.7 && oa <= 1.0, "{oa}");
        let (d0, oa0) = track_errors(&exact, &exact, 64, 64);
        assert_eq!((d0, oa0), (1.0, 1.0));
    }
}
