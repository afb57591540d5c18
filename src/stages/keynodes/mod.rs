//! Key-node selection (paper Sec. 4.2, "Key node selection"; official-release.md Sec. 3 and
//! Sec. 4.2 "Candidate filtering").
//!
//! The graph's Gaussians are those in `graph-scope` (dynamic by default in both profiles:
//! a well-observed static background would otherwise fill the confident pool and the key
//! budget); the others are listed as `unlinked`. Two stages, streamed frame by frame with
//! O(N) state:
//! 1. *Candidate sampling via 3D gridization.* At each frame t the confident set is the
//!    `candidates-per-frame` Gaussians of lowest u_{i,t} (paper: the top 2%; release: the
//!    top 1000). Their positions are binned into a voxel grid; voxels holding no confident
//!    Gaussian are discarded, and one Gaussian is picked per remaining voxel (paper: at
//!    random; release: the lowest-contribution one, i.e. the highest u). The candidates are
//!    the union over frames.
//! 2. *Thresholding by significant period.* A Gaussian is significant at frame t when
//!    u_{i,t} ≤ min(u of the confident cut at t, `spt-u-max`) and it is reliable there; the
//!    significant period is the longest run of such frames (paper) or their total count
//!    (release). Candidates with a period ≥ `min-significant-period` (5) become keys;
//!    the release caps them at 1500 by a seeded random pick.
//!
//! *Voxel size `auto` (paper default): the 1:49 key/non-key ratio.* The paper fixes the
//! key count, not the voxel: "a typical 1:49 key/non-key ratio", about 2% of the Gaussians
//! (Sec. 4.2 footnote, App. "key/non-key ratio"), with "the spatial volume unified" across
//! base models (App. "Adaptation"). A fixed voxel cannot give that: the union over frames
//! grows with T (12.8% of the Gaussians on a 20,000-Gaussian Fox). So the voxel edge is
//! chosen per run from a ladder of [`LADDER_RUNGS`] edges diag_t·2^(r−11), r = 0 (finest)
//! ..11 (the frame's bounding-box diagonal diag_t), all evaluated in the same streaming
//! pass. The ladder's factor 2 makes the grids nested (rung r's voxel is
//! `floor(cell₀ / 2^r)` of the finest cell, exactly, in integers), and both picks are a
//! minimum under a fixed total order (seeded key, or u), so a coarse voxel's pick is one
//! of its children's picks: candidates(r+1) ⊆ candidates(r), and one byte per Gaussian
//! (its coarsest rung, over frames) stores every rung's candidate set. The
//! significant-period filter does not depend on the rung, so the key count K_r is
//! non-increasing in r. The chosen rung is the finest with K_r ≤ budget (`key-budget`,
//! paper 2% of N); its keys are kept (voxel-uniform at that rung) and, when they fall
//! short of the budget, topped up by a seeded random pick among the next finer rung's
//! extra keys, so the count lands on the budget whenever the finest rung reaches it. If
//! even the coarsest rung exceeds the budget (T frames × a few voxels), its keys are
//! capped to the budget at random. The chosen edge (a fraction of each frame's
//! diagonal) and the per-rung counts are logged and recorded in the table's provenance.
//! With `auto` the random pick's seeded priorities are drawn once per run, not per frame
//! (each frame's pick is still a uniform draw among the voxel's confident Gaussians): a
//! voxel whose confident set does not change keeps its pick, so the union over frames
//! does not grow by re-drawing. On the 121-frame, 20,000-Gaussian Fox the per-frame draw
//! put 417 keys in the coarsest rung (one to eight voxels a frame) alone, over the 400
//! budget; the per-run draw lands on rung 9 (a quarter of the diagonal) topped up from
//! rung 8. A fixed `--voxel-size` evaluates the one grid with per-frame draws, as before.
//! Memory: O(N) for the rungs; time per frame O(pool · rungs).
//!
//! *Non-keys left out (release rows 33-35).* The release keeps only the non-keys with
//! max_t Contribs > max(n-th largest, `nonkey-min-contrib` 0.01), n = `nonkey-cap`
//! (36,000 if T > 350, 72,000 if T > 40, else 150,000), and deletes all the others from
//! the model at the start of training. With Contribs = 1/u (φ when unreliable), the
//! statistic is the per-Gaussian maximum over all frames of the normalised contribution,
//! 1/min_t u_{i,t}, ranked among the non-keys. The test is strict, as written: a non-key
//! tied with the n-th largest is left out too, so at most n − 1 non-keys stay when the
//! cap binds. Left-out non-keys get the role `culled` (`unselected-nonkeys cull`,
//! release) or `unlinked` (`keep`: in the model, without edges). Paper: no cap, no
//! minimum, nothing left out.
//!
//! Ablations of the paper's Table 3: (a) `--candidate-source uniform` draws the per-frame
//! pool uniformly at random instead of by uncertainty; (d) `--candidate-sampling random`
//! picks as many Gaussians as there were occupied voxels, at random, without the grid
//! (nested over rungs as well: the picks are the smallest seeded keys).

use std::collections::HashMap;
use std::path::PathBuf;

use rayon::prelude::*;

use super::graph::tracks::{
    GRAPH_SCOPE, GraphInputs, GraphScope, ScopedTracks, Tracks, bbox_diagonal,
};
use super::params::{Amount, check};
use crate::context::Context;
use crate::tables::key_nodes::{KeyNodes, Role};
use crate::util::rng::rank_key;

/// Rungs of the `auto` voxel ladder: edges diag_t·2^(r − 11), r = 0..11 (see the module doc).
pub const LADDER_RUNGS: usize = 12;

