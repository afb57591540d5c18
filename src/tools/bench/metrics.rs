//! `usplat4d bench metrics`: per-image timings of PSNR, SSIM and LPIPS on synthetic
//! `size x size` images, and optionally of `evaluate` over a temporary scene of N eval
//! images (the synthetic benchmark has 11 cameras x 121 frames = 1,331). Each line gives
//! the median wall time and the mean process CPU time (all threads). Build with
//! `--release` for meaningful numbers.

use std::time::Instant;

use anyhow::Context as _;

use crate::context::Context;
use crate::formats::png::{Image, write_png};
use crate::metrics::lpips::{Lpips, WeightsError};
use crate::metrics::{psnr::psnr, ssim::ssim};
use crate::scene::{Camera, Pinhole, Scene, Split};
use crate::stages::evaluate::{MaskMode, evaluate_images};
use crate::tables::Provenance;

/// Parameters of `usplat4d bench metrics`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BenchMetricsParams {
    /// Image side, pixels.
    #[arg(long, default_value_t = 512)]
    #[serde(default = "default_size")]
    pub size: usize,
    /// Timed repetitions per metric (the median is reported).
    #[arg(long, default_value_t = 5)]
    #[serde(default = "default_repeats")]
    pub repeats: usize,
    /// Also time `evaluate` over a temporary scene of this many eval images (0 = skip).
    #[arg(long, default_value_t = 0, value_name = "N")]
    #[serde(default)]
    pub evaluate: usize,
}

fn default_size() -> usize {
    512
}

fn default_repeats() -> usize {
    5
}

impl Default for BenchMetricsParams {
    fn default() -> Self {
        BenchMetricsParams { size: default_size(), repeats: default_repeats(), evaluate: 0 }
    }
}

/// A deterministic test image `[size, size, C]`: a smooth pattern plus splitmix64 noise of
/// amplitude `noise`.
fn test_image(size: usize, channels: usize, seed: u64, noise: f32) -> Image {
    let mut rng = crate::util::rng::Rng::from_state(seed);
    let mut next = move || rng.uniform_f32();
    let mut data = Vec::with_capacity(size * size * channels);
    for y in 0..size {
        for x in 0..size {
            for c in 0..channels {
                let base = if c == 3 {
                    1.0
                } else {
                    0.5 + 0.4 * ((x as f32 * 0.03 + c as f32) * (y as f32 * 0.02 + 1.0)).sin()
                };
                data.push((base + noise * (next() - 0.5)).clamp(0.0, 1.0));
            }
        }
    }
    Image { width: size, height: size, channels, data }.quantized()
}

/// Process CPU time in seconds ([`crate::tools::bench::cpu_ms`]).
fn cpu_secs() -> Option<f64> {
    crate::tools::bench::cpu_ms().map(|ms| ms / 1e3)
}

/// Wall and CPU time of a run, seconds.
struct Timing {
    wall: f64,
    cpu: Option<f64>,
}

impl Timing {
    /// `"W ms wall, C ms CPU"` per item, for `items` items.
    fn per(&self, items: usize) -> String {
        let n = items.max(1) as f64;
        let cpu = self.cpu.map_or("-".into(), |c| format!("{:.1}", c * 1e3 / n));
        format!("{:9.2} ms wall {cpu:>8} ms CPU", self.wall * 1e3 / n)
    }
}

/// Median wall seconds and mean CPU seconds of `repeats` runs of `f`.
fn time_runs(repeats: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<Timing> {
    let mut t = Vec::with_capacity(repeats);
    let cpu0 = cpu_secs();
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        f()?;
        t.push(start.elapsed().as_secs_f64());
    }
    let cpu = cpu_secs().zip(cpu0).map(|(b, a)| (b - a) / t.len() as f64);
    t.sort_by(f64::total_cmp);
    Ok(Timing { wall: t[t.len() / 2], cpu })
}

/// Run the benchmark.
pub fn run(p: &BenchMetricsParams, ctx: &Context) -> anyhow::Result<()> {
    let (n, r) = (p.size, p.repeats);
    let a = test_image(n, 3, 1, 0.1);
    let b = test_image(n, 3, 2, 0.3);
    let threads = rayon::current_num_threads();
    println!("bench metrics: {n}x{n} images, median of {r}, {threads} threads");
    let t = time_runs(r, || psnr(&a, &b, None).map(drop).map_err(Into::into))?;
    println!("psnr   {}/image", t.per(1));
    let t = time_runs(r, || ssim(&a, &b, None).map(drop).map_err(Into::into))?;
    println!("ssim   {}/image", t.per(1));
    let mask: Vec<f32> = (0..n * n).map(|i| if i % n < n / 2 { 1.0 } else { 0.0 }).collect();
    let t = time_runs(r, || ssim(&a, &b, Some(&mask)).map(drop).map_err(Into::into))?;
    println!("mssim  {}/image", t.per(1));
    let lpips = match Lpips::load_default() {
        Ok(l) => {
            let t = time_runs(r, || l.distance(&a, &b, None).map(drop).map_err(Into::into))?;
            println!("lpips  {}/image", t.per(1));
            Some(l)
        }
        Err(e @ WeightsError::Missing { .. }) => {
            println!("lpips  skipped: {e}");
            None
        }
        Err(e) => return Err(e.into()),
    };
    if p.evaluate > 0 {
        let tmp = tempfile::tempdir().context("creating a temporary directory")?;
        let scene = bench_scene(tmp.path(), n, p.evaluate)?;
        let renders = tmp.path().join("renders");
        let img = test_image(n, 4, 3, 0.3);
        for c in scene.eval() {
            write_png(&renders.join(&c.image_path), &img)?;
        }
        let mut rows = 0;
        let t = time_runs(1, || {
            rows = evaluate_images(&scene, &renders, "bench", lpips.as_ref(), MaskMode::Auto, ctx)?
                .len();
            Ok(())
        })?;
        let cpu = t.cpu.map_or("-".into(), |c| format!("{c:.1}"));
        println!(
            "evaluate {rows} images ({}): {:.1} s wall, {cpu} s CPU; {}/image",
            if lpips.is_some() { "psnr, ssim, lpips" } else { "psnr, ssim" },
            t.wall,
            t.per(rows)
        );
    }
    Ok(())
}

/// A scene of `count` eval images (11 cameras with angle offsets, round-robin) of side
/// `size` in `dir/scene`, plus one training image.
fn bench_scene(dir: &std::path::Path, size: usize, count: usize) -> anyhow::Result<Scene> {
    let w2c = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0];
    let pinhole = Pinhole::centred(size as f64, size as u32, size as u32, w2c);
    let cam = |name: String, frame: u32, split: Split, angle: Option<f32>| Camera {
        angle_offset_deg: angle,
        ..Camera::new(frame, &name, split, pinhole)
    };
    let mut cameras = vec![cam("cam00".into(), 0, Split::Train, None)];
    for i in 0..count {
        let k = i % 11 + 1;
        cameras.push(cam(
            format!("cam{k:02}"),
            (i / 11) as u32,
            Split::Eval,
            Some(30.0 * k as f32),
        ));
    }
    let scene = Scene { dir: dir.join("scene"), cameras };
    let img = test_image(size, 4, 4, 0.1);
    for c in &scene.cameras {
        write_png(&scene.resolve(&c.image_path), &img)?;
    }
    scene.save(&Provenance::new("bench metrics", &()))?;
    Ok(scene)
}
