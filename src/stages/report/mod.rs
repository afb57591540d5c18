//! `usplat4d report`: one self-contained HTML file (images as `data:` PNGs, charts as inline
//! SVG drawn with `plotters`) of a pipeline run or a benchmark.
//!
//! Sections, each present when its inputs are given: the paper's Table 2 form (metrics per
//! view range and method, with the difference to the first method), bar charts of those
//! metrics, tracking scores, training curves from `training_log.parquet`, image grids of
//! the farthest evaluation view (ground truth | each method), uncertainty heat maps (u of
//! the training frame rendered as a colour-mapped feature, dark = confident), key nodes and
//! motion segments over a render, and the key-graph weight matrix reordered by segment.

mod figures;
mod html;
mod plots;

use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::context::Context;
use crate::scene::Scene;
use crate::stages::evaluate::{Summary, summarise};
use crate::tables::Table;

/// Parameters of `usplat4d report`.
#[derive(Debug, Clone, clap::Args, serde::Serialize)]
pub struct ReportParams {
    /// Output directory; the report is `OUT/report.html`.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Title of the page.
    #[arg(long, default_value = "usplat4d report")]
    pub title: String,
    /// Scene directory (cameras and ground-truth images).
    #[arg(long, value_name = "DIR")]
    pub scene: PathBuf,
    /// An `evaluate` output of one method, as NAME=DIR; repeat for several methods. The
    /// first is the reference of the differences (e.g. the base model).
    #[arg(long = "eval", value_name = "NAME=DIR")]
    pub evals: Vec<String>,
    /// A `render` output of one method, as NAME=DIR, for the image grids of the farthest
    /// evaluation view.
    #[arg(long = "renders", value_name = "NAME=DIR")]
    pub renders: Vec<String>,
    /// A directory holding `training_log.parquet` (an `optimize` output), as NAME=DIR.
    #[arg(long = "training-log", value_name = "NAME=DIR")]
    pub logs: Vec<String>,
    /// Model directory of the graph figures (heat maps, key nodes, segments).
    #[arg(long, value_name = "DIR")]
    pub model: Option<PathBuf>,
    /// `uncertainty` output of that model, for the heat maps.
    #[arg(long, value_name = "DIR", requires = "model")]
    pub uncertainty: Option<PathBuf>,
    /// `segment` output of that model, for key nodes and segments over a render.
    #[arg(long, value_name = "DIR", requires = "model")]
    pub segments: Option<PathBuf>,
    /// `edges` output, for the key-graph weight matrix (needs --segments for its order).
    #[arg(long, value_name = "DIR", requires = "segments")]
    pub edges: Option<PathBuf>,
    /// Frames shown in the image grids and heat maps.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=32))]
    pub frames: u32,
}

/// Split `NAME=DIR` into its parts.
fn named(flag: &str, s: &str) -> anyhow::Result<(String, PathBuf)> {
    match s.split_once('=') {
        Some((n, d)) if !n.is_empty() && !d.is_empty() => Ok((n.to_string(), PathBuf::from(d))),
        _ => anyhow::bail!("--{flag} '{s}': expected NAME=DIR"),
    }
}

fn named_all(flag: &str, v: &[String]) -> anyhow::Result<Vec<(String, PathBuf)>> {
    v.iter().map(|s| named(flag, s)).collect()
}

/// A section of the page: anchor id, heading, HTML body.
type Section = (String, String, String);