/// Random stream of the per-run voxel-pick priorities of `auto`.
const STREAM_PRIORITY: u64 = u64::MAX - 3;
/// Random stream of the top-up from the next finer rung (frame streams are 0..T-1).
const STREAM_TOP_UP: u64 = u64::MAX - 2;
/// Random stream of the budget cap of the coarsest rung.
const STREAM_BUDGET: u64 = u64::MAX - 1;
/// Random stream of the `max-key-nodes` cap.
const STREAM_CAP: u64 = u64::MAX;

/// Edge of the candidate voxel grid (profile row 19).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(into = "String")]
pub enum VoxelSize {
    /// The finest rung of a ladder of edges whose keys fit `key-budget` (module doc).
    Auto,
    /// A fixed edge: world units, or a fraction of the frame's bounding-box diagonal.
    Fixed(Amount),
}

impl std::str::FromStr for VoxelSize {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.trim() == "auto" {
            return Ok(VoxelSize::Auto);
        }
        let edge: Amount = s.parse().map_err(|e| format!("{e}, or auto"))?;
        // Below this a voxel index no longer fits the grid (f32 positions): the edge
        // would silently collapse the grid to a few cells.
        match edge {
            Amount::Value(v) | Amount::Fraction(v) if v >= 1e-9 => Ok(VoxelSize::Fixed(edge)),
            _ => Err(format!("voxel edge '{s}' must be at least 1e-9 (or a percentage), or auto")),
        }
    }
}

impl std::fmt::Display for VoxelSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VoxelSize::Auto => write!(f, "auto"),
            VoxelSize::Fixed(a) => write!(f, "{a}"),
        }
    }
}

impl From<VoxelSize> for String {
    fn from(v: VoxelSize) -> String {
        v.to_string()
    }
}

/// The most non-keys kept in the graph (profile row 33).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(into = "String")]
pub enum NonkeyCap {
    /// No cap (paper).
    None,
    /// The release's `n_nonkey_max`: 36,000 if T > 350, 72,000 if T > 40, else 150,000.
    ByFrames,
    /// A fixed count.
    Count(usize),
}

impl NonkeyCap {
    /// The cap for a sequence of `num_frames` frames (`None`: no cap).
    pub fn of(self, num_frames: usize) -> Option<usize> {
        match self {
            NonkeyCap::None => None,
            NonkeyCap::ByFrames if num_frames > 350 => Some(36_000),
            NonkeyCap::ByFrames if num_frames > 40 => Some(72_000),
            NonkeyCap::ByFrames => Some(150_000),
            NonkeyCap::Count(n) => Some(n),
        }
    }
}

impl std::str::FromStr for NonkeyCap {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "none" => Ok(NonkeyCap::None),
            "by-frames" => Ok(NonkeyCap::ByFrames),
            n => n
                .parse()
                .map(NonkeyCap::Count)
                .map_err(|_| format!("'{s}' is not a non-key cap (a count, none or by-frames)")),
        }
    }
}

impl std::fmt::Display for NonkeyCap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NonkeyCap::None => write!(f, "none"),
            NonkeyCap::ByFrames => write!(f, "by-frames"),
            NonkeyCap::Count(n) => write!(f, "{n}"),
        }
    }
}

impl From<NonkeyCap> for String {
    fn from(c: NonkeyCap) -> String {
        c.to_string()
    }
}

/// What happens to the non-keys that the cap or the minimum contribution leaves out
/// (profile row 35).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum UnselectedNonkeys {
    /// Deleted from the model at the start of training (role `culled`; release).
    Cull,
    /// Kept in the model without edges (role `unlinked`).
    Keep,
}

/// How one Gaussian is picked in an occupied voxel (profile row 20).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum VoxelPick {
    /// Uniformly at random (seeded).
    Random,
    /// The lowest-contribution (highest u) confident Gaussian of the voxel.
    LowestContribution,
}

/// Where the per-frame candidate pool comes from (ablation (a) of the paper's Table 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CandidateSource {
    /// The most confident Gaussians (lowest u).
    Uncertainty,
    /// The same number of Gaussians, drawn uniformly at random (no uncertainty).
    Uniform,
}

/// How candidates are thinned out of the pool (ablation (d) of the paper's Table 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CandidateSampling {
    /// One per occupied voxel of the 3D grid.
    Voxel,
    /// As many as there are occupied voxels, picked at random from the pool.
    Random,
}

/// How the significant period counts frames (profile row 21).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SptCounting {
    /// Longest run of consecutive significant frames.
    Consecutive,
    /// Total number of significant frames.
    Total,
}

