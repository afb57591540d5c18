//! The benchmark pipelines run end to end at reduced sizes: `pipelines/extreme-view.yaml` (four
//! models, base fit, vanilla continued, USplat4D with both profiles and the four ablations,
//! benchmark and report), `pipelines/dycheck.yaml` (the synthetic DyCheck-layout Fox along the
//! paper-windmill path, masked metrics and PCK-T) and `pipelines/fox.yaml` (the oracle's graph
//! stages, and both recipes and profiles refining a drifting prior).

use usplat4d::tables::TableReader;
use usplat4d::tables::edges::EdgesTable;
use usplat4d::tables::io::KEY_PARAMS;

use crate::util::{Dir, copy_dir, repo};

/// A copy of `pipelines/FILE` and `pipelines/data` in a fresh directory, so the run's lock
/// file, cache and outputs stay out of the repository.
fn pipeline(file: &str) -> Dir {
    let d = Dir::new();
    std::fs::copy(repo().join("pipelines").join(file), d.join(file)).unwrap();
    copy_dir(&repo().join("pipelines/data"), &d.join("data"));
    d
}

fn run(d: &Dir, file: &str, sets: &[&str]) -> String {
    let mut args = vec!["pipeline", "run", file];
    for s in sets {
        args.extend(["--set", s]);
    }
    d.ok(&args)
}

#[test]
fn extreme_view_pipeline_writes_the_paper_tables_for_four_models() {
    let d = pipeline("extreme-view.yaml");
    let sets =
        ["frames=6", "size=48", "gaussians=1000", "init_gaussians=500", "base_steps=6", "steps=3"];
    let out = run(&d, "extreme-view.yaml", &sets);
    assert!(out.contains("177 stages: 177 run"), "{out}");
    let md = std::fs::read_to_string(d.join("out/extreme-view/benchmark/benchmark.md")).unwrap();
    for model in ["Fox", "CesiumMan", "RiggedFigure", "RiggedSimple"] {
        assert!(md.contains(&format!("usplat4d-release on {model} (Δ against vanilla)")), "{md}");
        let page = d.join(&format!("out/extreme-view/{model}/report/report.html"));
        assert!(std::fs::read_to_string(page).unwrap().trim_end().ends_with("</html>"));
    }
    assert!(md.contains("on the mean over scenes"), "{md}");
    assert!(md.contains("## Ablations (Table 3 form), mean over scenes"), "{md}");
    for range in ["(0°, 60°]", "(60°, 120°]", "(120°, 180°]"] {
        for m in [
            "base",
            "smoothness-only",
            "usplat4d-paper",
            "ablation-a",
            "ablation-b",
            "ablation-c",
            "ablation-d",
        ] {
            assert!(md.contains(&format!("| {range} | {m} |")), "{range} {m}:\n{md}");
        }
    }
    assert!(md.contains("| 3D EPE |"), "{md}");
    assert!(d.join("out/extreme-view/benchmark/benchmark.parquet").exists());
    // a second run has nothing to do
    let again = run(&d, "extreme-view.yaml", &sets);
    assert!(again.contains("all 177 stages up to date"), "{again}");
}

#[test]
fn dycheck_pipeline_runs_out_of_the_box_on_the_windmill_fox() {
    let d = pipeline("dycheck.yaml");
    let sets = [
        "example_factor=16",
        "example_stride=20",
        "gaussians=1000",
        "init_gaussians=800",
        "base_steps=20",
        "steps=3",
    ];
    let out = run(&d, "dycheck.yaml", &sets);
    assert!(out.contains("21 stages: 21 run"), "{out}");
    let bench = d.join("out/dycheck/fox-windmill/benchmark/benchmark.md");
    let md = std::fs::read_to_string(bench).unwrap();
    assert!(md.contains("vanilla vs base vs smoothness-only vs usplat4d on fox-windmill"), "{md}");
    assert!(md.contains("| all | usplat4d |") && md.contains("| all | smoothness-only |"), "{md}");
    let eval = d.join("out/dycheck/fox-windmill/eval/usplat4d");
    let files: Vec<String> = std::fs::read_dir(eval)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(files.iter().any(|f| f.ends_with(".md")), "{files:?}");
    let page = d.join("out/dycheck/fox-windmill/report/report.html");
    assert!(std::fs::read_to_string(page).unwrap().contains("PCK-T"));
    // The profile reaches the vanilla continuation, the graph stages, USplat4D and the
    // smoothness-only baseline (whose graph inputs it changes), and what depends on them; not
    // the example, the import or the base fit.
    let release = run(&d, "dycheck.yaml", &[&sets[..], &["profile=release"]].concat());
    assert!(release.contains("21 stages: 15 run, 0 restored from run cache, 6 up to date"));
    let edges = d.join("out/dycheck/fox-windmill/graph/edges/edges.parquet");
    let reader = TableReader::open::<EdgesTable>(&edges).unwrap();
    let params: serde_json::Value =
        serde_json::from_str(&reader.metadata_value(KEY_PARAMS).unwrap()).unwrap();
    assert_eq!(params["resolved"]["profile"], "release", "{params}");
}

#[test]
fn fox_pipeline_refines_a_drifting_prior_with_both_recipes_and_profiles() {
    let d = pipeline("fox.yaml");
    let sets = [
        "frames=6",
        "size=48",
        "gaussians=1000",
        "init_gaussians=500",
        "base_steps=6",
        "opt_steps=3",
        "max_segments=3",
    ];
    let out = run(&d, "fox.yaml", &sets);
    assert!(out.contains("42 stages: 42 run"), "{out}");
    let md = std::fs::read_to_string(d.join("out/fox/prior/benchmark/benchmark.md")).unwrap();
    let methods =
        ["prior", "vanilla-paper", "vanilla-release", "smoothness-only", "usplat4d-paper"];
    for m in methods.iter().chain(&["usplat4d-release"]) {
        assert!(md.contains(&format!("| (120°, 180°] | {m} |")), "{m}:\n{md}");
    }
    assert!(md.contains("| ablation-c |"), "{md}");
    assert!(md.contains("| 3D EPE |"), "{md}");
    let train = d.join("out/fox/prior/eval-train/base");
    assert!(std::fs::read_dir(train).unwrap().count() > 0);
}
