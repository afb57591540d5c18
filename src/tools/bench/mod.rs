//! `usplat4d bench ...`: timings of the renderer, the graph stages, the metrics and the
//! uncertainty stage (release builds only give meaningful numbers). The random-cloud options
//! shared by `bench render` and `bench uncertainty` ([`CloudParams`]) and the timing helpers
//! live here.

pub mod graph;
pub mod metrics;
pub mod optimize;
pub mod render;
pub mod uncertainty;

/// The seeded random clouds a benchmark times (see [`crate::render::synthetic::cloud`]).
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct CloudParams {
    /// Image width of the random clouds.
    #[arg(long, default_value_t = 480)]
    #[serde(default = "default_width")]
    pub width: u32,
    /// Image height of the random clouds.
    #[arg(long, default_value_t = 360)]
    #[serde(default = "default_height")]
    pub height: u32,
    /// Gaussian counts of the random clouds, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10000,50000,200000")]
    #[serde(default = "default_counts")]
    pub counts: Vec<usize>,
    /// How many times the clouds' 3σ discs cover the image.
    #[arg(long, default_value_t = 20.0)]
    #[serde(default = "default_depth_complexity")]
    pub depth_complexity: f32,
    /// Timed repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    #[serde(default = "default_repeats")]
    pub repeats: usize,
    /// Seed of the random clouds.
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub seed: u64,
}

fn default_width() -> u32 {
    480
}
fn default_height() -> u32 {
    360
}
fn default_counts() -> Vec<usize> {
    vec![10_000, 50_000, 200_000]
}
fn default_depth_complexity() -> f32 {
    20.0
}
fn default_repeats() -> usize {
    5
}

impl CloudParams {
    /// Reject zero sizes and repeats; warn that a debug build's timings mean nothing.
    pub fn check(&self, ctx: &crate::context::Context) -> anyhow::Result<()> {
        if self.repeats == 0 || self.width == 0 || self.height == 0 {
            anyhow::bail!("--repeats, --width and --height must be positive");
        }
        if cfg!(debug_assertions) {
            ctx.warn("debug build: timings are not meaningful (use cargo build --release)");
        }
        Ok(())
    }

    /// What the table's rows were measured on: `WxH, depth complexity D, K threads,
    /// median of R`.
    pub fn conditions(&self) -> String {
        format!(
            "{}x{}, depth complexity {}, {} threads, median of {}",
            self.width,
            self.height,
            self.depth_complexity,
            rayon::current_num_threads(),
            self.repeats
        )
    }
}

/// Process CPU time (user + system, all threads) in ms from `/proc/self/stat`, assuming
/// Linux's USER_HZ = 100; `None` elsewhere. On a busy shared machine wall time overstates
/// the cost; CPU time / threads is what an idle machine would show with perfect scaling.
pub fn cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks * 10.0)
}

/// Median of `v` (ms).
pub fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
