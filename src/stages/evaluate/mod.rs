//! `usplat4d evaluate`: image metrics of rendered views against a scene's eval images, and
//! `evaluate --compare` of two such evaluations.
//!
//! Each eval camera of the scene is paired with `RENDERS/<camera.image_path>`. Both images
//! are composited over white and quantised to 8 bits (DyCheck's `to_quantized_float32`),
//! then PSNR, SSIM and LPIPS are computed per image ([`crate::metrics`]). Cameras with a
//! horizontal angle offset (the synthetic benchmark) are scored on the full image and
//! summarised by the view ranges of the paper's Table 2 — (0°, 60°], (60°, 120°],
//! (120°, 180°], offsets above 180° counted as 360° − offset. Cameras without an offset
//! but with a mask (DyCheck-like validation views) are scored with the masked protocol
//! (mPSNR, mSSIM, mLPIPS over the covisibility mask). Every summary value is the mean of
//! the per-image values.
//!
//! With `--model MODEL_DIR`, the model's tracking scores are added to the summary
//! ([`tracks`]): 3D EPE and PCK at 5% and 10% of the bbox diagonal on a
//! scene with ground-truth tracks, DyCheck's PCK-T (with the numbers of pairs and
//! keypoints scored) on a scene with DyCheck keypoints.
//!
//! Outputs in `OUT/`: `metrics.parquet` (one row per image, scene camera order),
//! `summary.json` and `summary.md` (also printed).

pub mod compare;
pub mod tracks;

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use rayon::prelude::*;

use crate::context::Context;
use crate::formats;
use crate::metrics::lpips::{Lpips, WeightsError};
use crate::metrics::{psnr::psnr, ssim::ssim};
use crate::scene::{Camera, Scene};
use crate::tables::{Provenance, Table, metrics::MetricRow, metrics::MetricsTable};
use crate::util::fs::dir_label;
use tracks::{PckTSummary, TrackingSummary};

/// Whether LPIPS is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum LpipsMode {
    /// Compute LPIPS when the weights are installed; otherwise warn and leave it null.
    #[default]
    Auto,
    /// Never compute LPIPS.
    Off,
    /// Fail when the weights are not installed.
    Require,
}

/// Which eval cameras use their masks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskMode {
    /// Masked metrics for cameras that have a mask and no angle offset (DyCheck-like
    /// validation views); full-image metrics otherwise.
    #[default]
    Auto,
    /// Masked metrics for every camera that has a mask.
    Always,
    /// Full-image metrics everywhere.
    Never,
}

/// Parameters of `usplat4d evaluate`.
#[derive(Debug, Clone, Default, clap::Args, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct EvaluateParams {
    /// Directory of rendered images, laid out like the scene (`DIR/<camera image_path>`).
    #[arg(long, value_name = "DIR", required_unless_present = "compare")]
    pub renders: Option<PathBuf>,
    /// The scene directory with the ground-truth eval images.
    #[arg(long, value_name = "SCENE_DIR", required_unless_present = "compare")]
    pub scene: Option<PathBuf>,
    /// Method label stored in the table (default: the name of the renders directory).
    #[arg(long, value_name = "LABEL")]
    pub method: Option<String>,
    /// Output directory for metrics.parquet, summary.json and summary.md.
    #[arg(long, value_name = "DIR", required_unless_present = "compare")]
    pub out: Option<PathBuf>,
    /// Exit with status 1 when the mean PSNR over all images is below this value (dB).
    #[arg(long, value_name = "PSNR", value_parser = crate::stages::params::check::finite)]
    pub fail_below: Option<f64>,
    /// LPIPS: auto (when installed), off, or require.
    #[arg(long, value_enum, default_value_t = LpipsMode::Auto)]
    pub lpips: LpipsMode,
    /// Masked (DyCheck) metrics: auto, always or never.
    #[arg(long, value_enum, default_value_t = MaskMode::Auto)]
    pub masks: MaskMode,
    /// Model directory whose tracks are scored against the scene's ground-truth tracks
    /// (3D EPE and PCK) and DyCheck keypoints (PCK-T); skipped with a warning when the
    /// scene has neither.
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: Option<PathBuf>,
    /// Instead of evaluating, print evaluations side by side with their differences to the
    /// first, tracking included (output directories of `evaluate` or their metrics files).
    #[arg(long, num_args = 2.., value_names = ["A", "B"], conflicts_with_all = ["renders", "scene", "out", "fail_below", "model"])]
    pub compare: Option<Vec<PathBuf>>,
    /// Score the eval views (default) or the training views (how well a model fits its
    /// input video; no per-view-range rows).
    #[arg(long, value_enum, default_value_t = EvalSplit::Eval)]
    pub split: EvalSplit,
}

