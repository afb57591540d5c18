//! `usplat4d init`: an initial 4D Gaussian model lifted from what a monocular pipeline has —
//! the training cameras, their RGB images and foreground masks, the depth prior and the 2D
//! tracks prior with visibility (the files `priors.json` names; never `tracks_3d`, the
//! oracle model or the evaluation views).
//!
//! Steps (streamed by frame where the data allows):
//! 1. [`lift`]: every frame's visible tracks are unprojected with the depth prior.
//! 2. [`motion`]: tracks are filled where hidden and each track's neighbourhood gets a
//!    per-frame rigid fit (weighted Procrustes from the canonical frame), giving nodes with a
//!    position and an orientation at every frame, optionally smoothed over time
//!    (`--temporal-sigma`).
//! 3. [`seed`]: N Gaussians are sampled on the masked depth of R reference frames spread
//!    over the video (the orbit shows every side), coloured from the image, sized by SoM's
//!    3-NN rule, opacity 0.7 (Shape of Motion's `init_fg_from_tracks_3d`; 3DGS's 0.1 suits
//!    densification from sparse points, while ours are dense and must cover the image from
//!    the start), and skinned to their K nearest nodes; their trajectories are the blended
//!    node motions, written frame by frame.
//!
//! Why per-frame rigid fits of track neighbourhoods rather than SoM's global motion bases:
//! the nodes are the tracks themselves (as in MoSca's scaffold), so no clustering or
//! basis-count choice is needed, every articulated part moves with its own nearby tracks,
//! and the fits give each Gaussian a rotation, not only a translation. SoM's bases are
//! fitted by the same weighted Procrustes, per cluster instead of per neighbourhood.

mod lift;
mod motion;
mod seed;

use std::path::PathBuf;

use anyhow::Context as _;
use rayon::prelude::*;

use crate::context::Context;
use crate::model::{FrameState, Gaussians, Model};
use crate::scene::Scene;
use crate::tables::Provenance;
use crate::tables::tracks_2d::{Tracks2dFrame, Tracks2dReader};
use crate::util::rng::{Rng, mix as splitmix64};

/// Parameters of `usplat4d init`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct InitParams {
    /// Scene directory (training cameras, images, masks and the priors of `priors.json`).
    #[arg(long, help_heading = "Inputs")]
    pub scene: PathBuf,
    /// Output model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, help_heading = "Outputs")]
    pub out: PathBuf,
    /// Number of foreground Gaussians N.
    #[arg(long, default_value_t = 20000, help_heading = "Gaussians")]
    #[serde(default = "defaults::gaussians")]
    pub gaussians: u32,
    /// Number of reference frames R the Gaussians are sampled on (spread evenly over T).
    #[arg(long, default_value_t = 8, help_heading = "Gaussians")]
    #[serde(default = "defaults::reference_frames")]
    pub reference_frames: u32,
    /// Initial opacity of every Gaussian.
    #[arg(long, default_value_t = 0.7, help_heading = "Gaussians")]
    #[serde(default = "defaults::opacity")]
    pub opacity: f32,
    /// Tracks per neighbourhood fit and nodes per Gaussian K.
    #[arg(long, default_value_t = 8, help_heading = "Motion")]
    #[serde(default = "defaults::neighbors")]
    pub neighbors: u32,
    /// σ, in frames, of the Gaussian that smooths every node's motion over time (0: none, the
    /// per-frame fits as they are).
    #[arg(long, default_value_t = 0.0, help_heading = "Motion")]
    #[serde(default)]
    pub temporal_sigma: f64,
    /// Seed of the sampling.
    #[arg(long, default_value_t = 0, help_heading = "Gaussians")]
    #[serde(default)]
    pub seed: u64,
}

mod defaults {
    pub fn gaussians() -> u32 {
        20000
    }
    pub fn reference_frames() -> u32 {
        8
    }
    pub fn opacity() -> f32 {
        0.7
    }
    pub fn neighbors() -> u32 {
        8
    }
}

/// What [`init`] made.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Gaussians N.
    pub gaussians: usize,
    /// Frames T.
    pub frames: usize,
    /// Tracks in the prior M.
    pub tracks: usize,
    /// Tracks kept as nodes (observed in two frames or more).
    pub nodes: usize,
    /// The canonical frame.
    pub canonical: usize,
}