crate::stage_params! {
    /// Parameters of `usplat4d keynodes`; unset values take the profile's defaults.
    pub struct KeynodeParams;
    /// Concrete settings of key-node selection (recorded in the table's provenance).
    pub struct KeynodeSettings;
    inputs {
        /// The model and its uncertainty table.
        #[command(flatten)]
        #[serde(flatten)]
        graph: GraphInputs,
        /// Output directory (key_nodes.parquet).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    }
    params {
        heading "Method" {
            graph_scope: GraphScope => GraphScope { shared GRAPH_SCOPE },
            /// Confident Gaussians per frame: a count or a percentage of N.
            candidates_per_frame: Amount => Amount [check::share]
                { paper "2%", release "1000", row "18" },
            /// Voxel edge: world units, a percentage of the frame's bounding-box diagonal, or
            /// `auto` (the finest edge whose keys fit `key-budget`).
            voxel_size: VoxelSize => VoxelSize [check::parsed]
                { paper "auto", release "0.2", row "19" },
            /// Key count targeted by `voxel-size auto`: a count or a percentage of N (paper:
            /// 1:49 key/non-key).
            key_budget: Amount => Amount [check::share] { paper "2%", release "1500", row "23" },
            /// Pick within a voxel (random, lowest-contribution).
            voxel_pick: VoxelPick => VoxelPick [check::choice]
                { paper "random", release "lowest-contribution", row "20" },
            /// Significant-period counting (consecutive, total).
            spt_counting: SptCounting => SptCounting [check::choice]
                { paper "consecutive", release "total", row "21" },
            /// Upper cap on the per-frame significance threshold of u (release: 2, i.e.
            /// normalised contribution 0.5; inf for none).
            spt_u_max: f32 => f32 [check::parsed] { paper "inf", release "2", row "22" },
            /// Minimum significant period, frames.
            min_significant_period: u32 => u32 [check::parsed] { paper "5", release "5" },
            /// Cap on the number of keys, 0 for none.
            max_key_nodes: usize => Option<usize> [check::parsed]
                { paper "0", release "1500", row "23" },
        }
        heading "Ablations" {
            /// Candidate pool (uncertainty; ablation (a): uniform).
            candidate_source: CandidateSource => CandidateSource [check::choice]
                { paper "uncertainty", release "uncertainty" },
            /// Candidate thinning (voxel; ablation (d): random).
            candidate_sampling: CandidateSampling => CandidateSampling [check::choice]
                { paper "voxel", release "voxel" },
        }
        heading "Non-keys" {
            /// Most non-keys kept in the graph: a count, `none`, or `by-frames` (36,000 if T > 350,
            /// 72,000 if T > 40, else 150,000).
            nonkey_cap: NonkeyCap => NonkeyCap [check::parsed]
                { paper "none", release "by-frames", row "33" },
            /// A non-key stays in the graph only if its largest contribution max_t 1/u_{i,t}
            /// exceeds this, 0 for no minimum.
            nonkey_min_contrib: f64 => Option<f64> [check::non_negative]
                { paper "0", release "0.01", row "34" },
            /// Non-keys left out of the graph: deleted at the start of training, or kept without
            /// edges (keep, cull; the paper leaves none out).
            unselected_nonkeys: UnselectedNonkeys => UnselectedNonkeys [check::choice]
                { paper "keep", release "cull", row "35" },
        }
    }
    copied {
        heading "Method" {
            /// Seed of the random picks.
            seed: u64 [check::parsed] { default "0" },
        }
    }
}

/// Per-Gaussian significant-period state, updated one frame at a time.
#[derive(Debug, Clone, Copy, Default)]
struct Period {
    run: u32,
    longest: u32,
    total: u32,
    best_u: f32,
    t_hat: u32,
}

/// What a selection found besides the table (logged, and recorded in the provenance).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct SelectionReport {
    /// The voxel edge used: for `auto`, the chosen rung's fraction of each frame's
    /// bounding-box diagonal.
    pub voxel_size: Amount,
    /// The chosen rung of the `auto` ladder (0 = finest; 0 for a fixed edge).
    pub rung: usize,
    /// Keys (after the significant-period filter) at each rung, finest first: one entry
    /// for a fixed edge.
    pub keys_per_rung: Vec<usize>,
    /// The key count targeted by `auto` (`None` for a fixed edge).
    pub budget: Option<usize>,
    /// Keys added at random from the next finer rung to reach the budget.
    pub topped_up: usize,
    /// Keys removed by a random cap (the budget at the coarsest rung, or `max-key-nodes`).
    pub capped: usize,
    /// The non-key cap in force (`None`: no cap).
    pub nonkey_cap: Option<usize>,
    /// Number of Gaussians of each role: key, nonkey, unlinked, culled.
    pub roles: [usize; 4],
}

/// Select the key nodes of `tracks` (stage 1 and 2 above). Deterministic for a seed,
/// whatever the thread count.
pub fn select(tracks: &Tracks, s: &KeynodeSettings) -> KeyNodes {
    select_with_report(tracks, s).0
}