/// The views `evaluate` scores.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum EvalSplit {
    /// The held-out evaluation views.
    #[default]
    Eval,
    /// The training video.
    Train,
}

/// Run the stage.
pub fn run(p: &EvaluateParams, ctx: &Context) -> anyhow::Result<()> {
    if let Some(paths) = &p.compare {
        print!("{}", compare::compare(paths)?);
        return Ok(());
    }
    let (Some(renders), Some(scene_dir), Some(out)) = (&p.renders, &p.scene, &p.out) else {
        anyhow::bail!("evaluate needs --renders, --scene and --out (or --compare A B)");
    };
    let _span = tracing::info_span!("evaluate").entered();
    let mut scene = Scene::load(scene_dir)?;
    // Tracking renders the training cameras' frames: score it before the split is applied,
    // and before any output is written, so a failure leaves no partial evaluation.
    let tracking = match &p.model {
        Some(model) => Some(tracks::evaluate_model(&scene, model, ctx)?),
        None => None,
    };
    if p.split == EvalSplit::Train {
        // The training views, scored like eval views (offset 0: in no view range).
        scene.cameras.retain(|c| c.split == crate::scene::Split::Train);
        for c in &mut scene.cameras {
            c.split = crate::scene::Split::Eval;
        }
    }
    let method = p.method.clone().unwrap_or_else(|| dir_label(renders));
    let lpips = match p.lpips {
        LpipsMode::Off => None,
        LpipsMode::Require => Some(Lpips::load_default()?),
        LpipsMode::Auto => match Lpips::load_default() {
            Ok(l) => Some(l),
            Err(e @ WeightsError::Missing { .. }) => {
                ctx.warn(format!("{e}; the lpips column stays null"));
                None
            }
            Err(e) => return Err(e.into()),
        },
    };
    let rows = evaluate_images(&scene, renders, &method, lpips.as_ref(), p.masks, ctx)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    crate::tables::metrics::write(
        &out.join(MetricsTable::file_name()),
        &rows,
        &Provenance::new("evaluate", p),
    )?;
    let mut summary = summarise(&rows);
    if let Some(scores) = tracking {
        (summary.tracking, summary.pck_t) = (scores.tracking, scores.pck_t);
    }
    let json = serde_json::to_string_pretty(&summary).context("serialising the summary")?;
    crate::util::fs::write_atomic(&out.join("summary.json"), format!("{json}\n").as_bytes())?;
    let md = summary.markdown();
    crate::util::fs::write_atomic(&out.join("summary.md"), md.as_bytes())?;
    print!("{md}");
    if let Some(min) = p.fail_below {
        let all = summary.groups.last().map_or(f64::NAN, |g| g.psnr);
        if all.is_nan() || all < min {
            return Err(crate::stages::CheckFailed(format!(
                "mean PSNR {all:.3} dB of '{method}' on '{}' is below --fail-below {min}",
                summary.scene
            ))
            .into());
        }
    }
    Ok(())
}

/// Whether camera `c` is scored with its mask.
fn uses_mask(c: &Camera, mode: MaskMode) -> bool {
    match mode {
        MaskMode::Never => false,
        MaskMode::Always => c.mask_path.is_some(),
        MaskMode::Auto => c.mask_path.is_some() && c.angle_offset_deg.is_none(),
    }
}

