//! The tracking part of `usplat4d evaluate --model MODEL_DIR`: 3D end-point error and 3D
//! PCK of a model's Shape-of-Motion-style track predictions against a scene's ground-truth
//! tracks, and DyCheck's 2D PCK-T against its keypoints (formats-and-protocols.md §1.5,
//! §3.3). The math is in [`crate::metrics::tracking`].
//!
//! 3D tracks (synthetic scenes): `tracks_3d.parquet` (`[T][M, 3]` world positions of M
//! surface points), `tracks_2d.parquet` (their visibility in the training camera, `[T][M]`)
//! and `scene.json` (`bbox_diagonal`, the object's bounding-box diagonal in world units,
//! written by `synth`). Scores are over all ordered pairs of DyCheck's keyframes
//! (`keyframes(T, 10)`, or every frame when T < 10), with PCK thresholds at 5% and 10% of
//! the diagonal.
//!
//! PCK-T (scenes from `import dycheck` with keypoints): the keypoint files that
//! `scene.json` maps to training frames (`keypoints.frames`), converted to scene pixels at
//! the import factor ([`crate::datasets::dycheck::read_scene_keypoints`]); every ordered
//! pair of distinct keyframes, keypoints visible in both, correct within
//! `0.05·max(W, H)` pixels.

use std::path::Path;

use anyhow::Context as _;

use crate::context::Context;
use crate::datasets::dycheck::{KEYPOINT_DIR, SceneKeypoints, read_scene_keypoints};
use crate::metrics::tracking::{self, GtKeypoints, GtTracks3d, NUM_KEYFRAMES, PCK_3D_FRACTIONS};
use crate::model::Model;
use crate::scene::Scene;
use crate::tables::{tracks_2d::Tracks2dReader, tracks_3d::Tracks3dReader};
use crate::util::fs::dir_label;

/// The scene's ground-truth 3D tracks file.
pub const TRACKS_3D: &str = "tracks_3d.parquet";
/// The scene's ground-truth 2D tracks file (visibility in the training camera).
pub const TRACKS_2D: &str = "tracks_2d.parquet";

/// 3D tracking scores of one model on one scene.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TrackingSummary {
    /// Model directory label.
    pub model: String,
    /// Number of ground-truth tracks M.
    pub tracks: usize,
    /// Keyframes (training frame indices) whose ordered pairs are scored.
    pub keyframes: Vec<usize>,
    /// Ordered pairs with at least one valid point.
    pub pairs: usize,
    /// Object bounding-box diagonal, world units.
    pub bbox_diagonal: f64,
    /// Scored points summed over the pairs.
    pub points: usize,
    /// Of those, the points where the model renders nothing at the query pixel (no
    /// prediction: a miss at both PCK thresholds, left out of the EPE).
    pub unpredicted: usize,
    /// Mean 3D end-point error over the predicted points, world units.
    pub epe: f64,
    /// 3D PCK at 5% of the diagonal.
    pub pck_5: f64,
    /// 3D PCK at 10% of the diagonal.
    pub pck_10: f64,
}

impl TrackingSummary {
    /// The scores as a Markdown section.
    pub fn markdown(&self) -> String {
        format!(
            "\n## 3D tracking of {} ({} tracks, {} keyframes, {} pairs, {} points, {} without a \
             prediction, bbox diagonal {:.3})\n\n\
             | EPE | PCK@5% | PCK@10% |\n|---|---|---|\n| {:.4} | {:.3} | {:.3} |\n",
            self.model,
            self.tracks,
            self.keyframes.len(),
            self.pairs,
            self.points,
            self.unpredicted,
            self.bbox_diagonal,
            self.epe,
            self.pck_5,
            self.pck_10
        )
    }
}

/// DyCheck PCK-T of one model on one scene.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PckTSummary {
    /// Model directory label.
    pub model: String,
    /// Keypoints per keyframe J.
    pub keypoints: usize,
    /// Keyframes (training frame indices) with keypoint files.
    pub keyframes: Vec<usize>,
    /// Ordered pairs of distinct keyframes with at least one keypoint visible in both.
    pub pairs: usize,
    /// Keypoints scored, summed over those pairs.
    pub points: usize,
    /// Of those, the keypoints without a predicted pixel (nothing rendered at the source
    /// pixel, or a prediction behind the target camera): misses, left out of the EPE.
    pub unpredicted: usize,
    /// Correctness threshold `0.05·max(W, H)`, scene pixels (first keyframe's camera).
    pub threshold_px: f64,
    /// Mean over pairs of the fraction of correct keypoints.
    pub pck_t: f64,
    /// Mean over pairs of the mean end-point error of the predicted keypoints, scene pixels.
    pub epe_px: f64,
}

