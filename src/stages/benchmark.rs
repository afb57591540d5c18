//! `usplat4d benchmark`: the paper's tables from a set of evaluations. Table 2's form per
//! scene and averaged over scenes (each method's PSNR/SSIM/LPIPS per view range with the
//! difference to the baseline, the base model continued for the same steps), the tracking
//! scores beside them (Table 8: 3D EPE, PCK at 5% and 10%), and Table 3's ablations
//! averaged over scenes. Writes `benchmark.md` and the `benchmark` table.

use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::context::Context;
use crate::stages::evaluate::compare::{self, Evaluation, Tracking};
use crate::stages::evaluate::{Group, Summary};
use crate::tables::Table;
use crate::tables::benchmark::{BenchmarkRow, BenchmarkTable};

/// Parameters of `usplat4d benchmark`.
#[derive(Debug, Clone, clap::Args, serde::Serialize)]
pub struct BenchmarkParams {
    /// An evaluation (an `evaluate` output directory) as SCENE/METHOD=DIR; repeat for every
    /// scene and method.
    #[arg(long = "eval", value_name = "SCENE/METHOD=DIR", required = true)]
    pub evals: Vec<String>,
    /// The method every difference is taken against (the base model continued).
    #[arg(long, default_value = "vanilla")]
    pub baseline: String,
    /// Methods shown in the ablation table instead of Table 2 (repeatable).
    #[arg(long = "ablation", value_name = "METHOD")]
    pub ablations: Vec<String>,
    /// Output directory (benchmark.md, benchmark.parquet).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// `SCENE/METHOD=DIR` split into its parts.
fn parse_eval(s: &str) -> anyhow::Result<(String, String, PathBuf)> {
    let parsed = s.split_once('=').and_then(|(label, dir)| {
        let (scene, method) = label.split_once('/')?;
        (!scene.is_empty() && !method.is_empty() && !dir.is_empty())
            .then(|| (scene.to_string(), method.to_string(), PathBuf::from(dir)))
    });
    parsed.ok_or_else(|| anyhow::anyhow!("--eval '{s}': expected SCENE/METHOD=DIR"))
}

/// The mean over scenes of one method's evaluations (each scene weighs the same; a view
/// range or a score enters only when every scene has it).
fn mean(method: &str, evals: &[&Evaluation]) -> Evaluation {
    let n = evals.len() as f64;
    let first = &evals[0].summary;
    let groups = first
        .groups
        .iter()
        .filter_map(|g0| {
            let gs: Vec<&Group> = evals
                .iter()
                .filter_map(|e| e.summary.groups.iter().find(|g| g.label == g0.label))
                .collect();
            (gs.len() == evals.len()).then(|| Group {
                label: g0.label.clone(),
                images: gs.iter().map(|g| g.images).sum(),
                psnr: gs.iter().map(|g| g.psnr).sum::<f64>() / n,
                ssim: gs.iter().map(|g| g.ssim).sum::<f64>() / n,
                lpips: gs.iter().map(|g| g.lpips).sum::<Option<f64>>().map(|l| l / n),
            })
        })
        .collect();
    let avg = |f: fn(&Tracking) -> Option<f64>| {
        evals.iter().map(|e| f(&e.tracking)).sum::<Option<f64>>().map(|v| v / n)
    };
    Evaluation {
        summary: Summary {
            scene: "mean".into(),
            method: method.into(),
            masked: first.masked,
            groups,
            tracking: None,
            pck_t: None,
        },
        tracking: Tracking {
            epe: avg(|t| t.epe),
            pck_5: avg(|t| t.pck_5),
            pck_10: avg(|t| t.pck_10),
            pck_t: avg(|t| t.pck_t),
        },
    }
}

fn rows_of(scene: &str, method: &str, e: &Evaluation) -> Vec<BenchmarkRow> {
    e.summary
        .groups
        .iter()
        .map(|g| {
            let all = g.label == "all";
            BenchmarkRow {
                scene: scene.into(),
                method: method.into(),
                views: g.label.clone(),
                images: g.images as u32,
                psnr: g.psnr,
                ssim: g.ssim,
                lpips: g.lpips,
                epe: e.tracking.epe.filter(|_| all),
                pck_5: e.tracking.pck_5.filter(|_| all),
                pck_10: e.tracking.pck_10.filter(|_| all),
            }
        })
        .collect()
}

/// Run `usplat4d benchmark`.
pub fn run(p: &BenchmarkParams, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("stage.benchmark").entered();
    // scene -> method -> evaluation, scenes and methods in first-seen order.
    let mut scenes: Vec<String> = Vec::new();
    let mut methods: Vec<String> = Vec::new();
    let mut table: BTreeMap<(String, String), Evaluation> = BTreeMap::new();
    for s in &p.evals {
        let (scene, method, dir) = parse_eval(s)?;
        let e = compare::load(&dir).map_err(|e| anyhow::anyhow!("--eval {s}: {e:#}"))?;
        if !scenes.contains(&scene) {
            scenes.push(scene.clone());
        }
        if !methods.contains(&method) {
            methods.push(method.clone());
        }
        anyhow::ensure!(
            table.insert((scene.clone(), method.clone()), e).is_none(),
            "--eval {scene}/{method} is given twice"
        );
    }
    anyhow::ensure!(
        methods.contains(&p.baseline),
        "--baseline '{}' is not among the methods {methods:?}",
        p.baseline
    );
    for scene in &scenes {
        for method in &methods {
            anyhow::ensure!(
                table.contains_key(&(scene.clone(), method.clone())),
                "no evaluation of {scene}/{method} (every scene needs every method)"
            );
        }
    }
    for a in &p.ablations {
        anyhow::ensure!(
            methods.contains(a),
            "--ablation '{a}' is not among the methods {methods:?}"
        );
    }
    // Baseline first, then the other methods in the order given.
    let ordered: Vec<&String> =
        std::iter::once(&p.baseline).chain(methods.iter().filter(|m| **m != p.baseline)).collect();
    let main_methods: Vec<&String> =
        ordered.iter().copied().filter(|m| !p.ablations.contains(m)).collect();
    let means: BTreeMap<&String, Evaluation> = ordered
        .iter()
        .map(|m| {
            let evals: Vec<&Evaluation> =
                scenes.iter().map(|s| &table[&(s.clone(), (*m).clone())]).collect();
            (*m, mean(m, &evals))
        })
        .collect();
    let pick = |scene: Option<&String>, ms: &[&String]| -> Vec<(String, Evaluation)> {
        ms.iter()
            .map(|m| {
                let mut e = match scene {
                    Some(s) => table[&(s.clone(), (*m).clone())].clone(),
                    None => means[m].clone(),
                };
                // the heading names the scene as the --eval label does, not the directory
                e.summary.scene = scene.cloned().unwrap_or_else(|| "the mean over scenes".into());
                ((*m).clone(), e)
            })
            .collect()
    };
    let mut md = format!(
        "# Benchmark: {} scenes, {} methods, differences against {}\n\n## Table 2 form, per scene\n\n",
        scenes.len(),
        methods.len(),
        p.baseline
    );
    for s in &scenes {
        md.push_str(
            &compare::side_by_side(&pick(Some(s), &main_methods)).replacen("# ", "### ", 1),
        );
        md.push('\n');
    }
    md.push_str("## Table 2 form, mean over scenes\n\n");
    md.push_str(&compare::side_by_side(&pick(None, &main_methods)).replacen("# ", "### ", 1));
    if !p.ablations.is_empty() {
        let abl: Vec<&String> = std::iter::once(&p.baseline).chain(p.ablations.iter()).collect();
        md.push_str("\n## Ablations (Table 3 form), mean over scenes\n\n");
        md.push_str(&compare::side_by_side(&pick(None, &abl)).replacen("# ", "### ", 1));
    }
    let mut rows = Vec::new();
    for s in &scenes {
        for m in &ordered {
            rows.extend(rows_of(s, m, &table[&(s.clone(), (*m).clone())]));
        }
    }
    for m in &ordered {
        rows.extend(rows_of("mean", m, &means[m]));
    }
    let prov = crate::tables::Provenance::new("benchmark", &serde_json::json!({ "params": p }));
    crate::tables::benchmark::write(&p.out.join(BenchmarkTable::file_name()), &rows, &prov)?;
    crate::util::fs::write_atomic(&p.out.join("benchmark.md"), md.as_bytes())?;
    if !ctx.quiet {
        print!("{md}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eval_labels() {
        assert_eq!(
            parse_eval("fox/vanilla=out/e").unwrap(),
            ("fox".into(), "vanilla".into(), PathBuf::from("out/e"))
        );
        for bad in ["fox=out", "fox/=out", "/m=out", "fox/m=", "fox/m"] {
            assert_eq!(
                parse_eval(bad).unwrap_err().to_string(),
                format!("--eval '{bad}': expected SCENE/METHOD=DIR")
            );
        }
    }

    fn eval(psnr: [f64; 2], epe: Option<f64>) -> Evaluation {
        let g = |label: &str, psnr: f64| Group {
            label: label.into(),
            images: 2,
            psnr,
            ssim: 0.5,
            lpips: None,
        };
        Evaluation {
            summary: Summary {
                scene: "s".into(),
                method: "m".into(),
                masked: false,
                groups: vec![g("(120°, 180°]", psnr[0]), g("all", psnr[1])],
                tracking: None,
                pck_t: None,
            },
            tracking: Tracking { epe, ..Tracking::default() },
        }
    }

    #[test]
    fn mean_weighs_scenes_equally_and_needs_every_scene() {
        let (a, b) = (eval([20.0, 24.0], Some(0.1)), eval([22.0, 26.0], None));
        let m = mean("m", &[&a, &b]);
        assert_eq!(
            m.summary.groups.iter().map(|g| (g.psnr, g.images)).collect::<Vec<_>>(),
            vec![(21.0, 4), (25.0, 4)]
        );
        // One scene without tracking: no mean tracking.
        assert_eq!(m.tracking.epe, None);
        let m = mean("m", &[&a, &a]);
        assert_eq!(m.tracking.epe, Some(0.1));
        let rows = rows_of("mean", "m", &m);
        assert_eq!((rows[0].epe, rows[1].epe), (None, Some(0.1)));
    }
}
