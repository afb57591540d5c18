//! `usplat4d bench graph`: timings of key-node selection and edge construction at scale,
//! on a seeded synthetic model generated in memory (no I/O is timed).
//!
//! The synthetic model: `groups` rigid blobs, each turning and drifting with its own
//! motion, seen by a camera orbiting the scene; per-frame uncertainties are log-normal
//! with runs of unreliable (φ) frames. For each profile the bench times
//! [`keynodes::select`](super::keynodes::select) and [`edges::build`](super::edges::build),
//! checks the accelerated non-key assignment against brute force on a sample of non-keys,
//! and prints one table row (wall and CPU seconds, user + system over all threads, of
//! each stage). Peak memory is the process's VmHWM from /proc/self/status.

use std::time::Instant;

use glam::DMat3;

use crate::context::Context;
use crate::stages::edges::{self, EdgeSettings, NonkeyAssignMode};
use crate::stages::graph::metric::{MetricForm, apply};
use crate::stages::graph::search::{self, KeyFrames};
use crate::stages::graph::tracks::{Tracks, synthetic_tracks_hidden};
use crate::stages::keynodes::{self, KeynodeSettings};
use crate::stages::params::{Amount, Profile};

/// Parameters of `usplat4d bench graph`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BenchGraphParams {
    /// Number of Gaussians N.
    #[arg(long, default_value_t = 100_000)]
    #[serde(default = "default_n")]
    pub gaussians: usize,
    /// Number of frames T.
    #[arg(long, default_value_t = 200)]
    #[serde(default = "default_t")]
    pub frames: usize,
    /// Number of rigidly moving groups.
    #[arg(long, default_value_t = 8)]
    #[serde(default = "default_groups")]
    pub groups: usize,
    /// Profiles to time (comma-separated).
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Profile::Paper, Profile::Release])]
    #[serde(default = "default_profiles")]
    pub profiles: Vec<Profile>,
    /// Voxel size override for key selection (default: each profile's own).
    #[arg(long)]
    #[serde(default)]
    pub voxel_size: Option<Amount>,
    /// Form of the Eqs. 7-8 norm override (default: each profile's own).
    #[arg(long, value_enum)]
    #[serde(default)]
    pub metric_form: Option<MetricForm>,
    /// Non-keys whose assignment is checked against brute force.
    #[arg(long, default_value_t = 200)]
    #[serde(default = "default_checks")]
    pub check: usize,
    /// Initial fraction of Gaussians hidden (u = φ); each frame flips a Gaussian's
    /// visibility with probability 0.05.
    #[arg(long, default_value_t = 0.3)]
    #[serde(default = "default_hidden")]
    pub hidden_fraction: f64,
    /// Seed of the synthetic model.
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub seed: u64,
}

fn default_hidden() -> f64 {
    0.3
}

fn default_n() -> usize {
    100_000
}
fn default_t() -> usize {
    200
}
fn default_groups() -> usize {
    8
}
fn default_profiles() -> Vec<Profile> {
    vec![Profile::Paper, Profile::Release]
}
fn default_checks() -> usize {
    200
}

/// Peak resident memory of this process, bytes (VmHWM), if the kernel reports it.
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// CPU time of this process so far in seconds ([`crate::tools::bench::cpu_ms`]).
fn cpu_seconds() -> Option<f64> {
    crate::tools::bench::cpu_ms().map(|ms| ms / 1e3)
}

