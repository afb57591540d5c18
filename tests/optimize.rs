//! End-to-end tests of `usplat4d optimize` through the CLI on a tiny synthetic Fox scene
//! (`synth` on `pipelines/data/Fox.glb`, 8 frames at 64×64, 800 oracle Gaussians): a run
//! killed after a checkpoint and started again ends with the same bytes as an uninterrupted
//! run; the thread count does not change the bytes; L_rgb falls when the colours start
//! wrong; density control adds Gaussians with fresh ids on its schedule.
//!
//! Not validated here: the graph terms of the usplat4d recipe (unit-tested next to their
//! code) and image quality at scale (`bench optimize`, `pipelines/fox.yaml`).

use std::path::Path;

use usplat4d::model::Model;
use usplat4d::tables::Provenance;
use usplat4d::tables::key_nodes;
use usplat4d::tables::training_log::{self, LogRow};
use usplat4d::tables::uncertainty::UncertaintyReader;

use crate::util::{Dir, DriftDirection, drifted_prior, repo};

/// The scene in `dir/S` (oracle model in `dir/S/oracle`).
fn tiny_fox(dir: &Dir) {
    let gltf = repo().join("pipelines/data/Fox.glb");
    let args = ["synth", "--gltf", gltf.to_str().unwrap(), "--animation", "Walk", "--out", "S"];
    let size = ["--frames", "8", "--width", "64", "--height", "64", "--gaussians", "800"];
    dir.ok(&[&args[..], &size[..]].concat());
}

/// A start model: the oracle with every colour replaced by mid-grey.
fn grey_model(dir: &Dir) {
    let m = Model::load(&dir.join("S/oracle")).unwrap();
    let mut g = m.gaussians.clone();
    g.color.iter_mut().for_each(|c| *c = [0.5; 3]);
    let frames: Vec<_> = (0..m.num_frames()).map(|t| m.frame(t)).collect();
    Model::save(&dir.join("grey"), &g, frames, &Provenance::default()).unwrap();
}

/// A directory holding the tiny Fox scene and its grey start model.
fn grey_fox() -> Dir {
    let dir = Dir::new();
    tiny_fox(&dir);
    grey_model(&dir);
    dir
}

