//! Tracking metrics: 3D end-point error and 3D PCK for synthetic scenes with ground-truth
//! tracks (thresholds relative to the object size), DyCheck's 2D PCK-T for real sequences
//! with keypoints (formats-and-protocols.md §1.5, §3.3), and the Shape-of-Motion way of
//! predicting a model's tracks.
//!
//! Prediction (SoM): for a query point seen at pixel `q` of the source frame `s`, render
//! the frame-`s` Gaussians from the frame-`s` camera with their frame-`t` positions as
//! three feature channels; the predicted frame-`t` position is the blended feature at `q`
//! divided by the blended alpha ([`predict_positions`]). Where nothing is rendered at `q`
//! the model makes no prediction.
//!
//! Scoring: per ordered frame pair only points valid in both frames count; a pair's PCK is
//! the fraction of its points predicted within the threshold (a point without a prediction
//! is a miss), its EPE the mean error over its predicted points; the final value is the
//! mean over pairs that have at least one point ([`average_pairs`]), and the points without
//! a prediction are counted. The math is in pure functions over arrays (`[M, 3]`
//! points, M tracked points) so that it is testable without a renderer; the model-level
//! drivers [`track_3d`] and [`pck_t_model`] take the ground truth in memory
//! ([`GtTracks3d`], [`GtKeypoints`]).

use glam::DVec3;

use crate::model::{FrameState, Model};
use crate::render::{ColorSource, RenderCamera, RenderSettings, Renderer, SplatInputs};
use crate::scene::Scene;

/// PCK-3D thresholds as fractions of the object's bounding-box diagonal.
pub const PCK_3D_FRACTIONS: [f64; 2] = [0.05, 0.10];
/// DyCheck PCK-T threshold as a fraction of `max(W, H)`.
pub const PCK_T_RATIO: f64 = 0.05;
/// Number of keyframes of DyCheck's and SoM's tracking protocols.
pub const NUM_KEYFRAMES: usize = 10;

/// Errors of the model-level tracking drivers.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The renderer failed.
    #[error("rendering frame {frame}: {source}")]
    Render {
        /// Source frame.
        frame: usize,
        /// The underlying error.
        source: crate::render::Error,
    },
    /// The model could not be read.
    #[error(transparent)]
    Table(#[from] crate::tables::Error),
    /// Inputs disagree (frame count, point count, missing training camera).
    #[error("{0}")]
    Mismatch(String),
}

/// Scores of one (source, target) frame pair.
#[derive(Debug, Clone, PartialEq)]
pub struct PairScore {
    /// Points valid in both frames.
    pub points: usize,
    /// Of those, the points without a prediction.
    pub unpredicted: usize,
    /// Mean end-point error over the predicted points (world units for 3D, pixels for 2D);
    /// `None` when no point was predicted.
    pub epe: Option<f64>,
    /// Fraction of points with error below each threshold (strictly).
    pub pck: Vec<f64>,
}

/// Scores averaged over pairs.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TrackingScore {
    /// Pairs with at least one valid point.
    pub pairs: usize,
    /// Valid points summed over the pairs.
    pub points: usize,
    /// Of those, the points without a prediction (misses at every threshold).
    pub unpredicted: usize,
    /// Mean over the pairs with a predicted point of the per-pair mean EPE (NaN if none).
    pub epe: f64,
    /// Mean over pairs of the per-pair PCK, one per threshold.
    pub pck: Vec<f64>,
}