/// `usplat4d bench graph`.
pub fn run(p: &BenchGraphParams, ctx: &Context) -> anyhow::Result<()> {
    if cfg!(debug_assertions) {
        ctx.warn("bench graph: this is a debug build; timings are meaningful only with --release");
    }
    let t0 = Instant::now();
    let (tracks, rotations, _) =
        synthetic_tracks_hidden(p.gaussians, p.frames, p.groups, p.hidden_fraction, p.seed);
    ctx.info(format!(
        "synthetic model: N = {}, T = {}, {} groups, {}% hidden at start, generated in {:.2} s",
        p.gaussians,
        p.frames,
        p.groups,
        p.hidden_fraction * 100.0,
        t0.elapsed().as_secs_f64()
    ));
    println!(
        "| profile | N | T | keys | keynodes s | edges s | total s | keynodes CPU s | edges CPU s | edges | exact (sampled non-keys) | threads |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for &profile in &p.profiles {
        let mut ks = KeynodeSettings::defaults(profile);
        if let Some(v) = p.voxel_size {
            ks.voxel_size = keynodes::VoxelSize::Fixed(v);
        }
        let mut es = EdgeSettings::defaults(profile);
        if let Some(f) = p.metric_form {
            es.metric_form = f;
        }
        let c1 = cpu_seconds();
        let t1 = Instant::now();
        let keys = keynodes::select(&tracks, &ks);
        let t_keys = t1.elapsed().as_secs_f64();
        let c2 = cpu_seconds();
        let t2 = Instant::now();
        let e = edges::build(&tracks, &keys, &rotations, &es)?;
        let t_edges = t2.elapsed().as_secs_f64();
        let c3 = cpu_seconds();
        let cpu = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => format!("{:.2}", b - a),
            _ => "-".to_string(),
        };
        let (checked, ok) = check_sample(&tracks, &keys, &rotations, &es, &e, p.check);
        println!(
            "| {profile:?} | {} | {} | {} | {t_keys:.2} | {t_edges:.2} | {:.2} | {} | {} | {} | {ok}/{checked} | {} |",
            tracks.len(),
            tracks.num_frames,
            keys.num_keys(),
            t_keys + t_edges,
            cpu(c1, c2),
            cpu(c2, c3),
            e.len(),
            rayon::current_num_threads()
        );
    }
    if let Some(b) = peak_rss_bytes() {
        println!("\npeak memory (VmHWM): {:.2} GB", b as f64 / 1e9);
    }
    Ok(())
}

/// Compare the first `count` non-keys' assignments of `e` with brute force; returns
/// (checked, equal).
fn check_sample(
    tracks: &Tracks,
    keys: &crate::tables::key_nodes::KeyNodes,
    rotations: &[DMat3],
    s: &EdgeSettings,
    e: &crate::tables::edges::Edges,
    count: usize,
) -> (usize, usize) {
    let nt = tracks.num_frames;
    let key_rows = keys.rows(crate::tables::key_nodes::Role::Key);
    let mats: Vec<glam::Mat3> = if s.needs_rotations() {
        rotations.iter().map(|r| s.metric_form.transform(s.r_xyz, *r)).collect()
    } else {
        vec![s.metric_form.transform(s.r_xyz, DMat3::IDENTITY); nt]
    };
    let u_mask = 1.0 / s.contrib_threshold;
    let paper = s.nonkey_assign_mode == NonkeyAssignMode::ArgminSumMahalanobis;
    let mut kf = KeyFrames { num_keys: key_rows.len(), num_frames: nt, ..Default::default() };
    for &i in &key_rows {
        for t in 0..nt {
            kf.q.push(if paper { apply(&mats[t], tracks.pos(i, t)) } else { tracks.pos(i, t) });
            kf.u.push(tracks.u(i, t));
            kf.eligible.push(tracks.reliable(i, t) && (paper || tracks.u(i, t) < u_mask));
        }
    }
    let mut first_dst: std::collections::HashMap<u32, Vec<u32>> = std::collections::HashMap::new();
    for k in 0..e.len() {
        if e.kind[k] == crate::tables::edges::EdgeKind::NonkeyKey {
            first_dst.entry(e.src[k]).or_default().push(e.dst[k]);
        }
    }
    let (mut checked, mut ok) = (0, 0);
    for i in keys.rows(crate::tables::key_nodes::Role::Nonkey).into_iter().take(count) {
        let got = first_dst.get(&tracks.ids[i]).cloned().unwrap_or_default();
        let want: Vec<u32> = if paper {
            let q: Vec<[f32; 3]> = (0..nt).map(|t| apply(&mats[t], tracks.pos(i, t))).collect();
            let u: Vec<f32> = (0..nt).map(|t| tracks.u(i, t)).collect();
            search::argmin_sum_brute(&kf, &q, &u, s.metric_form)
                .map(|b| tracks.ids[key_rows[b.1 as usize]])
                .into_iter()
                .collect()
        } else {
            let p: Vec<[f32; 3]> = (0..nt).map(|t| tracks.pos(i, t)).collect();
            search::knn_max_brute(&kf, &p, s.nonkey_k)
                .into_iter()
                .map(|b| tracks.ids[key_rows[b.1 as usize]])
                .collect()
        };
        checked += 1;
        if (paper && got.first() == want.first()) || (!paper && got == want) {
            ok += 1;
        }
    }
    (checked, ok)
}