/// Metrics of every eval camera of `scene` against `renders/<image_path>`, in camera-table
/// order (rayon over images; the order of rows does not depend on the thread count).
pub fn evaluate_images(
    scene: &Scene,
    renders: &Path,
    method: &str,
    lpips: Option<&Lpips>,
    masks: MaskMode,
    ctx: &Context,
) -> anyhow::Result<Vec<MetricRow>> {
    let cams: Vec<&Camera> = scene.eval().collect();
    if cams.is_empty() {
        anyhow::bail!(
            "{}: the scene has no eval cameras",
            Scene::cameras_path(&scene.dir).display()
        );
    }
    for c in &cams {
        let path = renders.join(&c.image_path);
        if !path.is_file() {
            anyhow::bail!(
                "missing render for camera '{}' frame {}: {}",
                c.camera,
                c.frame,
                path.display()
            );
        }
    }
    let label = dir_label(&scene.dir);
    let bar = ctx.progress(cams.len() as u64, "evaluate");
    let rows = cams
        .par_iter()
        .map(|c| {
            let row = evaluate_one(scene, c, renders, &label, method, lpips, uses_mask(c, masks));
            bar.inc(1);
            row
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    bar.finish_and_clear();
    Ok(rows)
}

fn evaluate_one(
    scene: &Scene,
    c: &Camera,
    renders: &Path,
    scene_label: &str,
    method: &str,
    lpips: Option<&Lpips>,
    masked: bool,
) -> anyhow::Result<MetricRow> {
    let gt_path = scene.resolve(&c.image_path);
    let render_path = renders.join(&c.image_path);
    let truth = scene.ground_truth(c, [1.0; 3], masked, false)?;
    let gt = truth.rgb.quantized();
    let render = formats::png::read_png(&render_path)?.rgb_over([1.0; 3]).quantized();
    if (gt.width, gt.height) != (render.width, render.height) {
        anyhow::bail!(
            "{}: render is {}x{}, the ground truth {} is {}x{}",
            render_path.display(),
            render.width,
            render.height,
            gt_path.display(),
            gt.width,
            gt.height
        );
    }
    let mask = truth.mask.map(|m| m.data);
    let m = mask.as_deref();
    let ctx = |what: &str| format!("{what} of {}", render_path.display());
    Ok(MetricRow {
        scene: scene_label.to_string(),
        method: method.to_string(),
        camera: c.camera.clone(),
        frame: c.frame,
        angle_offset_deg: c.angle_offset_deg,
        psnr: psnr(&render, &gt, m).with_context(|| ctx("PSNR"))?,
        ssim: ssim(&render, &gt, m).with_context(|| ctx("SSIM"))?,
        lpips: lpips
            .map(|l| l.distance(&render, &gt, m))
            .transpose()
            .with_context(|| ctx("LPIPS"))?,
        masked: m.is_some(),
    })
}

/// The view ranges of the paper's Table 2, degrees (lower bound excluded).
pub const VIEW_RANGES: [(f32, f32); 3] = [(0.0, 60.0), (60.0, 120.0), (120.0, 180.0)];

/// The angular distance of a camera offset from the training view, in [0°, 180°].
pub fn angular_distance(offset_deg: f32) -> f32 {
    let a = offset_deg.rem_euclid(360.0);
    if a > 180.0 { 360.0 - a } else { a }
}

/// Index into [`VIEW_RANGES`] of an angle offset (offsets above 180° count as 360° − offset);
/// `None` for offset 0.
pub fn view_range(offset_deg: f32) -> Option<usize> {
    let a = angular_distance(offset_deg);
    VIEW_RANGES.iter().position(|(lo, hi)| a > *lo && a <= *hi)
}

/// Mean metrics of one group of images.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Group {
    /// `(0°, 60°]`, ..., or `all`.
    pub label: String,
    /// Number of images.
    pub images: usize,
    /// Mean PSNR, dB (JSON null if infinite).
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS, when every image has one.
    pub lpips: Option<f64>,
}

/// The aggregate of one evaluation.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Scene label.
    pub scene: String,
    /// Method label.
    pub method: String,
    /// Whether the metrics are masked (mPSNR, mSSIM, mLPIPS).
    pub masked: bool,
    /// Non-empty view-range groups (synthetic scenes) followed by `all`.
    pub groups: Vec<Group>,
    /// 3D tracking scores (`evaluate --model`), when computed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tracking: Option<TrackingSummary>,
    /// DyCheck PCK-T (`evaluate --model` on a scene with keypoints), when computed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pck_t: Option<PckTSummary>,
}

