//! The tracking part of `usplat4d evaluate --model MODEL_DIR`: 3D end-point error and 3D
//! PCK of a model's Shape-of-Motion-style track predictions against a scene's ground-truth
//! tracks (formats-and-protocols.md §3.3).
//!
//! Inputs from the scene directory: `tracks_3d.parquet` (`[T][M, 3]` world positions of M
//! surface points), `tracks_2d.parquet` (their visibility in the training camera, `[T][M]`)
//! and `scene.json` (`bbox_diagonal`, the object's bounding-box diagonal in world units,
//! written by `synth`). Scores are over all ordered pairs of DyCheck's keyframes
//! (`keyframes(T, 10)`, or every frame when T < 10), with PCK thresholds at 5% and 10% of
//! the diagonal; the math is in [`crate::metrics::tracking`]. DyCheck keypoints
//! (`keypoint/2x/train/*.json`, PCK-T) are not scored here yet.

use std::path::Path;

use anyhow::Context as _;

use crate::context::Context;
use crate::metrics::tracking::{self, GtTracks3d, NUM_KEYFRAMES, PCK_3D_FRACTIONS};
use crate::model::Model;
use crate::render::CpuRenderer;
use crate::scene::Scene;
use crate::tables::{tracks_2d::Tracks2dReader, tracks_3d::Tracks3dReader};

/// The scene's ground-truth 3D tracks file.
pub const TRACKS_3D: &str = "tracks_3d.parquet";
/// The scene's ground-truth 2D tracks file (visibility in the training camera).
pub const TRACKS_2D: &str = "tracks_2d.parquet";
/// DyCheck's keypoint directory as `import dycheck` copies it.
pub const KEYPOINTS: &str = "keypoint/2x/train";

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
    /// Mean 3D end-point error, world units.
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
            "\n## 3D tracking of {} ({} tracks, {} keyframes, {} pairs, bbox diagonal {:.3})\n\n\
             | EPE | PCK@5% | PCK@10% |\n|---|---|---|\n| {:.4} | {:.3} | {:.3} |\n",
            self.model,
            self.tracks,
            self.keyframes.len(),
            self.pairs,
            self.bbox_diagonal,
            self.epe,
            self.pck_5,
            self.pck_10
        )
    }
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

/// 3D tracking scores of the model in `model_dir` on `scene`, or `None` (with a warning)
/// when the scene has no `tracks_3d.parquet`.
pub fn evaluate_tracks(
    scene: &Scene,
    model_dir: &Path,
    ctx: &Context,
) -> anyhow::Result<Option<TrackingSummary>> {
    if !scene.dir.join(TRACKS_3D).is_file() {
        if scene.dir.join(KEYPOINTS).is_dir() {
            ctx.warn(format!(
                "{}: DyCheck keypoints (PCK-T) are not scored yet; no tracking metrics",
                scene.dir.join(KEYPOINTS).display()
            ));
        } else {
            ctx.warn(format!("{} has no {TRACKS_3D}: no tracking metrics", scene.dir.display()));
        }
        return Ok(None);
    }
    let _span = tracing::info_span!("evaluate_tracks").entered();
    let gt = read_ground_truth(&scene.dir)?;
    let diag = bbox_diagonal(&scene.dir)?;
    let model = Model::load(model_dir)?;
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
    let score = tracking::track_3d(&model, scene, &gt, &keys, &CpuRenderer, diag)
        .with_context(|| format!("tracking {} on {}", model_dir.display(), scene.dir.display()))?;
    let Some(score) = score else {
        ctx.warn("no ground-truth track is visible at any keyframe: no tracking metrics");
        return Ok(None);
    };
    debug_assert_eq!(score.pck.len(), PCK_3D_FRACTIONS.len());
    Ok(Some(TrackingSummary {
        model: super::evaluate::dir_label(model_dir),
        tracks: gt.positions.first().map_or(0, Vec::len),
        keyframes: keys,
        pairs: score.pairs,
        bbox_diagonal: diag,
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
            epe: 0.01,
            pck_5: 0.5,
            pck_10: 1.0,
        };
        let md = s.markdown();
        assert!(md.contains("| 0.0100 | 0.500 | 1.000 |"), "{md}");
        assert!(md.contains("4 tracks, 2 keyframes, 4 pairs"), "{md}");
    }
}