fn optimize(dir: &Dir, out: &str, extra: &[&str]) -> std::process::Output {
    let base = ["optimize", "--model", "grey", "--scene", "S", "--recipe", "vanilla"];
    dir.run(&[&base[..], &["--out", out], extra].concat())
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The log without its wall-clock column.
fn log_rows(dir: &Path) -> Vec<LogRow> {
    let mut rows = training_log::read(&dir.join("training_log.parquet")).unwrap();
    rows.iter_mut().for_each(|r| r.seconds = 0.0);
    rows
}

fn assert_same_outputs(a: &Path, b: &Path) {
    for f in ["gaussians.parquet", "trajectories.parquet"] {
        assert!(read(&a.join(f)) == read(&b.join(f)), "{f} differs between {a:?} and {b:?}");
    }
    assert_eq!(log_rows(a), log_rows(b));
}

fn ok(out: std::process::Output) {
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// Move finished output `R` to `name` (runs compared byte for byte must write to the same
/// path: it is part of the provenance).
fn keep_as(dir: &Dir, name: &str) {
    std::fs::rename(dir.join("R"), dir.join(name)).unwrap();
}

#[test]
fn killed_run_resumes_from_its_checkpoint_with_the_same_bytes() {
    let dir = grey_fox();
    let common = ["--steps", "6", "--checkpoint-every", "2", "--batch-frames", "3"];
    ok(optimize(&dir, "R", &common));
    assert!(!dir.join("R.ckpt").exists(), "a finished run removes its checkpoint");
    keep_as(&dir, "A");
    let killed = optimize(&dir, "R", &[&common[..], &["--abort-after-step", "4"]].concat());
    assert!(!killed.status.success(), "the run must die after step 4");
    assert!(dir.join("R.ckpt/checkpoint.bin").exists());
    assert!(!dir.join("R/training_log.parquet").exists(), "no output before the end");
    ok(optimize(&dir, "R", &common));
    assert_same_outputs(&dir.join("A"), &dir.join("R"));
    let rows = log_rows(&dir.join("A"));
    assert_eq!(rows.iter().map(|r| r.step).collect::<Vec<_>>(), (0..6).collect::<Vec<_>>());
}

#[test]
fn same_bytes_whatever_the_thread_count_and_the_loss_falls() {
    let dir = grey_fox();
    let common = ["--steps", "12", "--batch-frames", "4", "--lr-color", "0.05"];
    ok(optimize(&dir, "R", &[&["--threads", "1"][..], &common[..]].concat()));
    keep_as(&dir, "T1");
    ok(optimize(&dir, "R", &[&["--threads", "2"][..], &common[..]].concat()));
    keep_as(&dir, "T2");
    assert_same_outputs(&dir.join("T1"), &dir.join("T2"));
    // 6 threads: the batch's image losses in groups of 3 frames, a stream wave per thread
    ok(optimize(&dir, "R", &[&["--threads", "6"][..], &common[..]].concat()));
    keep_as(&dir, "T6");
    assert_same_outputs(&dir.join("T1"), &dir.join("T6"));
    let rows = log_rows(&dir.join("T1"));
    let first: f64 = rows[..3].iter().map(|r| r.loss).sum();
    let last: f64 = rows[rows.len() - 3..].iter().map(|r| r.loss).sum();
    println!("vanilla on grey colours: loss {:.4} -> {:.4}", first / 3.0, last / 3.0);
    assert!(last < 0.8 * first, "loss {first} -> {last}");
    // the output is a model every other stage reads
    dir.ok(&["check", "T1"]);
}

/// `--image-batch sum` (the release's) adds the batch frames' image terms where `mean`
/// averages them: at step 0 (the same model) each term is the batch size times as large.
#[test]
fn image_batch_sum_adds_the_frames_terms() {
    let dir = grey_fox();
    let common = ["--steps", "1", "--batch-frames", "4", "--profile", "release"];
    let rgb = |reduction: &str| {
        ok(optimize(&dir, reduction, &[&common[..], &["--image-batch", reduction]].concat()));
        let row = &log_rows(&dir.join(reduction))[0];
        row.terms.iter().find(|(k, _)| k == "rgb").unwrap().1
    };
    let (mean, sum) = (rgb("mean"), rgb("sum"));
    assert!(mean > 0.0 && (sum - 4.0 * mean).abs() < 1e-9 * sum, "sum {sum}, mean {mean}");
}

#[test]
fn density_control_adds_gaussians_with_fresh_ids() {
    let dir = grey_fox();
    let schedule = ["--density-start", "0", "--densify-every", "2", "--densify-grad", "0"];
    ok(optimize(
        &dir,
        "D",
        &[&["--steps", "3", "--batch-frames", "2"][..], &schedule[..]].concat(),
    ));
    let before = Model::load(&dir.join("grey")).unwrap();
    let after = Model::load(&dir.join("D")).unwrap();
    let max_in = *before.gaussians.id.iter().max().unwrap();
    let new = after.gaussians.id.iter().filter(|i| **i > max_in).count();
    let rows = log_rows(&dir.join("D"));
    println!(
        "density control: {} -> {} Gaussians ({new} new)",
        before.gaussians.len(),
        after.gaussians.len()
    );
    assert!(new > 0, "every visible Gaussian passes a zero threshold");
    assert_eq!(rows[2].num_gaussians as usize, after.gaussians.len());
    assert_eq!(rows[1].num_gaussians, rows[0].num_gaussians, "inactive at step 1");
    assert_eq!(after.num_frames(), before.num_frames());
}

/// The graph stages on `model` with `profile` into `U_`, `K_`, `E_` + profile.
fn graph_stages(dir: &Dir, model: &str, profile: &str) {
    let (u, k, e) = (format!("U_{profile}"), format!("K_{profile}"), format!("E_{profile}"));
    let m = ["--model", model, "--profile", profile];
    dir.ok(&[&["uncertainty"][..], &m[..], &["--scene", "S", "--out", &u]].concat());
    dir.ok(&[&["keynodes"][..], &m[..], &["--uncertainty", &u, "--out", &k]].concat());
    let e_args = ["--scene", "S", "--uncertainty", &u, "--keynodes", &k, "--out", &e];
    dir.ok(&[&["edges"][..], &m[..], &e_args[..]].concat());
}

fn usplat4d_args(profile: &str) -> Vec<String> {
    let (u, k, e) = (format!("U_{profile}"), format!("K_{profile}"), format!("E_{profile}"));
    ["--recipe", "usplat4d", "--profile", profile, "--uncertainty", &u, "--keynodes", &k]
        .iter()
        .map(|s| s.to_string())
        .chain(["--edges".to_string(), e])
        .collect()
}

#[test]
fn usplat4d_recipe_writes_a_model_its_roles_and_the_learned_graph() {
    let dir = Dir::new();
    tiny_fox(&dir);
    for profile in ["paper", "release"] {
        graph_stages(&dir, "S/oracle", profile);
        let out = format!("O_{profile}");
        let mut args: Vec<String> =
            ["optimize", "--model", "S/oracle", "--scene", "S", "--out", &out, "--steps", "4"]
                .iter()
                .map(|s| s.to_string())
                .collect();
        args.extend(usplat4d_args(profile));
        args.extend(
            ["--batch-frames", "2", "--density-start", "0", "--densify-every", "2"]
                .map(String::from),
        );
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        dir.ok(&a);
        let rows = log_rows(&dir.join(&out));
        let terms: Vec<&str> = rows[0].terms.iter().map(|(k, _)| k.as_str()).collect();
        println!("usplat4d [{profile}] terms at step 0: {:?}", rows[0].terms);
        assert!(terms.contains(&"nonkey_dqb") && terms.contains(&"key_rigidity"), "{terms:?}");
        let keys =
            usplat4d::tables::key_nodes::read(&dir.join(&out).join("key_nodes.parquet")).unwrap();
        let model = Model::load(&dir.join(&out)).unwrap();
        assert!(keys.id.iter().all(|i| model.gaussians.id.contains(i)));
        dir.ok(&["check", &out]);
        dir.ok(&["segment", "--edges", &out, "--out", &format!("G_{profile}")]);
    }
    // a killed usplat4d run resumes with the same bytes too (graph tensors in the checkpoint)
    let resume = |out: &str, extra: &[&str]| {
        let mut args: Vec<String> =
            ["optimize", "--model", "S/oracle", "--scene", "S", "--out", out, "--steps", "4"]
                .iter()
                .map(|s| s.to_string())
                .collect();
        args.extend(usplat4d_args("release"));
        args.extend(["--batch-frames", "2", "--checkpoint-every", "2"].map(String::from));
        args.extend(extra.iter().map(|s| s.to_string()));
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        dir.run(&a)
    };
    ok(resume("R", &[]));
    keep_as(&dir, "UA");
    assert!(!resume("R", &["--abort-after-step", "2"]).status.success());
    ok(resume("R", &[]));
    assert_same_outputs(&dir.join("UA"), &dir.join("R"));
    assert!(read(&dir.join("UA/edges.parquet")) == read(&dir.join("R/edges.parquet")));
    // ablation (c) runs too
    let mut args: Vec<String> =
        ["optimize", "--model", "S/oracle", "--scene", "S", "--out", "C", "--steps", "2"]
            .iter()
            .map(|s| s.to_string())
            .collect();
    args.extend(usplat4d_args("paper"));
    args.push("--no-loss-weighting".into());
    let a: Vec<&str> = args.iter().map(String::as_str).collect();
    dir.ok(&a);
    // the release's non-key weights need the edges stage's λ and distance unit: the learned
    // graph keeps them, a table without them is an error naming it
    let meta = |path: &str| {
        usplat4d::tables::io::TableReader::open::<usplat4d::tables::edges::EdgesTable>(
            &dir.join(path),
        )
        .unwrap()
        .metadata_value(usplat4d::stages::edges::GRAPH_KEY)
    };
    assert_eq!(meta("O_release/edges.parquet"), meta("E_release/edges.parquet"));
    let edges = usplat4d::tables::edges::read(&dir.join("E_release/edges.parquet")).unwrap();
    std::fs::create_dir_all(dir.join("E_bare")).unwrap();
    let bare = dir.join("E_bare/edges.parquet");
    usplat4d::tables::edges::write(&bare, &edges, &Provenance::default()).unwrap();
    let mut args: Vec<String> =
        ["optimize", "--model", "S/oracle", "--scene", "S", "--out", "B", "--steps", "1"]
            .iter()
            .map(|s| s.to_string())
            .collect();
    args.extend(usplat4d_args("release"));
    *args.last_mut().unwrap() = "E_bare".into();
    let a: Vec<&str> = args.iter().map(String::as_str).collect();
    let err = dir.fails(&a, 2);
    assert!(
        err.contains(&format!(
            "{}: no 'usplat4d.graph' metadata (non-key weight sharpness and distance unit)",
            std::path::Path::new("E_bare").join("edges.parquet").display()
        )),
        "{err}"
    );
}

/// Distance to the oracle of each (Gaussian, frame) pair of `pairs`, by id (`None` when the
/// model no longer has that Gaussian, e.g. culled by the release's key-node selection).
fn drift_errors(
    model: &Path,
    oracle: &[Vec<[f32; 3]>],
    ids: &[u32],
    pairs: &[(usize, usize)],
) -> Vec<Option<f64>> {
    let m = Model::load(model).unwrap();
    let at: std::collections::HashMap<u32, usize> =
        m.gaussians.id.iter().enumerate().map(|(r, &i)| (i, r)).collect();
    let frames: Vec<_> = (0..m.num_frames()).map(|t| m.frame(t).unwrap().position).collect();
    pairs
        .iter()
        .map(|&(i, t)| {
            let p = frames[t][*at.get(&ids[i])?];
            Some((0..3).map(|k| ((p[k] - oracle[t][i][k]) as f64).powi(2)).sum::<f64>().sqrt())
        })
        .collect()
}

/// Means of each run's errors over the pairs every run still has.
fn common_means(runs: &[Vec<Option<f64>>]) -> (usize, Vec<f64>) {
    let keep: Vec<usize> =
        (0..runs[0].len()).filter(|&k| runs.iter().all(|r| r[k].is_some())).collect();
    let mean = |r: &Vec<Option<f64>>| {
        keep.iter().map(|&k| r[k].unwrap_or(0.0)).sum::<f64>() / keep.len().max(1) as f64
    };
    (keep.len(), runs.iter().map(mean).collect())
}

/// Mean PSNR of `model`'s renders of the scene `S`'s evaluation views in the view range
/// (120°, 180°] (the far views of `evaluate`).
fn far_view_psnr(dir: &Dir, model: &str) -> f64 {
    let (r, e) = (format!("{model}_renders"), format!("{model}_eval"));
    dir.ok(&["render", "--model", model, "--scene", "S", "--split", "eval", "--out", &r]);
    dir.ok(&["evaluate", "--renders", &r, "--scene", "S", "--out", &e, "--lpips", "off"]);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(&e).join("summary.json")).unwrap())
            .unwrap();
    let far = json["groups"].as_array().unwrap().iter().find(|g| g["label"] == "(120°, 180°]");
    far.and_then(|g| g["psnr"].as_f64()).expect("far views in the evaluation")
}