/// [`select`], with what it found on the way.
pub fn select_with_report(tracks: &Tracks, s: &KeynodeSettings) -> (KeyNodes, SelectionReport) {
    let (n, nt) = (tracks.len(), tracks.num_frames);
    let rungs = match s.voxel_size {
        VoxelSize::Auto => LADDER_RUNGS,
        VoxelSize::Fixed(_) => 1,
    };
    let mut period = vec![Period { best_u: f32::INFINITY, ..Default::default() }; n];
    // 0: never a candidate; r + 1: a candidate at rungs 0..=r (in some frame).
    let mut reach = vec![0u8; n];
    let mut u_t = vec![0.0f32; n];
    let mut rel_t = vec![false; n];
    let mut p_t = vec![[0.0f32; 3]; n];
    for t in 0..nt {
        u_t.par_iter_mut().zip(rel_t.par_iter_mut()).zip(p_t.par_iter_mut()).enumerate().for_each(
            |(i, ((u, r), p))| {
                *u = tracks.u(i, t);
                *r = tracks.reliable(i, t);
                *p = tracks.pos(i, t);
            },
        );
        let confident =
            confident_set(&u_t, &rel_t, s.candidates_per_frame.of(n as f64).ceil() as usize);
        let cut = confident.last().map_or(f32::NEG_INFINITY, |&i| u_t[i]);
        let threshold = cut.min(s.spt_u_max);
        period.par_iter_mut().enumerate().for_each(|(i, st)| {
            let u = u_t[i];
            if u < st.best_u {
                st.best_u = u;
                st.t_hat = t as u32;
            }
            if rel_t[i] && u <= threshold {
                st.run += 1;
                st.total += 1;
                st.longest = st.longest.max(st.run);
            } else {
                st.run = 0;
            }
        });
        let pool = match s.candidate_source {
            CandidateSource::Uncertainty => confident,
            CandidateSource::Uniform => {
                random_subset(0..n, confident.len(), s.seed, t as u64, &tracks.ids)
            }
        };
        for (i, r) in frame_candidates(&pool, &p_t, &u_t, &tracks.ids, s, t as u64, rungs) {
            reach[i] = reach[i].max(r as u8 + 1);
        }
    }
    let spt: Vec<u32> = period
        .iter()
        .map(|p| match s.spt_counting {
            SptCounting::Consecutive => p.longest,
            SptCounting::Total => p.total,
        })
        .collect();
    // Ablation (a) takes uncertainty out of the selection, significant period included.
    let uniform = s.candidate_source == CandidateSource::Uniform;
    let eligible = |i: usize| reach[i] > 0 && (uniform || spt[i] >= s.min_significant_period);
    let mut keys_per_rung = vec![0usize; rungs];
    for i in (0..n).filter(|&i| eligible(i)) {
        for k in keys_per_rung.iter_mut().take(reach[i] as usize) {
            *k += 1;
        }
    }
    let budget = (s.voxel_size == VoxelSize::Auto)
        .then(|| (s.key_budget.of(n as f64).round() as usize).max(1));
    let rung =
        budget.map_or(0, |b| keys_per_rung.iter().position(|&k| k <= b).unwrap_or(rungs - 1));
    let mut is_key: Vec<bool> = (0..n).map(|i| eligible(i) && reach[i] as usize > rung).collect();
    let (mut topped_up, mut capped) = (0, 0);
    if let Some(b) = budget {
        let have = keys_per_rung[rung];
        if have < b && rung > 0 {
            let extra = (0..n).filter(|&i| eligible(i) && reach[i] as usize == rung);
            for i in random_subset(extra, b - have, s.seed, STREAM_TOP_UP, &tracks.ids) {
                is_key[i] = true;
                topped_up += 1;
            }
        }
        capped += cap_at_random(&mut is_key, b, s.seed, STREAM_BUDGET, &tracks.ids);
    }
    if let Some(cap) = s.max_key_nodes {
        capped += cap_at_random(&mut is_key, cap, s.seed, STREAM_CAP, &tracks.ids);
    }
    let best_u: Vec<f32> = period.iter().map(|p| p.best_u).collect();
    let nonkey_cap = s.nonkey_cap.of(nt);
    let role = roles(&is_key, &best_u, nonkey_cap, s.nonkey_min_contrib, s.unselected_nonkeys);
    let voxel_size = match s.voxel_size {
        VoxelSize::Auto => Amount::Fraction(rung_fraction(rung)),
        VoxelSize::Fixed(a) => a,
    };
    let keys = KeyNodes {
        id: tracks.ids.clone(),
        role,
        t_hat: period.iter().map(|p| p.t_hat).collect(),
        significant_period: spt,
    };
    let report = SelectionReport {
        voxel_size,
        rung,
        keys_per_rung,
        budget,
        topped_up,
        capped,
        nonkey_cap,
        roles: Role::ALL.map(|r| keys.count(r)),
    };
    (keys, report)
}

/// Edge of ladder rung `r` as a fraction of the frame's bounding-box diagonal.
fn rung_fraction(r: usize) -> f64 {
    (2.0f64).powi(r as i32 - (LADDER_RUNGS as i32 - 1))
}

/// Keep `cap` of the `true` entries of `is_key` `[N]` at random (seeded); returns how many
/// were dropped.
fn cap_at_random(is_key: &mut [bool], cap: usize, seed: u64, stream: u64, ids: &[u32]) -> usize {
    let keys: Vec<usize> = (0..is_key.len()).filter(|&i| is_key[i]).collect();
    if keys.len() <= cap {
        return 0;
    }
    let dropped = keys.len() - cap;
    is_key.fill(false);
    for i in random_subset(keys.into_iter(), cap, seed, stream, ids) {
        is_key[i] = true;
    }
    dropped
}

/// The role of each Gaussian given the keys `is_key` `[N]` and each Gaussian's lowest
/// uncertainty over all frames `best_u` `[N]` (φ when never reliable): a non-key stays in
/// the graph when its largest contribution 1/best_u is above both the `cap`-th largest among
/// the non-keys and `min_contrib` (release `main3`, strict comparisons); the others are
/// `culled` or `unlinked` per `unselected`.
fn roles(
    is_key: &[bool],
    best_u: &[f32],
    cap: Option<usize>,
    min_contrib: Option<f64>,
    unselected: UnselectedNonkeys,
) -> Vec<Role> {
    // In u: kept iff best_u < min(cap-th smallest best_u among the non-keys, 1/min_contrib).
    let mut limit = min_contrib.map_or(f64::INFINITY, |m| 1.0 / m);
    if let Some(cap) = cap {
        let mut u: Vec<f32> =
            (0..is_key.len()).filter(|&i| !is_key[i]).map(|i| best_u[i]).collect();
        if cap == 0 {
            limit = f64::NEG_INFINITY;
        } else if cap <= u.len() {
            let (_, nth, _) = u.select_nth_unstable_by(cap - 1, f32::total_cmp);
            limit = limit.min(*nth as f64);
        }
    }
    let left_out = match unselected {
        UnselectedNonkeys::Cull => Role::Culled,
        UnselectedNonkeys::Keep => Role::Unlinked,
    };
    (0..is_key.len())
        .map(|i| match () {
            _ if is_key[i] => Role::Key,
            _ if (best_u[i] as f64) < limit => Role::Nonkey,
            _ => left_out,
        })
        .collect()
}