impl PckTSummary {
    /// The scores as a Markdown section.
    pub fn markdown(&self) -> String {
        format!(
            "\n## PCK-T of {} ({} keypoints, {} keyframes, {} pairs, {} points, {} without a \
             prediction, threshold {:.1} px)\n\n| PCK-T | EPE (px) |\n|---|---|\n| {:.3} | \
             {:.2} |\n",
            self.model,
            self.keypoints,
            self.keyframes.len(),
            self.pairs,
            self.points,
            self.unpredicted,
            self.threshold_px,
            self.pck_t,
            self.epe_px
        )
    }
}

/// What `evaluate --model` scores: 3D tracking and PCK-T, each when the scene has its
/// ground truth.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ModelScores {
    /// 3D tracking (scenes with `tracks_3d.parquet`).
    pub tracking: Option<TrackingSummary>,
    /// PCK-T (scenes with DyCheck keypoints).
    pub pck_t: Option<PckTSummary>,
}

/// Tracking scores of the model in `model_dir` on `scene`: 3D tracking when the scene has
/// `tracks_3d.parquet`, PCK-T when its `scene.json` records keypoints; a warning and no
/// scores when it has neither.
pub fn evaluate_model(
    scene: &Scene,
    model_dir: &Path,
    ctx: &Context,
) -> anyhow::Result<ModelScores> {
    let has_tracks = scene.dir.join(TRACKS_3D).is_file();
    let keypoints = read_scene_keypoints(&scene.dir)?;
    if !has_tracks && keypoints.is_none() {
        ctx.warn(format!(
            "{} has neither {TRACKS_3D} nor DyCheck keypoints ({KEYPOINT_DIR}): no tracking \
             metrics",
            scene.dir.display()
        ));
        return Ok(ModelScores::default());
    }
    let model = Model::load(model_dir)?;
    let mut scores = ModelScores::default();
    if has_tracks {
        scores.tracking = evaluate_tracks(scene, &model, model_dir, ctx)?;
    }
    if let Some(k) = keypoints {
        scores.pck_t = evaluate_pck_t(scene, &model, model_dir, k, ctx)?;
    }
    Ok(scores)
}

/// PCK-T of `model` against the scene's keypoints `k`, or `None` (with a warning) when no
/// pair of keyframes shares a visible keypoint.
fn evaluate_pck_t(
    scene: &Scene,
    model: &Model,
    model_dir: &Path,
    k: SceneKeypoints,
    ctx: &Context,
) -> anyhow::Result<Option<PckTSummary>> {
    let _span = tracing::info_span!("evaluate_pck_t").entered();
    let train = scene.train_by_frame();
    for (name, &f) in k.names.iter().zip(&k.frames) {
        if f >= model.num_frames() || f >= train.len() {
            anyhow::bail!(
                "keypoint file {name}.json is at frame {f}, but {} has {} frames and {} has {} \
                 training frames",
                Model::trajectories_path(model_dir).display(),
                model.num_frames(),
                scene.dir.display(),
                train.len()
            );
        }
    }
    let threshold_px = k.frames.first().map_or(f64::NAN, |&f| {
        tracking::pck_t_threshold(train[f].pinhole.width, train[f].pinhole.height)
    });
    let keypoints = k.pixels.first().map_or(0, Vec::len);
    let gt = GtKeypoints { frames: k.frames, pixels: k.pixels, visible: k.visible };
    let score = tracking::pck_t_model(model, scene, &gt, &crate::stages::device::renderer(ctx)?)
        .with_context(|| format!("PCK-T of {} on {}", model_dir.display(), scene.dir.display()))?;
    let Some(score) = score else {
        ctx.warn("no two keyframes share a visible keypoint: no PCK-T");
        return Ok(None);
    };
    Ok(Some(PckTSummary {
        model: dir_label(model_dir),
        keypoints,
        keyframes: gt.frames,
        pairs: score.pairs,
        points: score.points,
        unpredicted: score.unpredicted,
        threshold_px,
        pck_t: score.pck[0],
        epe_px: score.epe,
    }))
}

/// The `bbox_diagonal` key of `SCENE/scene.json`.
fn bbox_diagonal(scene_dir: &Path) -> anyhow::Result<f64> {
    let path = scene_dir.join("scene.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    match json.get("bbox_diagonal").and_then(serde_json::Value::as_f64) {
        Some(d) if d.is_finite() && d > 0.0 => Ok(d),
        _ => anyhow::bail!(
            "{}: key 'bbox_diagonal' missing or not a positive number",
            path.display()
        ),
    }
}