/// The smoothness-only baseline of the benchmark pipelines: the usplat4d recipe with every
/// anchor and graph weight at 0, leaving L_rgb and the profile's velocity and acceleration
/// terms.
const SMOOTHNESS_ONLY: [&str; 6] =
    ["--key-anchor-weight", "0", "--nonkey-anchor-weight", "0", "--lambda-graph", "0"];

/// The runs of the recovery test on one drifted prior `drifted` in `dir` (scene `S`): each
/// run's name, its errors at the drifted pairs and its far-view PSNR. Runs: the prior,
/// vanilla, usplat4d paper, usplat4d paper with the release's anchor metric, usplat4d paper
/// with the non-keys' metric of their most reliable frame, the smoothness-only baseline,
/// usplat4d release (with its graph initialisation) and usplat4d release without it, each
/// for `steps` steps.
fn recovery_runs(
    dir: &Dir,
    truth: &[Vec<[f32; 3]>],
    ids: &[u32],
    pairs: &[(usize, usize)],
    steps: u32,
) -> Vec<(String, Vec<Option<f64>>, f64)> {
    let steps = steps.to_string();
    let common = ["--model", "drifted", "--scene", "S", "--steps", &steps, "--lr-position", "0.01"];
    dir.ok(&[&["optimize", "--recipe", "vanilla", "--out", "V"][..], &common[..]].concat());
    let mut names = vec!["drifted".to_string(), "V".to_string()];
    for (profile, out, extra) in [
        ("paper", "G_paper", &[][..]),
        ("paper", "G_paper_release_metric", &["--anchor-metric", "release"][..]),
        ("paper", "G_paper_most_reliable", &["--nonkey-metric-frame", "most-reliable"][..]),
        ("paper", "G_smoothness_only", &SMOOTHNESS_ONLY[..]),
        ("release", "G_release", &[][..]),
        ("release", "G_release_noinit", &["--graph-init-iters", "0"][..]),
    ] {
        if !dir.join(&format!("E_{profile}")).exists() {
            graph_stages(dir, "drifted", profile);
        }
        let mut a: Vec<String> =
            ["optimize", "--out", out].iter().chain(&common).map(|s| s.to_string()).collect();
        a.extend(usplat4d_args(profile));
        a.extend(extra.iter().map(|s| s.to_string()));
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        dir.ok(&a);
        names.push(out.to_string());
    }
    names
        .iter()
        .map(|m| (m.clone(), drift_errors(&dir.join(m), truth, ids, pairs), far_view_psnr(dir, m)))
        .collect()
}

