//! `usplat4d bench render`: forward and forward+backward timings of the rasterizer of
//! `--device` (the CPU by default) on seeded random clouds (see
//! [`crate::render::synthetic::cloud`]), printed as a Markdown table.
//! Meaningful only in a release build.
//!
//! Columns: N Gaussians; M tile-Gaussian intersections; blended (Gaussian, pixel) pairs
//! (α ≥ 1/255, before termination, i.e. Σ n_pixels); median ms per frame of the forward
//! pass and of forward + backward (wall clock); mean process CPU ms per frame of each (all
//! threads); blended pairs per second of the forward pass (wall clock).

use std::time::Instant;

use super::{cpu_ms, median_ms};
use crate::render::synthetic::{camera, cloud};
use crate::render::{Cutoff, DifferentiableRenderer, ImageGrads, RenderSettings, Renderer};

/// Parameters of `usplat4d bench render`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
pub struct BenchRenderParams {
    /// The clouds timed.
    #[command(flatten)]
    #[serde(flatten)]
    pub cloud: super::CloudParams,
}

/// Run the benchmark and print the table to stdout.
pub fn run(p: &BenchRenderParams, ctx: &crate::context::Context) -> anyhow::Result<()> {
    let p = &p.cloud;
    p.check(ctx)?;
    let r = crate::stages::device::renderer(ctx)?;
    let cam = camera(p.width, p.height);
    let settings = RenderSettings::default();
    let (w, h) = (p.width as usize, p.height as usize);
    println!("{} rasterizer, {}", r.tag(), p.conditions());
    println!();
    println!(
        "| N | M (tile pairs) | blended pairs | forward ms | fwd+bwd ms | forward CPU ms \
         | fwd+bwd CPU ms | blended pairs/s (fwd) |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    let bar = ctx.progress(p.counts.len() as u64, "bench render");
    for &n in &p.counts {
        let c = cloud(&cam, n, p.depth_complexity, p.seed);
        let inputs = c.inputs();
        let warm = r.render(&cam, &inputs, &settings)?;
        let blended: u64 = warm.aux.n_pixels.iter().map(|&v| v as u64).sum();
        let v = ImageGrads {
            color: vec![1e-3; w * h * 3],
            alpha: vec![1e-3; w * h],
            ..ImageGrads::default()
        };
        let (mut fwd, mut both, mut pairs) = (Vec::new(), Vec::new(), 0);
        let c0 = cpu_ms();
        for _ in 0..p.repeats {
            let t0 = Instant::now();
            std::hint::black_box(r.render(&cam, &inputs, &settings)?);
            fwd.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let c1 = cpu_ms();
        for _ in 0..p.repeats {
            let t0 = Instant::now();
            let (_, saved) = r.render_with_saved(&cam, &inputs, &settings, Cutoff::Hard)?;
            std::hint::black_box(r.backward(&cam, &inputs, &settings, &saved, &v)?);
            both.push(t0.elapsed().as_secs_f64() * 1e3);
            pairs = saved.num_pairs();
        }
        let c2 = cpu_ms();
        let per = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => format!("{:.1}", (b - a) / p.repeats as f64),
            _ => "-".into(),
        };
        let (f, b) = (median_ms(fwd), median_ms(both));
        println!(
            "| {n} | {pairs} | {blended} | {f:.1} | {b:.1} | {} | {} | {:.3e} |",
            per(c0, c1),
            per(c1, c2),
            blended as f64 / (f / 1e3)
        );
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}