/// EPE and PCK of predictions `pred` `[M, D]` (`None`: no prediction) against `gt`
/// `[M, D]` over the points with `valid[m]`; `thresholds` in the units of the points.
/// `None` when no point is valid.
pub fn score_pair<const D: usize>(
    pred: &[Option<[f32; D]>],
    gt: &[[f32; D]],
    valid: &[bool],
    thresholds: &[f64],
) -> Option<PairScore> {
    assert_eq!(pred.len(), gt.len(), "pred and gt are [M, D]");
    assert_eq!(valid.len(), gt.len(), "valid is [M]");
    let points = valid.iter().filter(|v| **v).count();
    if points == 0 {
        return None;
    }
    let errors: Vec<f64> = (0..gt.len())
        .filter(|&m| valid[m])
        .filter_map(|m| pred[m].map(|p| (p, gt[m])))
        .map(|(p, g)| (0..D).map(|d| (p[d] as f64 - g[d] as f64).powi(2)).sum::<f64>().sqrt())
        .collect();
    let n = points as f64;
    Some(PairScore {
        points,
        unpredicted: points - errors.len(),
        epe: (!errors.is_empty()).then(|| errors.iter().sum::<f64>() / errors.len() as f64),
        pck: thresholds
            .iter()
            .map(|t| errors.iter().filter(|e| **e < *t).count() as f64 / n)
            .collect(),
    })
}

/// Mean over the pairs that have points (SoM's and DyCheck's averaging); `None` if none.
pub fn average_pairs(pairs: &[Option<PairScore>]) -> Option<TrackingScore> {
    let scored: Vec<&PairScore> = pairs.iter().flatten().collect();
    let first = scored.first()?;
    let n = scored.len() as f64;
    let epes: Vec<f64> = scored.iter().filter_map(|p| p.epe).collect();
    Some(TrackingScore {
        pairs: scored.len(),
        points: scored.iter().map(|p| p.points).sum(),
        unpredicted: scored.iter().map(|p| p.unpredicted).sum(),
        epe: epes.iter().sum::<f64>() / epes.len() as f64,
        pck: (0..first.pck.len())
            .map(|k| scored.iter().map(|p| p.pck[k]).sum::<f64>() / n)
            .collect(),
    })
}

/// The 3D PCK thresholds (world units) of an object with bounding-box diagonal `diag`.
pub fn pck_3d_thresholds(diag: f64) -> Vec<f64> {
    PCK_3D_FRACTIONS.iter().map(|f| f * diag).collect()
}

/// DyCheck's PCK-T threshold, pixels: `0.05·max(W, H)`.
pub fn pck_t_threshold(width: u32, height: u32) -> f64 {
    PCK_T_RATIO * width.max(height) as f64
}

/// DyCheck's keyframes among `n` training frames: `linspace(0, n, count,
/// endpoint=False).astype(int)`.
pub fn keyframes(n: usize, count: usize) -> Vec<usize> {
    let step = n as f64 / count as f64;
    (0..count).map(|i| (i as f64 * step) as usize).collect()
}