/// The priors of the recovery test: the drifted Gaussians and frames are the same in each
/// (a seeded half of the dynamic Gaussians, at the frames the training camera does not see
/// them in the oracle), displaced by a tenth of the bounding-box diagonal.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Prior {
    /// One random direction per Gaussian: most drifted points come out from behind their
    /// occluders, so the prior's drift is seen by the training camera.
    Random,
    /// Random directions drawn again until the training camera does not see the drifted
    /// point at any drifted frame ([`hidden_directions`]).
    RandomHidden,
    /// Along the training camera's viewing ray, away from it: an occluded point stays
    /// occluded, as under a monocular depth error.
    AlongRays,
}

impl Prior {
    fn label(self) -> &'static str {
        match self {
            Prior::Random => "random directions",
            Prior::RandomHidden => "random directions kept hidden",
            Prior::AlongRays => "along the viewing rays",
        }
    }
}

/// The displacement of the recovery priors, as a fraction of the bounding-box diagonal.
const RECOVERY_DRIFT: f32 = 0.1;

/// Pixels each Gaussian of `model` covers in each training frame's render, `[T][N]` (an
/// `uncertainty` run on scene `S` into `dir/out`).
fn covered_pixels(dir: &Dir, model: &str, out: &str) -> Vec<Vec<u32>> {
    dir.ok(&["uncertainty", "--model", model, "--scene", "S", "--out", out]);
    let u = UncertaintyReader::open(&dir.join(out).join("uncertainty.parquet")).unwrap();
    (0..u.num_frames()).map(|t| u.frame(t).unwrap().n_pixels).collect()
}

