//! `usplat4d bench uncertainty`: wall and CPU time of the uncertainty stage's per-frame
//! work ([`uncertainty::frame_work`](super::uncertainty::frame_work): one render with the
//! per-Gaussian sums of Eq. 3, Eq. 4's pass map, the gates, the convergence indicator of
//! Eq. 5 from the same render), printed as a Markdown table. No I/O is timed.
//!
//! Two kinds of rows: seeded random clouds (see [`crate::render::synthetic::cloud`]) at each
//! of `--counts`, whose "ground truth" is their own render with `--fail-fraction` of the
//! image columns (from the left) brightened so that those pixels fail Eq. 4; and, with
//! `--model` and `--scene`, the first `--frames` training frames of a real model and scene.
//! Columns: N; the share of pixels failing the gates; median wall ms of the render alone
//! (`CpuRenderer::render`) and of the whole frame work; mean process CPU ms of each (all
//! threads). Meaningful only in a release build.

use std::path::PathBuf;
use std::time::Instant;

use super::{cpu_ms, median_ms};
use crate::context::Context;
use crate::render::synthetic::{camera, cloud};
use crate::render::{CpuRenderer, RenderCamera, RenderSettings, Renderer, SplatInputs};
use crate::stages::params::Profile;
use crate::stages::uncertainty::{
    FrameTruth, LoadedTruth, UncertaintySettings, frame_work, pixel_pass,
};

/// Parameters of `usplat4d bench uncertainty`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct BenchUncertaintyParams {
    /// The clouds timed (`--counts ''` for none).
    #[command(flatten)]
    #[serde(flatten)]
    pub cloud: super::CloudParams,
    /// Share of the synthetic image's columns whose ground truth differs (fail Eq. 4).
    #[arg(long, default_value_t = 0.3)]
    #[serde(default = "default_fail_fraction")]
    pub fail_fraction: f32,
    /// Uncertainty profile (its gate, η_c and extra gates).
    #[arg(long, value_enum, default_value_t = Profile::Paper)]
    #[serde(default)]
    pub profile: Profile,
    /// A real model directory to time (with `--scene`).
    #[arg(long, value_name = "MODEL_DIR", requires = "scene")]
    #[serde(default)]
    pub model: Option<PathBuf>,
    /// The scene of `--model` (its training cameras and images).
    #[arg(long, value_name = "SCENE_DIR", requires = "model")]
    #[serde(default)]
    pub scene: Option<PathBuf>,
    /// Training frames of the real model timed (from frame 0).
    #[arg(long, default_value_t = 4)]
    #[serde(default = "default_frames")]
    pub frames: usize,
}

fn default_fail_fraction() -> f32 {
    0.3
}
fn default_frames() -> usize {
    4
}

/// Timings of one table row.
#[derive(Default)]
struct Row {
    render_ms: Vec<f64>,
    frame_ms: Vec<f64>,
    render_cpu: f64,
    frame_cpu: f64,
    failing: f64,
    runs: usize,
}

