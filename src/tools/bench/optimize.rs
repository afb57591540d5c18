//! `usplat4d bench optimize`: milliseconds per optimisation step (batch of training frames)
//! and peak resident memory of `optimize` on a given model and scene (e.g. the Fox scene made
//! by `synth --width 256 --height 256 --gaussians 20000`). Runs the real stage into a
//! temporary directory without checkpoints or density control and reads the per-step wall
//! times from its training log; the first step (warm-up) is left out of the mean. A second
//! table splits the mean step into its phases (render forward and backward, L_rgb, the
//! motion or graph terms, Adam, ...; [`crate::stages::optimize::timing`]), in wall time
//! and in CPU time of all threads (which a busy machine inflates far less); L_rgb's phases
//! and the motion or graph terms run side by side, so they are listed (wall time only) as
//! parts of the phase that holds them and their sum exceeds it. Peak memory
//! is the process's VmHWM. The global `--device` picks the renderer (`--device gpu` times the
//! GPU renderer, software adapters included).

use std::path::PathBuf;

use crate::context::Context;
use crate::stages::optimize::params::{OptimizeParams, Recipe};
use crate::stages::params::Profile;

/// Parameters of `usplat4d bench optimize`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BenchOptimizeParams {
    /// Model directory to start from.
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: PathBuf,
    /// Scene directory.
    #[arg(long, value_name = "SCENE_DIR")]
    pub scene: PathBuf,
    /// Recipe to time.
    #[arg(long, value_enum, default_value_t = Recipe::Vanilla)]
    pub recipe: Recipe,
    /// Profile.
    #[arg(long, value_enum, default_value_t = Profile::Paper)]
    #[serde(default)]
    pub profile: Profile,
    /// uncertainty / keynodes / edges directories (usplat4d recipe).
    #[arg(long, num_args = 3, value_names = ["UNCERTAINTY", "KEYNODES", "EDGES"])]
    #[serde(default)]
    pub graph: Option<Vec<PathBuf>>,
    /// Steps to time.
    #[arg(long, default_value_t = 5)]
    pub steps: u32,
    /// Training frames per step.
    #[arg(long, default_value_t = 8)]
    pub batch_frames: usize,
}

/// Run the benchmark and print one table row.
pub fn run(p: &BenchOptimizeParams, ctx: &Context) -> anyhow::Result<()> {
    if cfg!(debug_assertions) {
        ctx.warn(
            "bench optimize: this is a debug build; timings are meaningful only with --release",
        );
    }
    let tmp = tempfile::tempdir()?;
    let out = tmp.path().join("model");
    let g = p.graph.clone().unwrap_or_default();
    let params = OptimizeParams {
        model: p.model.clone(),
        scene: p.scene.clone(),
        out: out.clone(),
        recipe: p.recipe,
        uncertainty: g.first().cloned(),
        keynodes: g.get(1).cloned(),
        edges: g.get(2).cloned(),
        steps: p.steps,
        profile: p.profile,
        batch_frames: Some(p.batch_frames),
        seed: 0,
        checkpoint_every: Some(0),
        abort_after_step: None,
        no_loss_weighting: false,
        lr_position: None,
        lr_rotation: None,
        lr_scale: None,
        lr_opacity: None,
        lr_color: None,
        lr_sh_rest: None,
        lr_graph: None,
        lr_lengths: None,
        lambda_ssim: None,
        lambda_mask: None,
        lambda_depth: None,
        lambda_track: None,
        image_batch: None,
        track_every: None,
        track_pause: None,
        track_density_stats: None,
        lambda_graph: None,
        key_anchor_weight: None,
        nonkey_anchor_weight: None,
        anchor_metric: None,
        nonkey_metric_frame: None,
        graph_reduction: None,
        nonkey_weights: None,
        nonkey_dweight_l2: None,
        nonkey_pose_offsets: None,
        nonkey_offset_l2: None,
        nonkey_motion_weight: None,
        dqb_weight: None,
        key_motion_weight: None,
        r_z: None,
        lambda_vel: None,
        lambda_acc: None,
        edge_keep_ratio: None,
        graph_init_iters: None,
        graph_init_lr: None,
        graph_init_edge_keep: None,
        graph_init_batch: None,
        graph_init_acc: None,
        knn_k: None,
        vanilla_knn: None,
        vanilla_vel: None,
        vanilla_acc: None,
        density_start: Some(2.0),
        density_end: None,
        densify_every: None,
        opacity_reset_every: Some(0),
        densify_grad: None,
        percent_dense: None,
        prune_opacity: None,
    };
    let (phases, init_seconds) = crate::stages::optimize::train::run_timed(&params, ctx, true)?;
    let log = crate::tables::training_log::read(&out.join("training_log.parquet"))?;
    let timed: Vec<f64> = log.iter().skip(1).map(|r| r.seconds).collect();
    let per_step = 1e3 / timed.len().max(1) as f64;
    let ms = per_step * timed.iter().sum::<f64>();
    let model = crate::model::Model::load(&out)?;
    let rss = crate::tools::bench::graph::peak_rss_bytes().map_or(f64::NAN, |b| b as f64 / 1e9);
    let device = crate::stages::device::renderer(ctx)?.tag();
    println!("| recipe | profile | N | T | batch | device | ms/step | peak RSS GB | threads |");
    println!("|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {:?} | {:?} | {} | {} | {} | {device} | {ms:.0} | {rss:.2} | {} |",
        p.recipe,
        p.profile,
        model.gaussians.len(),
        model.num_frames(),
        p.batch_frames,
        rayon::current_num_threads()
    );
    println!();
    println!("| phase | wall ms/step | share | CPU ms/step |");
    println!("|---|---|---|---|");
    let (mut wall, mut cpu) = (0.0, Some(0.0));
    for (name, w, c) in &phases.totals {
        let w = per_step * w.as_secs_f64();
        if phases.parent(name).is_some() {
            // a part of the phase above, beside its other parts: wall time only
            println!("| · {name} | {w:.1} | {:.0}% | |", 100.0 * w / ms);
            continue;
        }
        let c = c.map(|c| per_step * c.as_secs_f64());
        wall += w;
        cpu = cpu.zip(c).map(|(a, b)| a + b);
        println!("| {name} | {w:.1} | {:.0}% | {} |", 100.0 * w / ms, ms_or_dash(c));
    }
    let rest = ms - wall;
    println!("| other (batch draw, buffers, log) | {rest:.1} | {:.0}% | |", 100.0 * rest / ms);
    println!("| all phases | {wall:.1} | {:.0}% | {} |", 100.0 * wall / ms, ms_or_dash(cpu));
    println!();
    println!(
        "graph initialisation before step 0: {init_seconds:.1} s; 1,600 steps with it at N = \
         {n}: {:.1} min (a real run's density control adds Gaussians, and steps slow down with \
         them)",
        (init_seconds + 1.6 * ms) / 60.0,
        n = model.gaussians.len()
    );
    Ok(())
}

fn ms_or_dash(v: Option<f64>) -> String {
    v.map_or("–".into(), |v| format!("{v:.1}"))
}