/// Run the stage.
pub fn run(p: &InitParams, ctx: &Context) -> anyhow::Result<()> {
    let t0 = std::time::Instant::now();
    let s = init(p, ctx)?;
    ctx.info(format!(
        "init: {} Gaussians over {} frames from {} of {} tracks (canonical frame {}) in {}, {:.1} s",
        s.gaussians,
        s.frames,
        s.nodes,
        s.tracks,
        s.canonical,
        p.out.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(())
}

fn check(p: &InitParams) -> anyhow::Result<()> {
    anyhow::ensure!(p.gaussians > 0, "--gaussians: must be at least 1");
    anyhow::ensure!(p.reference_frames > 0, "--reference-frames: must be at least 1");
    anyhow::ensure!(p.neighbors >= 3, "--neighbors: must be at least 3");
    anyhow::ensure!(
        p.temporal_sigma.is_finite() && p.temporal_sigma >= 0.0,
        "--temporal-sigma: must be a finite number ≥ 0, got {}",
        p.temporal_sigma
    );
    anyhow::ensure!(p.opacity > 0.0 && p.opacity <= 1.0, "--opacity: must be in (0, 1]");
    Ok(())
}

/// Build the initial model of `p` (see the module doc).
pub fn init(p: &InitParams, ctx: &Context) -> anyhow::Result<Summary> {
    check(p)?;
    let scene = Scene::load(&p.scene)?;
    let cams = scene.train_by_frame();
    let tn = cams.len();
    anyhow::ensure!(tn > 0, "{}: the scene has no training camera", p.scene.display());
    let inputs = scene.monocular_inputs()?;
    let tracks_path = scene.resolve(&inputs.tracks_2d);
    let reader = Tracks2dReader::open(&tracks_path)?;
    anyhow::ensure!(
        reader.num_frames() == tn,
        "{}: {} frames of tracks, the scene has {tn} training frames",
        tracks_path.display(),
        reader.num_frames()
    );
    let m = reader.num_tracks();
    let tracks: Vec<Tracks2dFrame> = (0..tn).map(|t| reader.frame(t)).collect::<Result<_, _>>()?;
    let r = (p.reference_frames as usize).min(tn);
    let refs: Vec<usize> = (0..r).map(|i| i * tn / r).collect();

    // 1. Lift the visible tracks, keeping the reference frames' inputs.
    let bar = ctx.progress(tn as u64, "lift");
    let lifted: Vec<(Vec<Option<glam::Vec3>>, Option<lift::FrameInputs>)> = (0..tn)
        .into_par_iter()
        .map(|t| -> anyhow::Result<_> {
            let cam = cams[t];
            let is_ref = refs.contains(&t);
            let f = lift::read_frame(
                cam,
                inputs.depth_path(&scene, cam),
                cam.mask_path.as_deref().map(|m| scene.resolve(m)),
                is_ref.then(|| scene.resolve(&cam.image_path)),
            )?;
            bar.inc(1);
            Ok((f.lift_tracks(&tracks[t]), is_ref.then_some(f)))
        })
        .collect::<anyhow::Result<_>>()?;
    bar.finish_and_clear();
    let mut obs = motion::Observations { num_frames: tn, num_tracks: m, pos: Vec::new() };
    let mut frames_in = Vec::new();
    for (pos, f) in lifted {
        obs.pos.extend(pos);
        frames_in.push(f);
    }

    // 2. Nodes.
    let k = p.neighbors as usize;
    let mut nodes = motion::fit_nodes(&obs, k).with_context(|| {
        format!(
            "{}: fewer than 3 tracks are visible on valid foreground depth in two frames or more",
            tracks_path.display()
        )
    })?;
    motion::smooth_in_time(&mut nodes, tn, p.temporal_sigma);

    // 3. Gaussians on the reference frames' masked depth.
    let n = p.gaussians as usize;
    let per_ref: Vec<seed::Seeds> = refs
        .par_iter()
        .enumerate()
        .map(|(i, &t)| {
            let count = n / r + usize::from(i < n % r);
            let mut rng = Rng::from_state(splitmix64(p.seed ^ splitmix64(t as u64 + 1)));
            match &frames_in[t] {
                Some(f) => seed::sample_frame(f, t as u32, count, &mut rng),
                None => seed::Seeds::default(),
            }
        })
        .collect();
    drop(frames_in);
    let mut seeds = seed::Seeds::default();
    for s in per_ref {
        seeds.frame.extend(s.frame);
        seeds.pos.extend(s.pos);
        seeds.color.extend(s.color);
        seeds.scale.extend(s.scale);
    }
    anyhow::ensure!(
        !seeds.pos.is_empty(),
        "{}: no reference frame has foreground pixels with a valid depth prior",
        p.scene.display()
    );
    seed::clamp_quantiles(&mut seeds.scale, 0.05, 0.95);
    let skin = seed::skin(&seeds, &nodes, k);
    let ng = seeds.pos.len();
    let gaussians = Gaussians {
        id: (0..ng as u32).collect(),
        dynamic: vec![true; ng],
        scale: seeds.scale.iter().map(|&s| [s; 3]).collect(),
        opacity: vec![p.opacity; ng],
        color: seeds.color.clone(),
        sh_degree: 0,
        sh_rest: Vec::new(),
    };
    let bar = ctx.progress(tn as u64, "trajectories");
    let frames = (0..tn).map(|t| {
        let (position, rotation) = seed::pose(&seeds, &skin, &nodes, t);
        bar.inc(1);
        Ok(FrameState { frame: t as u32, position, rotation })
    });
    Model::save(&p.out, &gaussians, frames, &Provenance::new("init", p))?;
    bar.finish_and_clear();
    Ok(Summary {
        gaussians: ng,
        frames: tn,
        tracks: m,
        nodes: nodes.num_nodes,
        canonical: nodes.canonical,
    })
}