/// Run `usplat4d report`.
pub fn run(p: &ReportParams, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("stage.report").entered();
    let scene = Scene::load(&p.scene)?;
    let evals = named_all("eval", &p.evals)?;
    let renders = named_all("renders", &p.renders)?;
    let logs = named_all("training-log", &p.logs)?;
    let mut sections: Vec<Section> = Vec::new();
    if !evals.is_empty() {
        let summaries = evals
            .iter()
            .map(|(name, dir)| {
                let path = dir.join(crate::tables::metrics::MetricsTable::file_name());
                let mut s = summarise(&crate::tables::metrics::read(&path)?);
                s.method = name.clone();
                Ok((s, tracking_json(dir)?))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        sections.push(metrics_section(&summaries));
        sections.push(charts_section(&summaries)?);
        if summaries.iter().any(|(_, t)| t.is_some()) {
            sections.push(tracking_section(&summaries));
        }
    }
    if !logs.is_empty() {
        sections.push(curves_section(&logs)?);
    }
    if !renders.is_empty() {
        sections.push(views_section(&scene, &renders, p.frames as usize)?);
    }
    if let Some(model_dir) = &p.model {
        let model = crate::model::Model::load(model_dir)?;
        let frames = spaced_frames(model.num_frames(), p.frames as usize);
        if let Some(dir) = &p.uncertainty {
            sections.push(uncertainty_section(&scene, &model, dir, &frames)?);
        }
        if let Some(dir) = &p.segments {
            let path = dir.join(crate::tables::segments::SegmentsTable::file_name());
            let segments = crate::tables::segments::read(&path)?;
            sections.push(segments_section(&scene, &model, &segments, &frames)?);
            if let Some(edges_dir) = &p.edges {
                let path = edges_dir.join(crate::tables::edges::EdgesTable::file_name());
                let edges = crate::tables::edges::read(&path)?;
                sections.push(matrix_section(&edges, &segments)?);
            }
        }
    }
    anyhow::ensure!(
        !sections.is_empty(),
        "report: nothing to show (give --eval, --renders, --training-log or --model)"
    );
    let page = html::page(&p.title, &sections);
    let path = p.out.join("report.html");
    crate::util::fs::write_atomic(&path, page.as_bytes())?;
    ctx.info(format!(
        "report: {} sections, {} KiB, in {}",
        sections.len(),
        page.len() / 1024,
        path.display()
    ));
    Ok(())
}

/// `n` frames evenly spaced over `0..t` (all of them when `t <= n`).
fn spaced_frames(t: usize, n: usize) -> Vec<usize> {
    if t <= n {
        return (0..t).collect();
    }
    (0..n).map(|k| k * (t - 1) / (n - 1).max(1)).collect()
}

/// The `tracking` and `pck_t` parts of an evaluation's `summary.json`, when present.
fn tracking_json(dir: &Path) -> anyhow::Result<Option<serde_json::Value>> {
    let path = dir.join("summary.json");
    if !path.exists() {
        return Ok(None);
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&path)?)
        .with_context(|| format!("{}: not valid JSON", path.display()))?;
    let t = serde_json::json!({ "tracking": v.get("tracking"), "pck_t": v.get("pck_t") });
    Ok((!v.get("tracking").is_none_or(|x| x.is_null())
        || !v.get("pck_t").is_none_or(|x| x.is_null()))
    .then_some(t))
}

fn metric_names(masked: bool) -> [&'static str; 3] {
    if masked { ["mPSNR", "mSSIM", "mLPIPS"] } else { ["PSNR", "SSIM", "LPIPS"] }
}

fn metrics_section(summaries: &[(Summary, Option<serde_json::Value>)]) -> Section {
    let names = metric_names(summaries[0].0.masked);
    let mut header = vec!["method".to_string(), "views".to_string(), "images".to_string()];
    header.extend(names.iter().map(|n| n.to_string()));
    if summaries.len() > 1 {
        header.extend(names.iter().map(|n| format!("Δ{n} vs {}", summaries[0].0.method)));
    }
    let reference = &summaries[0].0;
    let mut rows = Vec::new();
    for (s, _) in summaries {
        for g in &s.groups {
            let mut row = vec![s.method.clone(), g.label.clone(), g.images.to_string()];
            row.push(format!("{:.2}", g.psnr));
            row.push(format!("{:.4}", g.ssim));
            row.push(g.lpips.map_or("-".into(), |l| format!("{l:.4}")));
            if summaries.len() > 1 {
                let r = reference.groups.iter().find(|r| r.label == g.label);
                row.push(r.map_or("-".into(), |r| format!("{:+.2}", g.psnr - r.psnr)));
                row.push(r.map_or("-".into(), |r| format!("{:+.4}", g.ssim - r.ssim)));
                row.push(
                    r.and_then(|r| Some(g.lpips? - r.lpips?))
                        .map_or("-".into(), |d| format!("{d:+.4}")),
                );
            }
            rows.push(row);
        }
    }
    ("metrics".into(), "Novel views by view range".into(), html::table(&header, &rows))
}

fn charts_section(summaries: &[(Summary, Option<serde_json::Value>)]) -> anyhow::Result<Section> {
    let names = metric_names(summaries[0].0.masked);
    let methods: Vec<String> = summaries.iter().map(|(s, _)| s.method.clone()).collect();
    let mut groups: Vec<String> = Vec::new();
    for (s, _) in summaries {
        for g in &s.groups {
            if !groups.contains(&g.label) {
                groups.push(g.label.clone());
            }
        }
    }
    let mut body = String::new();
    for (k, name) in names.iter().enumerate() {
        let values: Vec<Vec<Option<f64>>> = groups
            .iter()
            .map(|label| {
                summaries
                    .iter()
                    .map(|(s, _)| {
                        let g = s.groups.iter().find(|g| &g.label == label)?;
                        [Some(g.psnr), Some(g.ssim), g.lpips][k].filter(|v| v.is_finite())
                    })
                    .collect()
            })
            .collect();
        if values.iter().flatten().any(Option::is_some) {
            let lower = if k == 2 { " (lower is better)" } else { "" };
            let svg = plots::grouped_bars(
                &format!("{name} by view range{lower}"),
                name,
                &groups,
                &methods,
                &values,
            )?;
            body.push_str(&html::figure(&svg, name));
        }
    }
    Ok(("charts".into(), "Charts by view range".into(), body))
}

fn tracking_section(summaries: &[(Summary, Option<serde_json::Value>)]) -> Section {
    let header: Vec<String> = ["method", "3D EPE", "PCK@5%", "PCK@10%", "PCK-T", "2D EPE (px)"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let num = |v: &serde_json::Value, part: &str, key: &str, digits: usize| {
        v[part][key].as_f64().map_or("-".to_string(), |x| format!("{x:.digits$}"))
    };
    let rows = summaries
        .iter()
        .filter_map(|(s, t)| {
            let t = t.as_ref()?;
            Some(vec![
                s.method.clone(),
                num(t, "tracking", "epe", 4),
                num(t, "tracking", "pck_5", 3),
                num(t, "tracking", "pck_10", 3),
                num(t, "pck_t", "pck_t", 3),
                num(t, "pck_t", "epe_px", 2),
            ])
        })
        .collect::<Vec<_>>();
    ("tracking".into(), "Tracking".into(), html::table(&header, &rows))
}

/// Every numeric column of a training log against its `step` column.
fn read_log(path: &Path) -> anyhow::Result<Vec<plots::Curve>> {
    use arrow::array::{Array, Float64Array};
    use arrow::datatypes::DataType;
    let file =
        std::fs::File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
    let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{}: not a Parquet file", path.display()))?
        .build()?;
    let mut cols: Vec<(String, Vec<f64>)> = Vec::new();
    for batch in reader {
        let batch = batch.with_context(|| format!("{}: reading", path.display()))?;
        for (i, f) in batch.schema().fields().iter().enumerate() {
            if !f.data_type().is_numeric() {
                continue;
            }
            let col = arrow::compute::cast(batch.column(i), &DataType::Float64)?;
            let col = col.as_any().downcast_ref::<Float64Array>().context("cast to f64")?;
            let values =
                (0..col.len()).map(|r| if col.is_null(r) { f64::NAN } else { col.value(r) });
            match cols.iter_mut().find(|(n, _)| n == f.name()) {
                Some((_, v)) => v.extend(values),
                None => cols.push((f.name().clone(), values.collect())),
            }
        }
    }
    let step = cols
        .iter()
        .position(|(n, _)| n == "step")
        .with_context(|| format!("{}: no 'step' column", path.display()))?;
    let steps = cols.remove(step).1;
    Ok(cols
        .into_iter()
        .filter(|(n, _)| n.starts_with("loss") || n.contains("loss") || n.starts_with("l_"))
        .map(|(n, v)| (n, steps.iter().copied().zip(v).collect()))
        .collect())
}

fn curves_section(logs: &[(String, PathBuf)]) -> anyhow::Result<Section> {
    let mut body = String::new();
    for (name, dir) in logs {
        let curves = read_log(&dir.join("training_log.parquet"))?;
        anyhow::ensure!(
            !curves.is_empty(),
            "{}: no loss columns",
            dir.join("training_log.parquet").display()
        );
        let svg = plots::log_curves(&format!("training losses: {name}"), &curves)?;
        body.push_str(&html::figure(&svg, name));
    }
    Ok(("training".into(), "Training curves".into(), body))
}

fn views_section(
    scene: &Scene,
    renders: &[(String, PathBuf)],
    frames: usize,
) -> anyhow::Result<Section> {
    let cams = figures::farthest_views(scene, frames);
    anyhow::ensure!(
        !cams.is_empty(),
        "{}: the scene has no evaluation camera",
        scene.dir.display()
    );
    let rows = figures::view_grid(scene, &cams, renders)?;
    let columns = renders.len() + 1;
    let mut body = format!(
        "<div class=\"grid\" style=\"grid-template-columns:repeat({columns},1fr)\">\n<div>ground truth</div>"
    );
    for (name, _) in renders {
        body.push_str(&format!("<div>{}</div>", html::escape(name)));
    }
    for (label, images) in &rows {
        for (k, im) in images.iter().enumerate() {
            let who = if k == 0 { "ground truth" } else { &renders[k - 1].0 };
            body.push_str(&format!(
                "<div>{}<br>{}</div>",
                html::img(im, &format!("{who}, {label}"))?,
                html::escape(label)
            ));
        }
    }
    body.push_str("</div>\n");
    let offset = cams[0]
        .angle_offset_deg
        .map_or(String::new(), |a| format!(" ({a:.0}° from the training view)"));
    Ok(("views".into(), format!("Farthest evaluation view{offset}"), body))
}

fn uncertainty_section(
    scene: &Scene,
    model: &crate::model::Model,
    dir: &Path,
    frames: &[usize],
) -> anyhow::Result<Section> {
    let reader = crate::tables::uncertainty::UncertaintyReader::open(
        &dir.join(crate::tables::uncertainty::UncertaintyTable::file_name()),
    )?;
    anyhow::ensure!(
        reader.ids() == model.gaussians.id.as_slice(),
        "{}: its Gaussians are not those of the model {}",
        dir.display(),
        model.dir.display()
    );
    let train = scene.train_by_frame();
    let us = frames.iter().map(|&t| Ok(reader.frame(t)?.u)).collect::<anyhow::Result<Vec<_>>>()?;
    let range = figures::log_range(&us.concat());
    let mut body = String::new();
    for (&t, u) in frames.iter().zip(&us) {
        let cam = train
            .get(t)
            .with_context(|| format!("{}: no training camera at frame {t}", scene.dir.display()))?;
        let img = figures::render_colored(model, t, cam, &figures::heat_colors(u, range))?;
        body.push_str(&html::figure(
            &html::img(&img, &format!("u at frame {t}"))?,
            &format!("frame {t}"),
        ));
    }
    body.push_str(&html::figure(
        &plots::colour_bar("log10 u", range.0, range.1, figures::viridis)?,
        "colour scale",
    ));
    Ok(("uncertainty".into(), "Uncertainty in the training view".into(), body))
}

fn segments_section(
    scene: &Scene,
    model: &crate::model::Model,
    segments: &crate::tables::segments::Segments,
    frames: &[usize],
) -> anyhow::Result<Section> {
    let train = scene.train_by_frame();
    let colors = figures::segment_colors(model, segments);
    let k = segments.segment.iter().max().map_or(0, |m| m + 1);
    let mut body = String::new();
    for &t in frames {
        let cam = train
            .get(t)
            .with_context(|| format!("{}: no training camera at frame {t}", scene.dir.display()))?;
        let plain = figures::render_colored(model, t, cam, &model.gaussians.color)?;
        let mut seg = figures::render_colored(model, t, cam, &colors)?;
        let drawn = figures::draw_keys(&mut seg, model, t, cam, segments)?;
        let both = figures::hstack(&[plain, seg], 4);
        body.push_str(&html::figure(
            &html::img(&both, &format!("segments at frame {t}"))?,
            &format!("frame {t}: render | {k} motion segments with {drawn} key nodes (dots)"),
        ));
    }
    Ok(("segments".into(), "Key nodes and motion segments".into(), body))
}

fn matrix_section(
    edges: &crate::tables::edges::Edges,
    segments: &crate::tables::segments::Segments,
) -> anyhow::Result<Section> {
    let (img, max) = figures::weight_matrix(edges, segments, 512);
    if max <= 0.0 {
        let body =
            "<p>The edges table has no key-key edge with a positive weight.</p>\n".to_string();
        return Ok(("graph".into(), "Key-graph weight matrix".into(), body));
    }
    let mut body = html::figure(
        &html::img(&img, "key-graph weight matrix")?,
        "keys ordered by motion segment (white: no edge)",
    );
    body.push_str(&html::figure(
        &plots::colour_bar("edge weight (w_ij + w_ji) / 2", 0.0, max, figures::viridis)?,
        "colour scale",
    ));
    Ok(("graph".into(), "Key-graph weight matrix".into(), body))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn named_inputs() {
        assert_eq!(named("eval", "base=out/x").unwrap(), ("base".into(), PathBuf::from("out/x")));
        assert_eq!(
            named("eval", "out/x").unwrap_err().to_string(),
            "--eval 'out/x': expected NAME=DIR"
        );
        assert!(named("eval", "=x").is_err() && named("eval", "a=").is_err());
    }

    #[test]
    fn frames_are_spread() {
        assert_eq!(spaced_frames(121, 3), vec![0, 60, 120]);
        assert_eq!(spaced_frames(2, 3), vec![0, 1]);
        assert_eq!(spaced_frames(10, 1), vec![0]);
    }
}