/// Directions for [`Prior::RandomHidden`] (seed 11): every Gaussian whose drifted point the
/// training camera sees at one of its drifted frames gets a new random direction, up to
/// `REDRAWS` times, and after that none (it is not drifted).
fn hidden_directions(dir: &Dir, oracle: &Model, seen: &[Vec<u32>]) -> Vec<Option<[f64; 3]>> {
    const REDRAWS: usize = 8;
    let mut rng = usplat4d::util::rng::Rng::new(11);
    let mut draw = || Some([rng.normal(), rng.normal(), rng.normal()]);
    let mut dirs: Vec<_> = (0..oracle.gaussians.len()).map(|_| draw()).collect();
    for round in 0.. {
        let given = (RECOVERY_DRIFT, DriftDirection::Given(&dirs));
        let drift = drifted_prior(dir, oracle, |i, t| seen[t][i] == 0, given, 0);
        let covered = covered_pixels(dir, "drifted", &format!("U_hidden_{round}"));
        let mut visible: Vec<usize> =
            drift.pairs().into_iter().filter(|&(i, t)| covered[t][i] > 0).map(|p| p.0).collect();
        visible.dedup();
        if visible.is_empty() {
            break;
        }
        for i in visible {
            dirs[i] = if round < REDRAWS { draw() } else { None };
        }
    }
    dirs
}