/// The `count` reliable Gaussians of lowest u (ties: lower index first), in ascending u.
fn confident_set(u: &[f32], reliable: &[bool], count: usize) -> Vec<usize> {
    let mut pool: Vec<usize> = (0..u.len()).filter(|&i| reliable[i]).collect();
    let by_u = |a: &usize, b: &usize| u[*a].total_cmp(&u[*b]).then(a.cmp(b));
    let count = count.min(pool.len());
    if count == 0 {
        return Vec::new();
    }
    if count < pool.len() {
        pool.select_nth_unstable_by(count - 1, by_u);
        pool.truncate(count);
    }
    pool.sort_unstable_by(by_u);
    pool
}

/// `count` items of `items` chosen uniformly at random (smallest seeded keys), sorted.
fn random_subset(
    items: impl Iterator<Item = usize>,
    count: usize,
    seed: u64,
    stream: u64,
    ids: &[u32],
) -> Vec<usize> {
    let mut keyed: Vec<(u64, usize)> =
        items.map(|i| (rank_key(seed, stream, ids[i] as u64), i)).collect();
    let count = count.min(keyed.len());
    if count < keyed.len() && count > 0 {
        keyed.select_nth_unstable(count - 1);
    }
    keyed.truncate(count);
    let mut out: Vec<usize> = keyed.into_iter().map(|(_, i)| i).collect();
    out.sort_unstable();
    out
}

/// Voxel coordinates of `p` for edge `size`.
fn voxel(p: [f32; 3], size: f64) -> [i64; 3] {
    p.map(|c| (c as f64 / size).floor() as i64)
}

/// The candidates of one frame with their coarsest rung: at each of the `rungs` nested
/// grids (rung r's cell is the finest cell divided by 2^r, rounded down), one Gaussian of
/// `pool` per occupied voxel, or (ablation d) as many at random. `p` and `u` are the frame's
/// `[N]` positions and uncertainties. A Gaussian picked at rung r is picked at every finer
/// rung (module doc), so `(i, r)` means "a candidate at rungs 0..=r".
fn frame_candidates(
    pool: &[usize],
    p: &[[f32; 3]],
    u: &[f32],
    ids: &[u32],
    s: &KeynodeSettings,
    t: u64,
    rungs: usize,
) -> Vec<(usize, usize)> {
    if pool.is_empty() {
        return Vec::new();
    }
    let size = match s.voxel_size {
        VoxelSize::Auto => rung_fraction(0) * bbox_diagonal(p),
        VoxelSize::Fixed(Amount::Value(v)) => v,
        VoxelSize::Fixed(Amount::Fraction(f)) => f * bbox_diagonal(p),
    }
    .max(f64::MIN_POSITIVE);
    // True when i beats j as its voxel's pick (a total order, so picks nest over rungs).
    // `auto` draws the random priorities once per run, a fixed edge once per frame.
    let stream = if s.voxel_size == VoxelSize::Auto { STREAM_PRIORITY } else { t };
    let better = |i: usize, j: usize| match s.voxel_pick {
        VoxelPick::Random => {
            (rank_key(s.seed, stream, ids[i] as u64), i)
                < (rank_key(s.seed, stream, ids[j] as u64), j)
        }
        VoxelPick::LowestContribution => u[i].total_cmp(&u[j]).then(j.cmp(&i)).is_gt(),
    };
    // Survivors of the rungs so far, with their finest cell.
    let mut alive: Vec<(usize, [i64; 3])> = pool.iter().map(|&i| (i, voxel(p[i], size))).collect();
    let mut out = Vec::new();
    let mut occupied = Vec::with_capacity(rungs);
    for r in 0..rungs {
        let mut best: HashMap<[i64; 3], (usize, [i64; 3])> = HashMap::with_capacity(alive.len());
        for &(i, c) in &alive {
            best.entry(c.map(|x| x >> r))
                .and_modify(|b| {
                    if better(i, b.0) {
                        *b = (i, c)
                    }
                })
                .or_insert((i, c));
        }
        occupied.push(best.len());
        let mut next: Vec<(usize, [i64; 3])> = best.into_values().collect();
        next.sort_unstable_by_key(|x| x.0);
        if r > 0 {
            // the losers of this rung were last picked at rung r - 1
            let kept: std::collections::HashSet<usize> = next.iter().map(|x| x.0).collect();
            out.extend(alive.iter().filter(|x| !kept.contains(&x.0)).map(|x| (x.0, r - 1)));
        }
        alive = next;
    }
    out.extend(alive.iter().map(|x| (x.0, rungs - 1)));
    match s.candidate_sampling {
        CandidateSampling::Voxel => out,
        CandidateSampling::Random => {
            // as many as the rung's occupied voxels, by the smallest seeded keys: nested too
            let mut by_key: Vec<(u64, usize)> =
                pool.iter().map(|&i| (rank_key(s.seed, t ^ 0x5EED, ids[i] as u64), i)).collect();
            by_key.sort_unstable();
            by_key
                .into_iter()
                .enumerate()
                .filter(|&(k, _)| occupied[0] > k)
                .map(|(k, (_, i))| (i, occupied.iter().rposition(|&c| c > k).unwrap_or(0)))
                .collect()
        }
    }
}

/// The key-node table over every Gaussian of the uncertainty table: the selection `keys` of
/// the in-scope Gaussians, and the role `unlinked` (t̂ = 0, significant period 0) for the
/// others (outside the graph scope: rendered, in the model, no edges).
fn in_table(keys: KeyNodes, scoped: &ScopedTracks) -> KeyNodes {
    let n = scoped.table_ids.len();
    let mut out = KeyNodes {
        id: scoped.table_ids.clone(),
        role: vec![Role::Unlinked; n],
        t_hat: vec![0; n],
        significant_period: vec![0; n],
    };
    for (i, &r) in scoped.table_rows.iter().enumerate() {
        out.role[r] = keys.role[i];
        out.t_hat[r] = keys.t_hat[i];
        out.significant_period[r] = keys.significant_period[i];
    }
    out
}