/// Bilinear sample of channel block `[H, W, C]` at pixel coordinates `(x, y)` (pixel
/// centres at +0.5), clamped at the borders.
fn sample(img: &[f32], w: usize, h: usize, c: usize, x: f32, y: f32) -> Vec<f32> {
    let (u, v) = ((x - 0.5).clamp(0.0, (w - 1) as f32), (y - 0.5).clamp(0.0, (h - 1) as f32));
    let (x0, y0) = (u.floor() as usize, v.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (u - x0 as f32, v - y0 as f32);
    let at = |xx: usize, yy: usize, k: usize| img[(yy * w + xx) * c + k];
    (0..c)
        .map(|k| {
            let top = (1.0 - fx) * at(x0, y0, k) + fx * at(x1, y0, k);
            let bottom = (1.0 - fx) * at(x0, y1, k) + fx * at(x1, y1, k);
            (1.0 - fy) * top + fy * bottom
        })
        .collect()
}

/// SoM-style prediction: render `source` (one frame's Gaussians, `[N]` arrays) from
/// `camera` with each target frame's positions `targets[k]` `[N, 3]` (the same Gaussians
/// at target frame k) as features (`[N, 3K]`, one render for all targets), and read the
/// alpha-normalised features at each query pixel `queries` `[M, 2]` (pixel coordinates,
/// centres at +0.5, bilinear). Returns `[K][M, 3]`, `None` where nothing is rendered
/// (alpha < 1e-6): no prediction.
pub fn predict_positions(
    renderer: &dyn Renderer,
    camera: &RenderCamera,
    source: &SplatInputs,
    targets: &[&[[f32; 3]]],
    queries: &[[f32; 2]],
    settings: &RenderSettings,
) -> Result<Vec<Vec<Option<[f32; 3]>>>, crate::render::Error> {
    let n = source.means.len();
    if let Some(bad) = targets.iter().find(|t| t.len() != n) {
        return Err(crate::render::Error::Shape { name: "targets", got: bad.len(), expected: n });
    }
    let k = targets.len();
    let mut features = Vec::with_capacity(n * 3 * k);
    for g in 0..n {
        for t in targets {
            features.extend_from_slice(&t[g]);
        }
    }
    let inputs = SplatInputs { features: &features, num_features: 3 * k, ..*source };
    let out = renderer.render(camera, &inputs, settings)?;
    let (w, h) = (out.width, out.height);
    let samples: Vec<(Vec<f32>, f32)> = queries
        .iter()
        .map(|q| {
            (
                sample(&out.features, w, h, 3 * k, q[0], q[1]),
                sample(&out.alpha, w, h, 1, q[0], q[1])[0],
            )
        })
        .collect();
    Ok((0..k)
        .map(|t| {
            samples
                .iter()
                .map(|(f, a)| {
                    (*a >= 1e-6).then(|| [f[3 * t] / a, f[3 * t + 1] / a, f[3 * t + 2] / a])
                })
                .collect()
        })
        .collect())
}

/// Ground-truth 3D tracks: `positions[t]` `[M, 3]` world positions and `visible[t]` `[M]`
/// (visible in the training camera) for every training frame t.
#[derive(Debug, Clone, PartialEq)]
pub struct GtTracks3d {
    /// `[T][M, 3]`.
    pub positions: Vec<Vec<[f32; 3]>>,
    /// `[T][M]`.
    pub visible: Vec<Vec<bool>>,
}

/// Ground-truth 2D keypoints in the training camera at keyframes: `frames[k]` is keyframe
/// k's training frame, `pixels[k]` `[J, 2]` its keypoints (scene pixel coordinates,
/// centres at +0.5) and `visible[k]` `[J]` their visibility.
#[derive(Debug, Clone, PartialEq)]
pub struct GtKeypoints {
    /// `[K]` training frames.
    pub frames: Vec<usize>,
    /// `[K][J, 2]`.
    pub pixels: Vec<Vec<[f32; 2]>>,
    /// `[K][J]`.
    pub visible: Vec<Vec<bool>>,
}

/// The renderer inputs of `model` at frame state `s` (plain degree-0 colour; colour does
/// not matter for tracking).
fn splat_inputs<'a>(model: &'a Model, s: &'a FrameState) -> SplatInputs<'a> {
    SplatInputs { colors: ColorSource::Rgb(&model.gaussians.color), ..model.splat_inputs(s) }
}

/// The states of `frames` and the render camera of each (training camera at that frame).
fn keyframe_states(
    model: &Model,
    scene: &Scene,
    frames: &[usize],
) -> Result<Vec<(FrameState, RenderCamera)>, Error> {
    let train = scene.train_by_frame();
    frames
        .iter()
        .map(|&f| {
            let cam = train
                .get(f)
                .ok_or_else(|| Error::Mismatch(format!("no training camera at frame {f}")))?;
            Ok((model.frame(f)?, RenderCamera::from(&model.training_camera(cam))))
        })
        .collect()
}

/// 3D EPE and PCK (at [`PCK_3D_FRACTIONS`] of `bbox_diagonal`) of `model`'s SoM-style
/// predictions over all ordered pairs of `frames` (the source frame included as its own
/// target, as SoM's `(10·10, J, 3)` layout has it). Queries are the ground-truth points
/// projected into the source training camera; a point counts in a pair when it is visible
/// in the source frame (`gt.visible[s]`, visibility in the training camera) and projects
/// inside the source image. The target needs no visibility: the 3D target position is
/// known whether or not the training camera sees it.
pub fn track_3d(
    model: &Model,
    scene: &Scene,
    gt: &GtTracks3d,
    frames: &[usize],
    renderer: &dyn Renderer,
    bbox_diagonal: f64,
) -> Result<Option<TrackingScore>, Error> {
    let states = keyframe_states(model, scene, frames)?;
    let thresholds = pck_3d_thresholds(bbox_diagonal);
    let train = scene.train_by_frame();
    let settings = RenderSettings { background: [0.0; 3], ..RenderSettings::default() };
    let mut pairs = Vec::new();
    for (si, &s) in frames.iter().enumerate() {
        let (state, cam) = &states[si];
        let scam = train[s];
        let (gs, vs) = gt_frame(gt, s)?;
        let proj: Vec<Option<[f32; 2]>> = gs
            .iter()
            .map(|p| {
                let (x, y, _) = scam.project(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))?;
                let inside = x >= 0.0
                    && y >= 0.0
                    && x < scam.pinhole.width as f64
                    && y < scam.pinhole.height as f64;
                inside.then_some([x as f32, y as f32])
            })
            .collect();
        let queries: Vec<[f32; 2]> = proj.iter().map(|q| q.unwrap_or([0.0; 2])).collect();
        let targets: Vec<&[[f32; 3]]> =
            states.iter().map(|(st, _)| st.position.as_slice()).collect();
        let preds = predict_positions(
            renderer,
            cam,
            &splat_inputs(model, state),
            &targets,
            &queries,
            &settings,
        )
        .map_err(|source| Error::Render { frame: s, source })?;
        for (&t, pred) in frames.iter().zip(&preds) {
            let (gt_t, _) = gt_frame(gt, t)?;
            let valid: Vec<bool> = (0..gs.len()).map(|m| vs[m] && proj[m].is_some()).collect();
            pairs.push(score_pair(pred, gt_t, &valid, &thresholds));
        }
    }
    Ok(average_pairs(&pairs))
}