/// For each drifted pair, whether its Gaussian's most reliable frame t̂ under the paper
/// profile (`K_paper`) is one of its drifted frames.
fn t_hat_drifted(dir: &Dir, ids: &[u32], pairs: &[(usize, usize)]) -> Vec<bool> {
    let keys = key_nodes::read(&dir.join("K_paper/key_nodes.parquet")).unwrap();
    let t_hat = |i: usize| {
        let row = keys.id.iter().position(|&g| g == ids[i]).unwrap();
        keys.t_hat[row] as usize
    };
    pairs.iter().map(|&(i, _)| pairs.contains(&(i, t_hat(i)))).collect()
}

/// What the paper profile's uncertainty made of a prior's drift: the drifted pairs the
/// training camera sees in the prior, and those of them whose convergence indicator holds
/// (`U_paper`).
fn drift_seen(dir: &Dir, ids: &[u32], pairs: &[(usize, usize)]) -> (usize, usize) {
    let u = UncertaintyReader::open(&dir.join("U_paper/uncertainty.parquet")).unwrap();
    let frames: Vec<_> = (0..u.num_frames()).map(|t| u.frame(t).unwrap()).collect();
    let row = |i: usize| u.ids().iter().position(|&g| g == ids[i]).unwrap();
    let seen = pairs.iter().filter(|&&(i, t)| frames[t].n_pixels[row(i)] > 0).count();
    let passed = pairs.iter().filter(|&&(i, t)| frames[t].converged[row(i)]).count();
    (seen, passed)
}

