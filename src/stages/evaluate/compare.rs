//! Evaluations read back and set side by side: `evaluate --compare A B [C ...]` and the
//! benchmark tables. The first evaluation is the reference of every difference.

use std::path::Path;

use super::{Summary, summarise};
use crate::tables::Table;
use crate::tables::metrics::{MetricRow, MetricsTable};

/// Tracking scores of an evaluation (`evaluate --model`), each when computed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tracking {
    /// Mean 3D end-point error, world units.
    pub epe: Option<f64>,
    /// 3D PCK at 5% of the bounding-box diagonal.
    pub pck_5: Option<f64>,
    /// 3D PCK at 10% of the diagonal.
    pub pck_10: Option<f64>,
    /// DyCheck's 2D PCK-T.
    pub pck_t: Option<f64>,
}

/// One evaluation: per-range metrics and tracking.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Means by view range (and `all`).
    pub summary: Summary,
    /// Tracking scores from `summary.json`, when the evaluation scored a model.
    pub tracking: Tracking,
}

/// Read the rows of an evaluation: an `evaluate` output directory or its metrics file.
pub fn read_rows(p: &Path) -> anyhow::Result<Vec<MetricRow>> {
    let file = if p.is_dir() { p.join(MetricsTable::file_name()) } else { p.to_path_buf() };
    Ok(crate::tables::metrics::read(&file)?)
}

/// Load an evaluation (directory or metrics file; tracking from `summary.json` beside it).
pub fn load(p: &Path) -> anyhow::Result<Evaluation> {
    let summary = summarise(&read_rows(p)?);
    let dir = if p.is_dir() { p } else { p.parent().unwrap_or(Path::new(".")) };
    let json_path = dir.join("summary.json");
    let mut tracking = Tracking::default();
    if json_path.exists() {
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json_path)?)
            .map_err(|e| anyhow::anyhow!("{}: not valid JSON: {e}", json_path.display()))?;
        let num =
            |part: &str, key: &str| v.get(part).and_then(|t| t.get(key)).and_then(|x| x.as_f64());
        tracking = Tracking {
            epe: num("tracking", "epe"),
            pck_5: num("tracking", "pck_5"),
            pck_10: num("tracking", "pck_10"),
            pck_t: num("pck_t", "pck_t"),
        };
    }
    Ok(Evaluation { summary, tracking })
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.filter(|x| x.is_finite()).map_or("-".into(), |v| format!("{v:.digits$}"))
}

fn delta(a: Option<f64>, b: Option<f64>, digits: usize) -> String {
    match (a, b) {
        (Some(a), Some(b)) if a.is_finite() && b.is_finite() => format!("{:+.digits$}", b - a),
        _ => "-".into(),
    }
}

/// Markdown of `evals` side by side: per view range each method's PSNR/SSIM/LPIPS with the
/// difference to the first, then the tracking scores when any evaluation has them.
pub fn side_by_side(evals: &[(String, Evaluation)]) -> String {
    let Some((ref_name, reference)) = evals.first() else { return String::new() };
    let [p, s, l] = reference.summary.names();
    let mut md = format!(
        "# {} on {} (Δ against {ref_name})\n\n",
        evals.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(" vs "),
        reference.summary.scene
    );
    md.push_str(&format!("| views | method | images | {p} | Δ{p} | {s} | Δ{s} | {l} | Δ{l} |\n|---|---|---|---|---|---|---|---|---|\n"));
    for g0 in &reference.summary.groups {
        for (name, e) in evals {
            let Some(g) = e.summary.groups.iter().find(|g| g.label == g0.label) else { continue };
            md.push_str(&format!(
                "| {} | {name} | {} | {:.2} | {} | {:.3} | {} | {} | {} |\n",
                g.label,
                g.images,
                g.psnr,
                delta(Some(g0.psnr), Some(g.psnr), 2),
                g.ssim,
                delta(Some(g0.ssim), Some(g.ssim), 3),
                opt(g.lpips, 3),
                delta(g0.lpips, g.lpips, 3),
            ));
        }
    }
    if evals.iter().any(|(_, e)| e.tracking != Tracking::default()) {
        md.push_str(
            "\n| method | 3D EPE | Δ | PCK@5% | PCK@10% | PCK-T |\n|---|---|---|---|---|---|\n",
        );
        let t0 = &reference.tracking;
        for (name, e) in evals {
            let t = &e.tracking;
            md.push_str(&format!(
                "| {name} | {} | {} | {} | {} | {} |\n",
                opt(t.epe, 4),
                delta(t0.epe, t.epe, 4),
                opt(t.pck_5, 3),
                opt(t.pck_10, 3),
                opt(t.pck_t, 3)
            ));
        }
    }
    md
}

/// `evaluate --compare`: the evaluations at `paths`, labelled by their method names.
pub fn compare(paths: &[std::path::PathBuf]) -> anyhow::Result<String> {
    anyhow::ensure!(paths.len() >= 2, "--compare takes at least two evaluations");
    let evals = paths
        .iter()
        .map(|p| {
            let e = load(p)?;
            Ok((e.summary.method.clone(), e))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(side_by_side(&evals))
}