fn gt_frame(gt: &GtTracks3d, t: usize) -> Result<(&[[f32; 3]], &[bool]), Error> {
    match (gt.positions.get(t), gt.visible.get(t)) {
        (Some(p), Some(v)) if p.len() == v.len() => Ok((p, v)),
        _ => Err(Error::Mismatch(format!(
            "ground-truth tracks have no frame {t} (or its arrays disagree)"
        ))),
    }
}

/// DyCheck's PCK-T of `model` (formats-and-protocols.md §3.3): for every ordered pair
/// (s, t) of distinct keyframes of `gt` (90 pairs for 10 keyframes, as MoSca's packs;
/// DyCheck's own loop also scores the 10 pairs s = t), the keypoints visible in both are
/// queried at their ground-truth source pixels, predicted SoM-style at frame t, projected
/// into the frame-t training camera and counted correct within `0.05·max(W, H)` of the
/// ground-truth target pixel. Pairs without common keypoints are skipped; the score is the
/// mean over pairs of the per-pair fraction (EPE in pixels alongside).
pub fn pck_t_model(
    model: &Model,
    scene: &Scene,
    gt: &GtKeypoints,
    renderer: &dyn Renderer,
) -> Result<Option<TrackingScore>, Error> {
    let k = gt.frames.len();
    let j = gt.pixels.first().map_or(0, Vec::len);
    if gt.pixels.len() != k
        || gt.visible.len() != k
        || gt.pixels.iter().zip(&gt.visible).any(|(p, v)| p.len() != j || v.len() != j)
    {
        return Err(Error::Mismatch(format!(
            "ground-truth keypoints: {k} frames but {} pixel and {} visibility lists, or a \
             keyframe without {j} keypoints",
            gt.pixels.len(),
            gt.visible.len()
        )));
    }
    let states = keyframe_states(model, scene, &gt.frames)?;
    let train = scene.train_by_frame();
    let settings = RenderSettings { background: [0.0; 3], ..RenderSettings::default() };
    let targets: Vec<&[[f32; 3]]> = states.iter().map(|(st, _)| st.position.as_slice()).collect();
    let mut pairs = Vec::new();
    for (si, &s) in gt.frames.iter().enumerate() {
        let (ps, vs) = (&gt.pixels[si], &gt.visible[si]);
        let (state, cam) = &states[si];
        let preds =
            predict_positions(renderer, cam, &splat_inputs(model, state), &targets, ps, &settings)
                .map_err(|source| Error::Render { frame: s, source })?;
        for (ti, pred3) in preds.iter().enumerate() {
            if ti == si {
                continue;
            }
            let (pt, vt) = (&gt.pixels[ti], &gt.visible[ti]);
            let tcam = train[gt.frames[ti]];
            // No pixel without a 3D prediction, nor for one behind the target camera.
            let pred: Vec<Option<[f32; 2]>> = pred3
                .iter()
                .map(|p| {
                    let p = p.as_ref()?;
                    let (x, y, _) =
                        tcam.project(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))?;
                    Some([x as f32, y as f32])
                })
                .collect();
            let valid: Vec<bool> = (0..j).map(|m| vs[m] && vt[m]).collect();
            pairs.push(score_pair(
                &pred,
                pt,
                &valid,
                &[pck_t_threshold(tcam.pinhole.width, tcam.pinhole.height)],
            ));
        }
    }
    Ok(average_pairs(&pairs))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::RenderOutput;

    #[test]
    fn epe_and_pck_on_hand_made_points() {
        let gt = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [5.0, 5.0, 5.0]];
        let mut pred =
            [[0.0, 0.0, 0.3], [1.0, 0.04, 0.0], [0.0, 2.0, 0.1], [0.0, 0.0, 0.0]].map(Some);
        // Point 3 is invalid: errors 0.3, 0.04, 0.1.
        let s = score_pair(&pred, &gt, &[true, true, true, false], &[0.05, 0.1, 0.2]).unwrap();
        assert_eq!((s.points, s.unpredicted), (3, 0));
        assert!((s.epe.unwrap() - 0.44 / 3.0).abs() < 1e-6, "{s:?}");
        // 0.1 is not strictly below the 0.1 threshold (f32 rounding aside it is ~0.1).
        assert_eq!(s.pck[0], 1.0 / 3.0);
        assert_eq!(s.pck[2], 2.0 / 3.0);
        assert_eq!(score_pair(&pred, &gt, &[false; 4], &[0.1]), None);
        // A point without a prediction misses every threshold and leaves the EPE mean.
        pred[1] = None;
        let s = score_pair(&pred, &gt, &[true, true, true, false], &[0.05, 0.2]).unwrap();
        assert!((s.epe.unwrap() - 0.2).abs() < 1e-6, "{s:?}");
        assert_eq!((s.points, s.unpredicted, s.pck), (3, 1, vec![0.0, 1.0 / 3.0]));
        let none = score_pair(&[None::<[f32; 2]>], &[[0.0; 2]], &[true], &[1.0]).unwrap();
        assert_eq!((none.unpredicted, none.epe, none.pck), (1, None, vec![0.0]));
    }

    #[test]
    fn pairs_without_points_are_skipped() {
        let a = PairScore { points: 2, unpredicted: 0, epe: Some(1.0), pck: vec![0.5, 1.0] };
        let b = PairScore { points: 7, unpredicted: 1, epe: Some(3.0), pck: vec![0.0, 0.5] };
        let c = PairScore { points: 1, unpredicted: 1, epe: None, pck: vec![0.0, 0.0] };
        let s = average_pairs(&[Some(a), None, Some(b), Some(c)]).unwrap();
        let want = TrackingScore {
            pairs: 3,
            points: 10,
            unpredicted: 2,
            epe: 2.0,
            pck: vec![0.5 / 3.0, 1.5 / 3.0],
        };
        assert_eq!(s, want);
        assert_eq!(average_pairs(&[None, None]), None);
    }

    #[test]
    fn pck_t_threshold_and_keyframes_follow_dycheck() {
        assert_eq!(pck_t_threshold(360, 480), 24.0);
        assert_eq!(pck_t_threshold(720, 960), 48.0);
        // numpy: linspace(0, 277, 10, endpoint=False).astype(int)
        assert_eq!(keyframes(277, 10), [0, 27, 55, 83, 110, 138, 166, 193, 221, 249]);
        assert_eq!(keyframes(10, 10), (0..10).collect::<Vec<_>>());
        let gt = [[100.0, 100.0], [10.0, 10.0]];
        let pred = [[123.9, 100.0], [34.0, 10.0]].map(Some);
        let s = score_pair(&pred, &gt, &[true, true], &[pck_t_threshold(360, 480)]).unwrap();
        assert_eq!(s.pck, [0.5]);
    }

    /// A renderer whose feature image is the first Gaussian's features times a left-to-right
    /// alpha ramp, to check the feature layout, the read-out and the normalisation.
    struct Ramp;

    impl Renderer for Ramp {
        fn render(
            &self,
            c: &RenderCamera,
            i: &SplatInputs,
            _s: &RenderSettings,
        ) -> Result<RenderOutput, crate::render::Error> {
            let (w, h) = (c.width as usize, c.height as usize);
            let f = i.num_features;
            let mut out = RenderOutput { width: w, height: h, ..Default::default() };
            for _y in 0..h {
                for x in 0..w {
                    let a = x as f32 / (w - 1) as f32;
                    out.alpha.push(a);
                    out.features.extend(i.features[..f].iter().map(|v| v * a));
                }
            }
            Ok(out)
        }
    }

    #[test]
    fn prediction_reads_alpha_normalised_target_positions() {
        let cam = RenderCamera {
            fx: 10.0,
            fy: 10.0,
            cx: 4.0,
            cy: 3.0,
            w2c: glam::Mat4::IDENTITY,
            width: 8,
            height: 6,
            near: 0.01,
            far: 100.0,
        };
        let means = [[0.0, 0.0, 1.0]];
        let inputs = SplatInputs {
            means: &means,
            quats: &[[1.0, 0.0, 0.0, 0.0]],
            scales: &[[0.1; 3]],
            opacities: &[1.0],
            colors: ColorSource::Rgb(&[[0.5; 3]]),
            features: &[],
            num_features: 0,
        };
        let (t0, t1) = ([[1.0, -2.0, 3.0]], [[0.5, 0.25, -4.0]]);
        let queries = [[4.5, 2.5], [0.5, 0.5]];
        let got = predict_positions(
            &Ramp,
            &cam,
            &inputs,
            &[&t0, &t1],
            &queries,
            &RenderSettings::default(),
        )
        .unwrap();
        assert_eq!(got.len(), 2);
        for (pred, want) in got.iter().zip([t0[0], t1[0]]) {
            let p = pred[0].unwrap();
            assert!(p.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "{got:?}");
            // Alpha is 0 in the first column: no prediction.
            assert_eq!(pred[1], None);
        }
        let e = predict_positions(&Ramp, &cam, &inputs, &[&[]], &[], &RenderSettings::default())
            .unwrap_err();
        assert_eq!(e.to_string(), "input 'targets' has 0 entries, expected 1");
    }
}