/// The recovery test of issue 11: a prior whose trajectories drift in the frames where points
/// are not seen by the training camera (as `graph_fox` builds it: [`Prior::Random`], the
/// assertions). After the same number of steps, the usplat4d recipe (paper profile, the
/// default) should leave the drifted pairs closer to the ground truth than the vanilla
/// recipe and render the far views ((120°, 180°]) better. Printed besides: the same
/// Gaussians drifted in random directions that keep them hidden ([`Prior::RandomHidden`])
/// and along the viewing rays ([`Prior::AlongRays`]), and each prior's errors split by
/// whether the Gaussian's most reliable frame t̂ (paper profile) is one of its drifted frames.
///
/// Ignored because neither assertion holds. Measured (debug build, `cargo test --test tests
/// usplat4d_brings -- --ignored --nocapture`; error at the drifted pairs from 0.195,
/// far-view PSNR in dB; release runs on the pairs they keep, vanilla there in brackets;
/// vanilla with the base model's weights, the default since 54bd25e):
///
/// | run | random: error | PSNR | hidden (12 pairs): error | PSNR | along rays: error | PSNR |
/// |---|---|---|---|---|---|---|
/// | prior | 0.195 | 23.50 | 0.195 | 23.96 | 0.195 | 23.37 |
/// | vanilla | 0.074 | 23.67 | 0.050 | 24.01 | 0.072 | 23.69 |
/// | vanilla, App. A.2's weights (before 54bd25e) | 0.099 | 22.06 | 0.055 | 22.24 | 0.074 | 21.90 |
/// | usplat4d paper | 0.120 | 23.44 | 0.059 | 24.02 | 0.072 | 23.79 |
/// | paper, `--anchor-metric release` | 0.149 | 22.27 | 0.104 | 22.59 | 0.101 | 22.54 |
/// | paper, `--nonkey-metric-frame most-reliable` | 0.146 | 23.84 | 0.156 | 24.19 | 0.121 | 23.84 |
/// | smoothness only (no anchor or graph term) | 0.089 | 23.65 | 0.063 | 24.12 | 0.083 | 23.81 |
/// | usplat4d release | 0.261 (0.074) | 19.07 | 0.299 (0.046) | 19.14 | 0.326 (0.058) | 19.12 |
/// | release, `--graph-init-iters 0` | 0.112 (0.074) | 22.63 | 0.076 (0.046) | 22.70 | 0.079 (0.058) | 22.62 |
///
/// (The release rows since c1b4d92, whose release profile adds the batch frames' image terms
/// and follows the release's track schedule; before 782d420 they were 0.225, 0.298 and 0.288
/// with 19.35, 19.29 and 19.28 dB, and without the graph initialisation 0.115, 0.075 and
/// 0.081 with 22.98, 22.96 and 22.98 dB.)
///
/// On the random prior the drift is mostly in view: the training camera sees 131 of the 142
/// drifted pairs in the prior (the displaced point comes out from behind its occluder) and 90
/// of them pass Eq. 4's colour test (the fox is nearly one colour: the textureless case of the
/// paper's Appendix on challenging cases, where wrong priors pass for right), so the
/// uncertainty stage trusts them; for 24 of the 61 drifted Gaussians (69 pairs) it picks a
/// drifted frame as t̂, where the drifted point is in view. There the U⁻¹-weighted anchor
/// holds the drift and DQB, relative to t̂, carries it to the other frames: paper 0.157
/// against vanilla 0.085. On the 73 pairs whose t̂ is clean vanilla is the closer too (0.063
/// against 0.085). A base model's drift is one its training views do not show, which the
/// other two priors keep: along the rays the two are level (0.072) and usplat4d renders the
/// far views better; random directions kept hidden leave only 12 drifted pairs (10 Gaussians;
/// most directions bring a point into view within 8 redraws), too few to assert on, and there
/// vanilla is the closer (0.050 against 0.059), as its kNN and smoothness terms average the
/// independent drifts of neighbours while a non-key is tied to its keys, and the parts the
/// camera never sees (the far legs) get none.
///
/// `USPLAT4D_RECOVERY_STEPS=N` runs N steps instead of 30 (same assertions). At 150 steps,
/// the length of the benchmark pipelines' branches (`USPLAT4D_RECOVERY_STEPS=150` before the
/// same command; build of e36e920; same columns as above):
///
/// | run | random: error | PSNR | hidden (12 pairs): error | PSNR | along rays: error | PSNR |
/// |---|---|---|---|---|---|---|
/// | vanilla | 0.088 | 22.55 | 0.080 | 22.91 | 0.087 | 22.81 |
/// | usplat4d paper | 0.135 | 23.87 | 0.074 | 23.89 | 0.084 | 23.86 |
/// | smoothness only | 0.094 | 23.75 | 0.085 | 23.53 | 0.093 | 23.32 |
///
/// The vanilla continuation's far views fall below the prior on all three, and on the two
/// priors whose drift the training views do not show usplat4d is ahead on both criteria. On
/// the random prior it renders the far views 1.3 dB better but leaves the drifted points
/// farther: level with vanilla on the 73 pairs whose t̂ is clean (0.088 against 0.086),
/// 0.185 against 0.090 on the 69 whose t̂ is drifted. (With App. A.2's vanilla weights, before
/// 54bd25e, vanilla reached 0.093 and 0.092 on the random and along-ray priors with 19.76 and
/// 19.55 dB; usplat4d's rows were the same.)
#[test]
#[ignore = "issue 11's recovery criteria do not hold on the random prior (see the doc comment)"]
fn usplat4d_brings_drifted_points_closer_than_vanilla() {
    let steps: u32 =
        std::env::var("USPLAT4D_RECOVERY_STEPS").ok().and_then(|v| v.parse().ok()).unwrap_or(30);
    let mut assertions = None;
    for prior in [Prior::Random, Prior::RandomHidden, Prior::AlongRays] {
        let dir = Dir::new();
        let gltf = repo().join("pipelines/data/Fox.glb");
        let args = ["synth", "--gltf", gltf.to_str().unwrap(), "--animation", "Walk", "--out", "S"];
        let size = ["--frames", "12", "--width", "96", "--height", "96", "--gaussians", "1500"];
        dir.ok(&[&args[..], &size[..]].concat());
        let seen = covered_pixels(&dir, "S/oracle", "U0");
        let oracle = Model::load(&dir.join("S/oracle")).unwrap();
        let (nt, ids) = (oracle.num_frames(), &oracle.gaussians.id);
        let truth: Vec<Vec<[f32; 3]>> =
            (0..nt).map(|t| oracle.frame(t).unwrap().position).collect();
        let scene = usplat4d::scene::Scene::load(&dir.join("S")).unwrap();
        let centres: Vec<[f64; 3]> =
            scene.train_by_frame().iter().map(|c| c.center().to_array()).collect();
        let hidden;
        let towards = match prior {
            Prior::Random => DriftDirection::Random,
            Prior::RandomHidden => {
                hidden = hidden_directions(&dir, &oracle, &seen);
                DriftDirection::Given(&hidden)
            }
            Prior::AlongRays => DriftDirection::AwayFrom(&centres),
        };
        let drift =
            drifted_prior(&dir, &oracle, |i, t| seen[t][i] == 0, (RECOVERY_DRIFT, towards), 0);
        let pairs = drift.pairs();
        let runs = recovery_runs(&dir, &truth, ids, &pairs, steps);
        let errors: Vec<_> = runs.iter().map(|r| r.1.clone()).collect();
        // The runs before the release profile's on every drifted pair; all runs on the pairs
        // the release keeps (it culls most non-keys).
        let before_release = runs.iter().take_while(|r| !r.0.starts_with("G_release")).count();
        let ((n_all, m_all), (n_kept, m_kept)) =
            (common_means(&errors[..before_release]), common_means(&errors));
        let (n_seen, n_passed) = drift_seen(&dir, ids, &pairs);
        let t_hat = t_hat_drifted(&dir, ids, &pairs);
        println!(
            "recovery, drift {:.3} in {}, {} drifted pairs, {steps} steps; the training camera \
             sees {n_seen} of them in the prior, {n_passed} pass Eq. 4; t̂ (paper) is a drifted \
             frame at {}:",
            drift.offset,
            prior.label(),
            pairs.len(),
            t_hat.iter().filter(|d| **d).count()
        );
        for (k, (m, _, psnr)) in runs.iter().enumerate() {
            let first = m_all.get(k).map_or("-".to_string(), |e| format!("{e:.4}"));
            println!(
                "  {m:>22}: error {first} on {n_all} pairs, {:.4} on the {n_kept} the release keeps; \
                 far-view PSNR {psnr:.2} dB",
                m_kept[k]
            );
        }
        for (drifted_t_hat, label) in [(false, "clean"), (true, "drifted")] {
            let part: Vec<Vec<Option<f64>>> = errors[..before_release]
                .iter()
                .map(|e| {
                    e.iter().zip(&t_hat).filter(|p| *p.1 == drifted_t_hat).map(|p| *p.0).collect()
                })
                .collect();
            let (n, m) = common_means(&part);
            if n == 0 {
                continue;
            }
            let means: Vec<String> =
                runs.iter().zip(&m).map(|(r, e)| format!("{} {e:.4}", r.0)).collect();
            println!("  the {n} pairs whose t̂ is {label}: {}", means.join(", "));
        }
        if prior == Prior::Random {
            assertions = Some((n_all, m_all, runs.iter().map(|r| r.2).collect::<Vec<_>>()));
        }
    }
    let (n, error, psnr) = assertions.unwrap();
    assert!(n >= 50, "only {n} drifted pairs");
    assert!(error[2] < error[1], "usplat4d (paper) {:.4} vs vanilla {:.4}", error[2], error[1]);
    assert!(
        psnr[2] > psnr[1],
        "far views: usplat4d (paper) {:.2} vs vanilla {:.2}",
        psnr[2],
        psnr[1]
    );
}