/// `usplat4d keynodes`: read the model and the uncertainty table, select, write
/// `OUT/key_nodes.parquet`.
pub fn run(p: &KeynodeParams, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("keynodes").entered();
    let settings = p.resolve()?;
    let (_, scoped) = p.graph.load(settings.graph_scope, ctx)?;
    let tracks = &scoped.tracks;
    let (keys, mut report) = select_with_report(tracks, &settings);
    let keys = in_table(keys, &scoped);
    report.roles = Role::ALL.map(|r| keys.count(r));
    let [n_key, n_nonkey, n_unlinked, n_culled] = report.roles;
    ctx.info(format!(
        "keynodes: {n_key} key nodes of {} Gaussians ({} frames), voxel edge {}{}; \
         {n_nonkey} non-keys in the graph, {n_unlinked} unlinked ({} outside the graph \
         scope), {n_culled} culled",
        tracks.len(),
        tracks.num_frames,
        report.voxel_size,
        match report.budget {
            Some(b) => format!(
                " (auto: rung {} of keys per rung {:?}, budget {b}, {} topped up, {} capped)",
                report.rung, report.keys_per_rung, report.topped_up, report.capped
            ),
            None => String::new(),
        },
        scoped.table_ids.len() - tracks.len(),
    ));
    if n_key == 0 {
        ctx.warn(format!(
            "keynodes: no key node: no Gaussian of {} is reliable for a significant period \
             (the base model may be fitted too poorly, or the video is too short); the \
             usplat4d recipe then has no key anchors",
            p.graph.model.display()
        ));
    }
    let prov = crate::tables::Provenance::new(
        "keynodes",
        &serde_json::json!({ "params": p, "resolved": settings, "outcome": report }),
    );
    let out =
        p.out.join(<crate::tables::key_nodes::KeyNodesTable as crate::tables::Table>::file_name());
    crate::tables::key_nodes::write(&out, &keys, &prov)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::params::Profile;
    use crate::util::parse_args;

    /// N Gaussians on a line (x = i) for T frames, u given per (i, t).
    fn tracks(n: usize, nt: usize, u: impl Fn(usize, usize) -> f32) -> Tracks {
        let mut tr = Tracks {
            ids: (0..n as u32).map(|i| 100 + i).collect(),
            num_frames: nt,
            ..Default::default()
        };
        for i in 0..n {
            for t in 0..nt {
                tr.positions.push([i as f32, 0.0, 0.0]);
                let v = u(i, t);
                tr.u.push(v);
                tr.reliable.push(v < 1e8);
            }
        }
        tr
    }

    fn settings(profile: Profile) -> KeynodeSettings {
        KeynodeSettings::defaults(profile)
    }

    /// Whether each Gaussian is a key `[N]`.
    fn is_key(k: &KeyNodes) -> Vec<bool> {
        k.role.iter().map(|r| *r == Role::Key).collect()
    }

    fn fixed(v: f64) -> VoxelSize {
        VoxelSize::Fixed(Amount::Value(v))
    }

    #[test]
    fn one_pick_per_voxel_among_confident_gaussians() {
        // 8 Gaussians at x = 0..7, voxel edge 2: voxels {0,1} {2,3} {4,5} {6,7}. The three
        // most confident are 0, 1 and 4, so voxels {0,1} and {4,5} survive.
        let tr = tracks(8, 6, |i, _| [0.1, 0.2, 5.0, 5.0, 0.3, 5.0, 5.0, 5.0][i]);
        let mut s = settings(Profile::Release);
        s.candidates_per_frame = Amount::Value(3.0);
        s.voxel_size = fixed(2.0);
        s.spt_u_max = f32::INFINITY;
        let k = select(&tr, &s);
        // lowest contribution (highest u) in voxel {0,1} is 1; voxel {4,5} has only 4.
        assert_eq!(is_key(&k), vec![false, true, false, false, true, false, false, false]);
        assert_eq!(k.significant_period[1], 6);
        s.voxel_pick = VoxelPick::Random;
        // a random pick per voxel and frame: the union over frames stays within the voxels
        let k = select(&tr, &s);
        let kk = is_key(&k);
        assert!(kk[4] && (kk[0] || kk[1]));
        assert_eq!(k.num_keys(), (0..8).filter(|&i| kk[i] && [0, 1, 4].contains(&i)).count());
    }

    #[test]
    fn random_picks_are_seeded() {
        let tr = tracks(400, 8, |i, t| 0.01 + ((i * 7 + t * 13) % 97) as f32 / 100.0);
        let mut s = settings(Profile::Paper);
        s.candidates_per_frame = Amount::Value(200.0);
        s.voxel_size = fixed(10.0);
        s.min_significant_period = 1;
        let a = select(&tr, &s);
        assert_eq!(a, select(&tr, &s));
        let b = select(&tr, &KeynodeSettings { seed: 7, ..s.clone() });
        assert_ne!(a.role, b.role);
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| select(&tr, &s));
        assert_eq!(a, one);
    }

    #[test]
    fn significant_period_filter_and_counting() {
        // Gaussian 0 is confident in frames 0-2 and 5-6 (5 in total, longest run 3);
        // Gaussian 1 in frames 0-5 (run 6). Everything else is unreliable.
        let on0 = [1, 1, 1, 0, 0, 1, 1, 0];
        let tr = tracks(4, 8, |i, t| match i {
            0 if on0[t] == 1 => 0.1,
            1 if t < 6 => 0.2,
            _ => 1e8,
        });
        let mut s = settings(Profile::Paper);
        s.voxel_size = fixed(0.5);
        s.candidates_per_frame = Amount::Value(2.0);
        let k = select(&tr, &s);
        assert_eq!(k.significant_period, vec![3, 6, 0, 0]);
        assert_eq!(is_key(&k), vec![false, true, false, false]);
        assert_eq!(k.t_hat, vec![0, 0, 0, 0]);
        s.spt_counting = SptCounting::Total;
        let k = select(&tr, &s);
        assert_eq!(k.significant_period, vec![5, 6, 0, 0]);
        assert_eq!(is_key(&k), vec![true, true, false, false]);
    }

    #[test]
    fn profiles_differ_as_documented() {
        let p = settings(Profile::Paper);
        let r = settings(Profile::Release);
        assert_eq!(p.candidates_per_frame, Amount::Fraction(0.02));
        assert_eq!(r.candidates_per_frame, Amount::Value(1000.0));
        assert_eq!(
            (p.voxel_pick, r.voxel_pick),
            (VoxelPick::Random, VoxelPick::LowestContribution)
        );
        assert_eq!(
            (p.spt_counting, r.spt_counting),
            (SptCounting::Consecutive, SptCounting::Total)
        );
        assert_eq!((p.max_key_nodes, r.max_key_nodes), (None, Some(1500)));
        assert_eq!(p.min_significant_period, r.min_significant_period);
        let args = "--model m --uncertainty u --out o --profile release --max-key-nodes 0 \
                    --voxel-size 5%";
        let o = parse_args::<KeynodeParams>(&args.split_whitespace().collect::<Vec<_>>())
            .unwrap()
            .resolve()
            .unwrap();
        assert_eq!(o.max_key_nodes, None);
        assert_eq!(o.voxel_size, VoxelSize::Fixed(Amount::Fraction(0.05)));
        assert_eq!(o.voxel_pick, VoxelPick::LowestContribution);
        assert_eq!((o.nonkey_cap, o.nonkey_min_contrib), (NonkeyCap::ByFrames, Some(0.01)));
        assert_eq!(o.unselected_nonkeys, UnselectedNonkeys::Cull);
        assert_eq!((p.voxel_size, p.key_budget), (VoxelSize::Auto, Amount::Fraction(0.02)));
        assert_eq!((p.nonkey_cap, p.nonkey_min_contrib), (NonkeyCap::None, None));
        let args = "--model m --uncertainty u --out o --voxel-size auto --key-budget 300 \
                    --nonkey-cap 20 --nonkey-min-contrib 0 --unselected-nonkeys keep";
        let o = parse_args::<KeynodeParams>(&args.split_whitespace().collect::<Vec<_>>())
            .unwrap()
            .resolve()
            .unwrap();
        assert_eq!((o.key_budget, o.nonkey_cap), (Amount::Value(300.0), NonkeyCap::Count(20)));
        assert_eq!(o.nonkey_min_contrib, None);
        assert_eq!(o.unselected_nonkeys, UnselectedNonkeys::Keep);
        let bad = ["--model", "m", "--uncertainty", "u", "--out", "o"];
        let err = parse_args::<KeynodeParams>(&[&bad[..], &["--nonkey-min-contrib=-1"]].concat())
            .unwrap_err()
            .to_string();
        assert!(err.contains("--nonkey-min-contrib") && err.contains("non-negative"), "{err}");
        assert_eq!("by-frames".parse::<NonkeyCap>().unwrap().of(351), Some(36_000));
        assert_eq!(NonkeyCap::ByFrames.of(350), Some(72_000));
        assert_eq!(NonkeyCap::ByFrames.of(40), Some(150_000));
        assert!("many".parse::<NonkeyCap>().is_err() && "x".parse::<VoxelSize>().is_err());
        // release caps the number of keys at random
        let tr = tracks(50, 6, |_, _| 0.1);
        let mut s = r.clone();
        s.voxel_size = fixed(0.5);
        s.max_key_nodes = Some(10);
        assert_eq!(select(&tr, &s).num_keys(), 10);
    }

    #[test]
    fn ablations_change_the_candidates() {
        let tr = tracks(300, 6, |i, _| if i < 100 { 0.1 + i as f32 * 1e-3 } else { 0.5 });
        let mut s = settings(Profile::Paper);
        s.candidates_per_frame = Amount::Value(30.0);
        s.voxel_size = fixed(5.0);
        s.voxel_pick = VoxelPick::LowestContribution;
        let full = select(&tr, &s);
        // confident Gaussians are 0..30 at x = 0..30 → 6 voxels, one key each.
        assert_eq!(full.num_keys(), 6);
        assert!((0..300).all(|i| full.role[i] != Role::Key || i < 30));
        let d = select(
            &tr,
            &KeynodeSettings { candidate_sampling: CandidateSampling::Random, ..s.clone() },
        );
        assert!((0..300).all(|i| d.role[i] != Role::Key || i < 30));
        assert_ne!(d.role, full.role);
        let a = select(
            &tr,
            &KeynodeSettings { candidate_source: CandidateSource::Uniform, ..s.clone() },
        );
        assert!((30..300).any(|i| a.role[i] == Role::Key));
    }

    #[test]
    fn nonkey_cap_minimum_and_cull() {
        // Gaussian 0 is a key; the non-keys' lowest u over all frames are 0.5, 0.1, 0.3,
        // 200 (contribution 0.005 < 0.01), 1e8 (never reliable) and 0.3 (tied with 2).
        let is_key = [true, false, false, false, false, false, false];
        let best_u = [0.2, 0.5, 0.1, 0.3, 200.0, 1e8, 0.3];
        let cull = UnselectedNonkeys::Cull;
        let (k, n, c, l) = (Role::Key, Role::Nonkey, Role::Culled, Role::Unlinked);
        // paper: every non-key stays
        assert_eq!(roles(&is_key, &best_u, None, None, cull), vec![k, n, n, n, n, n, n]);
        // release minimum only: contributions 1/200 and 1e-8 are not above 0.01
        assert_eq!(roles(&is_key, &best_u, None, Some(0.01), cull), vec![k, n, n, n, c, c, n]);
        // cap 4: the 4th largest contribution is 1/0.5; strictly above it: 1/0.1, 1/0.3 (x2)
        assert_eq!(roles(&is_key, &best_u, Some(4), Some(0.01), cull), vec![k, c, n, n, c, c, n]);
        // cap 3 lands in the tie at u = 0.3, which fails the strict test as a whole
        assert_eq!(roles(&is_key, &best_u, Some(3), None, cull), vec![k, c, n, c, c, c, c]);
        // a cap above the non-key count leaves the minimum in charge; keep = unlinked
        let keep = UnselectedNonkeys::Keep;
        assert_eq!(roles(&is_key, &best_u, Some(50), Some(0.01), keep), vec![k, n, n, n, l, l, n]);
        assert_eq!(roles(&is_key, &best_u, Some(0), None, keep), vec![k, l, l, l, l, l, l]);
        // end to end through select: release defaults cull the never-reliable Gaussian 3
        let tr = tracks(4, 6, |i, t| if i == 3 { 1e8 } else { 0.1 + (i + t) as f32 * 1e-3 });
        let mut s = settings(Profile::Release);
        s.voxel_size = fixed(100.0);
        s.spt_u_max = f32::INFINITY;
        s.nonkey_cap = NonkeyCap::Count(2);
        let (kn, report) = select_with_report(&tr, &s);
        // the key is the highest-u Gaussian 2; of the non-keys 0 (u 0.1) and 1 (u 0.101)
        // only 0 is strictly above the 2nd largest contribution
        assert_eq!(kn.role, vec![n, c, k, c]);
        assert_eq!((report.roles, report.nonkey_cap), ([1, 1, 0, 2], Some(2)));
    }

    /// Gaussians on a 40×40 grid in the plane z = 0 (x = i % 40, y = i / 40), u smallest
    /// at the centre, all reliable for 8 frames.
    fn plane() -> Tracks {
        let (n, nt) = (1600, 8);
        let mut tr = Tracks {
            ids: (0..n as u32).map(|i| 7 + i).collect(),
            num_frames: nt,
            ..Default::default()
        };
        for i in 0..n {
            let (x, y) = ((i % 40) as f32, (i / 40) as f32);
            for t in 0..nt {
                tr.positions.push([x, y, 0.0]);
                tr.u.push(
                    0.01 + ((x - 19.5).powi(2) + (y - 19.5).powi(2)) * 1e-4 + t as f32 * 1e-6,
                );
                tr.reliable.push(true);
            }
        }
        tr
    }

    #[test]
    fn auto_voxel_ladder_is_nested_and_meets_the_budget() {
        let tr = plane();
        let mut s = settings(Profile::Paper);
        s.candidates_per_frame = Amount::Fraction(0.5);
        let (k, r) = select_with_report(&tr, &s);
        // nested grids: the key count never grows with the voxel
        assert_eq!(r.keys_per_rung.len(), LADDER_RUNGS);
        assert!(r.keys_per_rung.windows(2).all(|w| w[0] >= w[1]), "{:?}", r.keys_per_rung);
        // the finest rung holds every confident Gaussian (800), so 2% of 1600 = 32 is met
        // exactly: the chosen rung fits, the next finer does not
        assert_eq!((r.budget, k.num_keys()), (Some(32), 32));
        assert!(r.keys_per_rung[r.rung] <= 32 && r.keys_per_rung[r.rung - 1] > 32);
        assert_eq!(r.topped_up, 32 - r.keys_per_rung[r.rung]);
        assert_eq!(r.voxel_size, Amount::Fraction(rung_fraction(r.rung)));
        // every key is confident somewhere, i.e. in the inner disc of 800 lowest-u Gaussians
        let ring = |i: usize| ((i % 40) as f32 - 19.5).powi(2) + ((i / 40) as f32 - 19.5).powi(2);
        let mut r2: Vec<f32> = (0..1600).map(ring).collect();
        r2.sort_by(f32::total_cmp);
        assert!(k.rows(Role::Key).iter().all(|&i| ring(i) <= r2[799]));
        // a budget below the coarsest rung's count is met by the random cap
        let one = select(&tr, &KeynodeSettings { key_budget: Amount::Value(1.0), ..s.clone() });
        assert_eq!(one.num_keys(), 1);
        // same bytes whatever the thread count, and the fixed-edge path is unchanged
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        assert_eq!(pool.install(|| select(&tr, &s)), k);
        let mut f = s.clone();
        f.voxel_size = VoxelSize::Fixed(Amount::Fraction(0.02));
        let (_, rf) = select_with_report(&tr, &f);
        assert_eq!((rf.keys_per_rung.len(), rf.budget, rf.rung), (1, None, 0));
        // ablation (d) nests over rungs as well
        let d = KeynodeSettings { candidate_sampling: CandidateSampling::Random, ..s.clone() };
        let (kd, rd) = select_with_report(&tr, &d);
        assert!(rd.keys_per_rung.windows(2).all(|w| w[0] >= w[1]), "{:?}", rd.keys_per_rung);
        assert_eq!(kd.num_keys(), 32);
    }
}