impl Row {
    /// Time `repeats` renders and `repeats` frame works of one frame.
    fn time(
        &mut self,
        repeats: usize,
        (camera, inputs, settings): (&RenderCamera, &SplatInputs, &RenderSettings),
        truth: &FrameTruth,
        rows: &[usize],
        s: &UncertaintySettings,
    ) -> anyhow::Result<()> {
        let c0 = cpu_ms();
        for _ in 0..repeats {
            let t0 = Instant::now();
            std::hint::black_box(CpuRenderer.render(camera, inputs, settings)?);
            self.render_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let c1 = cpu_ms();
        for _ in 0..repeats {
            let t0 = Instant::now();
            std::hint::black_box(frame_work(
                &CpuRenderer,
                0,
                camera,
                inputs,
                settings,
                truth,
                rows,
                s,
            )?);
            self.frame_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let c2 = cpu_ms();
        if let (Some(c0), Some(c1), Some(c2)) = (c0, c1, c2) {
            self.render_cpu += c1 - c0;
            self.frame_cpu += c2 - c1;
        }
        self.runs += repeats;
        Ok(())
    }

    fn print(self, name: &str, n: usize) {
        let runs = self.runs.max(1) as f64;
        println!(
            "| {name} | {n} | {:.1}% | {:.1} | {:.1} | {:.1} | {:.1} |",
            100.0 * self.failing,
            median_ms(self.render_ms),
            median_ms(self.frame_ms),
            self.render_cpu / runs,
            self.frame_cpu / runs
        );
    }
}

/// Share of pixels failing Eq. 4 and the gates of `s` (for the table; not timed).
fn failing_share(
    (camera, inputs, settings): (&RenderCamera, &SplatInputs, &RenderSettings),
    truth: &FrameTruth,
    s: &UncertaintySettings,
) -> anyhow::Result<f64> {
    let out = CpuRenderer.render(camera, inputs, settings)?;
    let mut pass = pixel_pass(&out.color, truth.rgb, s.eta_c, s.channel_reduce);
    crate::stages::uncertainty::apply_gates(
        &mut pass,
        &out.color,
        truth.rgb,
        truth.depth,
        truth.mask,
        (out.width, out.height),
        s,
    );
    Ok(pass.iter().filter(|p| !**p).count() as f64 / pass.len().max(1) as f64)
}

/// Run the benchmark and print the table to stdout.
pub fn run(p: &BenchUncertaintyParams, ctx: &Context) -> anyhow::Result<()> {
    if !(0.0..=1.0).contains(&p.fail_fraction) {
        anyhow::bail!("--fail-fraction must be in [0, 1], got {}", p.fail_fraction);
    }
    let (profile, fail_fraction) = (p.profile, p.fail_fraction);
    let (model_dir, scene_dir, frames) = (&p.model, &p.scene, p.frames);
    let p = &p.cloud;
    p.check(ctx)?;
    let s = UncertaintySettings::defaults(profile);
    let settings = RenderSettings::default();
    println!("uncertainty frame work, profile {profile:?}, synthetic {} per frame", p.conditions());
    println!();
    println!(
        "| scene | N | failing pixels | render ms | frame ms | render CPU ms | frame CPU ms |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|");
    let bar = ctx.progress(p.counts.len() as u64, "bench uncertainty");
    let cam = camera(p.width, p.height);
    for &n in &p.counts {
        let c = cloud(&cam, n, p.depth_complexity, p.seed);
        let inputs = c.inputs();
        let mut rgb = CpuRenderer.render(&cam, &inputs, &settings)?.color;
        let fail_cols = (fail_fraction * p.width as f32) as usize;
        for (i, v) in rgb.iter_mut().enumerate() {
            if (i / 3) % (p.width as usize) < fail_cols {
                *v = if *v > 0.5 { *v - 0.5 } else { *v + 0.5 };
            }
        }
        let mask = vec![true; rgb.len() / 3];
        let truth = FrameTruth { rgb: &rgb, mask: &mask, depth: None };
        let rows: Vec<usize> = (0..n).collect();
        let job = (&cam, &inputs, &settings);
        let mut row = Row { failing: failing_share(job, &truth, &s)?, ..Row::default() };
        row.time(p.repeats, job, &truth, &rows, &s)?;
        row.print(&format!("cloud {}x{}", p.width, p.height), n);
        bar.inc(1);
    }
    bar.finish_and_clear();
    if let (Some(model_dir), Some(scene_dir)) = (model_dir, scene_dir) {
        let model = crate::model::Model::load(model_dir)?;
        let scene = crate::scene::Scene::load(scene_dir)?;
        let cams = scene.train_by_frame();
        let g = &model.gaussians;
        let rows: Vec<usize> = (0..g.len()).collect();
        let frames = frames.min(cams.len()).min(model.num_frames());
        let mut row = Row::default();
        let bar = ctx.progress(frames as u64, "bench uncertainty (model)");
        for (t, cam) in cams.iter().enumerate().take(frames) {
            let state = model.frame(t)?;
            let inputs = model.splat_inputs(&state);
            let loaded = LoadedTruth::load(&scene, cam, settings.background, &s)?;
            let camera = RenderCamera::from(*cam);
            let job = (&camera, &inputs, &settings);
            row.failing += failing_share(job, &loaded.view(), &s)? / frames as f64;
            row.time(p.repeats, job, &loaded.view(), &rows, &s)?;
            bar.inc(1);
        }
        bar.finish_and_clear();
        let (w, h) = cams.first().map_or((0, 0), |c| (c.pinhole.width, c.pinhole.height));
        row.print(&format!("{} {w}x{h}", model_dir.display()), g.len());
    }
    Ok(())
}