/// Ground-truth tracks of the scene: 3D positions, and visibility from `tracks_2d`.
fn read_ground_truth(scene_dir: &Path) -> anyhow::Result<GtTracks3d> {
    let p3 = scene_dir.join(TRACKS_3D);
    let p2 = scene_dir.join(TRACKS_2D);
    let r3 = Tracks3dReader::open(&p3)?;
    let r2 = Tracks2dReader::open(&p2)?;
    if (r3.num_frames(), r3.num_tracks()) != (r2.num_frames(), r2.num_tracks()) {
        anyhow::bail!(
            "{} has {} frames × {} tracks, {} has {} × {}",
            p3.display(),
            r3.num_frames(),
            r3.num_tracks(),
            p2.display(),
            r2.num_frames(),
            r2.num_tracks()
        );
    }
    let mut gt = GtTracks3d { positions: Vec::new(), visible: Vec::new() };
    for t in 0..r3.num_frames() {
        gt.positions.push(r3.frame(t)?);
        gt.visible.push(r2.frame(t)?.visible);
    }
    Ok(gt)
}

/// 3D tracking scores of `model` (from `model_dir`) on `scene`, which has
/// `tracks_3d.parquet`; `None` (with a warning) when no track is visible at a keyframe.
fn evaluate_tracks(
    scene: &Scene,
    model: &Model,
    model_dir: &Path,
    ctx: &Context,
) -> anyhow::Result<Option<TrackingSummary>> {
    let _span = tracing::info_span!("evaluate_tracks").entered();
    let gt = read_ground_truth(&scene.dir)?;
    let diag = bbox_diagonal(&scene.dir)?;
    let frames = gt.positions.len();
    if model.num_frames() != frames {
        anyhow::bail!(
            "{} has {} frames, {} has {frames}",
            Model::trajectories_path(model_dir).display(),
            model.num_frames(),
            scene.dir.join(TRACKS_3D).display()
        );
    }
    let keys = tracking::keyframes(frames, NUM_KEYFRAMES.min(frames));
    let score =
        tracking::track_3d(model, scene, &gt, &keys, &crate::stages::device::renderer(ctx)?, diag)
            .with_context(|| {
                format!("tracking {} on {}", model_dir.display(), scene.dir.display())
            })?;
    let Some(score) = score else {
        ctx.warn("no ground-truth track is visible at any keyframe: no tracking metrics");
        return Ok(None);
    };
    debug_assert_eq!(score.pck.len(), PCK_3D_FRACTIONS.len());
    Ok(Some(TrackingSummary {
        model: dir_label(model_dir),
        tracks: gt.positions.first().map_or(0, Vec::len),
        keyframes: keys,
        pairs: score.pairs,
        bbox_diagonal: diag,
        points: score.points,
        unpredicted: score.unpredicted,
        epe: score.epe,
        pck_5: score.pck[0],
        pck_10: score.pck[1],
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bbox_diagonal_is_read_and_checked() {
        let dir = std::env::temp_dir().join(format!("usplat4d-evtracks-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("scene.json"), r#"{"bbox_diagonal": 2.0}"#).unwrap();
        assert_eq!(bbox_diagonal(&dir).unwrap(), 2.0);
        std::fs::write(dir.join("scene.json"), r#"{"bbox_diagonal": -1}"#).unwrap();
        let e = bbox_diagonal(&dir).unwrap_err().to_string();
        assert!(e.contains("scene.json") && e.contains("bbox_diagonal"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn markdown_names_the_scores() {
        let s = TrackingSummary {
            model: "m".into(),
            tracks: 4,
            keyframes: vec![0, 1],
            pairs: 4,
            bbox_diagonal: 2.0,
            points: 30,
            unpredicted: 2,
            epe: 0.01,
            pck_5: 0.5,
            pck_10: 1.0,
        };
        let md = s.markdown();
        assert!(md.contains("| 0.0100 | 0.500 | 1.000 |"), "{md}");
        assert!(md.contains("4 tracks, 2 keyframes, 4 pairs, 30 points, 2 without a prediction"));
    }

    #[test]
    fn pck_t_markdown_names_pairs_and_points() {
        let s = PckTSummary {
            model: "m".into(),
            keypoints: 16,
            keyframes: (0..10).collect(),
            pairs: 90,
            points: 1400,
            unpredicted: 0,
            threshold_px: 24.0,
            pck_t: 0.9875,
            epe_px: 1.234,
        };
        let md = s.markdown();
        assert!(md.contains("| PCK-T | EPE (px) |\n|---|---|\n| 0.988 | 1.23 |"), "{md}");
        assert!(
            md.contains(
                "(16 keypoints, 10 keyframes, 90 pairs, 1400 points, 0 without a prediction, \
                 threshold 24.0 px)"
            ),
            "{md}"
        );
    }
}