fn group(label: String, rows: &[&MetricRow]) -> Group {
    let n = rows.len().max(1) as f64;
    let lpips = rows.iter().map(|r| r.lpips).collect::<Option<Vec<f64>>>();
    Group {
        label,
        images: rows.len(),
        psnr: rows.iter().map(|r| r.psnr).sum::<f64>() / n,
        ssim: rows.iter().map(|r| r.ssim).sum::<f64>() / n,
        lpips: lpips.filter(|l| !l.is_empty()).map(|l| l.iter().sum::<f64>() / n),
    }
}

/// Per-range means (when any row has an angle offset) and the mean over all rows.
pub fn summarise(rows: &[MetricRow]) -> Summary {
    let mut groups = Vec::new();
    if rows.iter().any(|r| r.angle_offset_deg.is_some()) {
        for (i, (lo, hi)) in VIEW_RANGES.iter().enumerate() {
            let in_range: Vec<&MetricRow> = rows
                .iter()
                .filter(|r| r.angle_offset_deg.and_then(view_range) == Some(i))
                .collect();
            if !in_range.is_empty() {
                groups.push(group(format!("({lo}°, {hi}°]"), &in_range));
            }
        }
    }
    groups.push(group("all".into(), &rows.iter().collect::<Vec<_>>()));
    let first = rows.first();
    Summary {
        scene: first.map(|r| r.scene.clone()).unwrap_or_default(),
        method: first.map(|r| r.method.clone()).unwrap_or_default(),
        masked: rows.iter().any(|r| r.masked),
        groups,
        tracking: None,
        pck_t: None,
    }
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".into(), |v| format!("{v:.digits$}"))
}

impl Summary {
    fn names(&self) -> [&'static str; 3] {
        if self.masked { ["mPSNR", "mSSIM", "mLPIPS"] } else { ["PSNR", "SSIM", "LPIPS"] }
    }

    /// The summary as a Markdown table.
    pub fn markdown(&self) -> String {
        let [p, s, l] = self.names();
        let mut md = format!(
            "# {} on {}\n\n| views | images | {p} | {s} | {l} |\n|---|---|---|---|---|\n",
            self.method, self.scene
        );
        for g in &self.groups {
            md.push_str(&format!(
                "| {} | {} | {:.2} | {:.3} | {} |\n",
                g.label,
                g.images,
                g.psnr,
                g.ssim,
                fmt_opt(g.lpips, 3)
            ));
        }
        if let Some(t) = &self.tracking {
            md.push_str(&t.markdown());
        }
        if let Some(k) = &self.pck_t {
            md.push_str(&k.markdown());
        }
        md
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_ranges_follow_table_2() {
        assert_eq!(view_range(0.0), None);
        assert_eq!(view_range(30.0), Some(0));
        assert_eq!(view_range(60.0), Some(0));
        assert_eq!(view_range(90.0), Some(1));
        assert_eq!(view_range(120.0), Some(1));
        assert_eq!(view_range(150.0), Some(2));
        assert_eq!(view_range(180.0), Some(2));
        assert_eq!(view_range(210.0), Some(2));
        assert_eq!(view_range(300.0), Some(0));
        assert_eq!(view_range(330.0), Some(0));
        assert_eq!(view_range(-30.0), Some(0));
    }

    #[test]
    fn summary_groups_by_range() {
        let row = |a: f32, psnr: f64| MetricRow {
            scene: "s".into(),
            method: "m".into(),
            camera: format!("c{a}"),
            frame: 0,
            angle_offset_deg: Some(a),
            psnr,
            ssim: 0.5,
            lpips: Some(0.1),
            masked: false,
        };
        let rows = [row(30.0, 20.0), row(330.0, 22.0), row(90.0, 10.0), row(180.0, 5.0)];
        let s = summarise(&rows);
        let labels: Vec<&str> = s.groups.iter().map(|g| g.label.as_str()).collect();
        assert_eq!(labels, ["(0°, 60°]", "(60°, 120°]", "(120°, 180°]", "all"]);
        assert_eq!(s.groups.iter().map(|g| g.images).collect::<Vec<_>>(), [2, 1, 1, 4]);
        assert_eq!(s.groups[0].psnr, 21.0);
        assert_eq!(s.groups[3].psnr, 57.0 / 4.0);
        assert_eq!(s.groups[3].lpips, Some(0.1));
    }
}
