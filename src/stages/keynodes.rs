//! Key-node selection (paper Sec. 4.2, "Key node selection"; official-release.md Sec. 3).
//!
//! Two stages, streamed frame by frame with O(N) state:
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
//! Ablations of the paper's Table 3: (a) `--candidate-source uniform` draws the per-frame
//! pool uniformly at random instead of by uncertainty; (d) `--candidate-sampling random`
//! picks as many Gaussians as there were occupied voxels, at random, without the grid.

use std::collections::HashMap;
use std::path::PathBuf;

use rayon::prelude::*;

use super::graph::{Amount, Profile, Tracks, rank_key};
use crate::context::Context;
use crate::tables::key_nodes::KeyNodes;

/// How one Gaussian is picked in an occupied voxel (profile row 20).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum VoxelPick {
    /// Uniformly at random (seeded).
    Random,
    /// The lowest-contribution (highest u) confident Gaussian of the voxel.
    LowestContribution,
}

/// Where the per-frame candidate pool comes from (ablation (a) of the paper's Table 3).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum CandidateSource {
    /// The most confident Gaussians (lowest u).
    Uncertainty,
    /// The same number of Gaussians, drawn uniformly at random (no uncertainty).
    Uniform,
}

/// How candidates are thinned out of the pool (ablation (d) of the paper's Table 3).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum CandidateSampling {
    /// One per occupied voxel of the 3D grid.
    Voxel,
    /// As many as there are occupied voxels, picked at random from the pool.
    Random,
}

/// How the significant period counts frames (profile row 21).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum SptCounting {
    /// Longest run of consecutive significant frames.
    Consecutive,
    /// Total number of significant frames.
    Total,
}

/// Parameters of `usplat4d keynodes`; unset values take the profile's defaults.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct KeynodeParams {
    /// Model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: PathBuf,
    /// Directory holding uncertainty.parquet.
    #[arg(long, value_name = "DIR")]
    pub uncertainty: PathBuf,
    /// Output directory (key_nodes.parquet).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Which defaults the unset parameters take.
    #[arg(long, value_enum, default_value_t = Profile::Paper, help_heading = "Method")]
    #[serde(default)]
    pub profile: Profile,
    /// Confident Gaussians per frame: a count or a percentage of N [paper 2%, release 1000].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub candidates_per_frame: Option<Amount>,
    /// Voxel edge: world units, or a percentage of the frame's bounding-box diagonal
    /// [paper 2%, release 0.2].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub voxel_size: Option<Amount>,
    /// Pick within a voxel [paper random, release lowest-contribution].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub voxel_pick: Option<VoxelPick>,
    /// Candidate pool (ablation (a): uniform) [uncertainty].
    #[arg(long, value_enum, help_heading = "Ablations")]
    #[serde(default)]
    pub candidate_source: Option<CandidateSource>,
    /// Candidate thinning (ablation (d): random) [voxel].
    #[arg(long, value_enum, help_heading = "Ablations")]
    #[serde(default)]
    pub candidate_sampling: Option<CandidateSampling>,
    /// Significant-period counting [paper consecutive, release total].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub spt_counting: Option<SptCounting>,
    /// Upper cap on the per-frame significance threshold of u [paper none, release 2, i.e.
    /// normalised contribution 0.5].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub spt_u_max: Option<f32>,
    /// Minimum significant period, frames [5].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub min_significant_period: Option<u32>,
    /// Cap on the number of keys, 0 for none [paper none, release 1500].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub max_key_nodes: Option<usize>,
    /// Seed of the random picks.
    #[arg(long, default_value_t = 0, help_heading = "Method")]
    #[serde(default)]
    pub seed: u64,
}

/// Concrete settings of key-node selection (recorded in the table's provenance).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct KeynodeSettings {
    /// The profile the defaults came from.
    pub profile: Profile,
    /// Confident Gaussians per frame.
    pub candidates_per_frame: Amount,
    /// Voxel edge.
    pub voxel_size: Amount,
    /// Pick within a voxel.
    pub voxel_pick: VoxelPick,
    /// Candidate pool.
    pub candidate_source: CandidateSource,
    /// Candidate thinning.
    pub candidate_sampling: CandidateSampling,
    /// Significant-period counting.
    pub spt_counting: SptCounting,
    /// Cap on the per-frame significance threshold (infinite for none).
    pub spt_u_max: f32,
    /// Minimum significant period.
    pub min_significant_period: u32,
    /// Cap on the number of keys (`None`: no cap).
    #[serde(default)]
    pub max_key_nodes: Option<usize>,
    /// Seed.
    pub seed: u64,
}

impl KeynodeSettings {
    /// The defaults of `profile` (official-release.md Sec. 11, rows 18-24).
    pub fn defaults(profile: Profile) -> Self {
        let paper = profile == Profile::Paper;
        KeynodeSettings {
            profile,
            candidates_per_frame: if paper {
                Amount::Fraction(0.02)
            } else {
                Amount::Value(1000.0)
            },
            voxel_size: if paper { Amount::Fraction(0.02) } else { Amount::Value(0.2) },
            voxel_pick: if paper { VoxelPick::Random } else { VoxelPick::LowestContribution },
            candidate_source: CandidateSource::Uncertainty,
            candidate_sampling: CandidateSampling::Voxel,
            spt_counting: if paper { SptCounting::Consecutive } else { SptCounting::Total },
            spt_u_max: if paper { f32::INFINITY } else { 2.0 },
            min_significant_period: 5,
            max_key_nodes: if paper { None } else { Some(1500) },
            seed: 0,
        }
    }
}

impl KeynodeParams {
    /// The profile's defaults with the overrides applied.
    pub fn resolve(&self) -> KeynodeSettings {
        let d = KeynodeSettings::defaults(self.profile);
        KeynodeSettings {
            profile: self.profile,
            candidates_per_frame: self.candidates_per_frame.unwrap_or(d.candidates_per_frame),
            voxel_size: self.voxel_size.unwrap_or(d.voxel_size),
            voxel_pick: self.voxel_pick.unwrap_or(d.voxel_pick),
            candidate_source: self.candidate_source.unwrap_or(d.candidate_source),
            candidate_sampling: self.candidate_sampling.unwrap_or(d.candidate_sampling),
            spt_counting: self.spt_counting.unwrap_or(d.spt_counting),
            spt_u_max: self.spt_u_max.unwrap_or(d.spt_u_max),
            min_significant_period: self.min_significant_period.unwrap_or(d.min_significant_period),
            max_key_nodes: match self.max_key_nodes {
                Some(0) => None,
                Some(m) => Some(m),
                None => d.max_key_nodes,
            },
            seed: self.seed,
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

/// Select the key nodes of `tracks` (stage 1 and 2 above). Deterministic for a seed,
/// whatever the thread count.
pub fn select(tracks: &Tracks, s: &KeynodeSettings) -> KeyNodes {
    let (n, nt) = (tracks.len(), tracks.num_frames);
    let mut period = vec![Period { best_u: f32::INFINITY, ..Default::default() }; n];
    let mut candidate = vec![false; n];
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
        for i in frame_candidates(&pool, &p_t, &u_t, &tracks.ids, s, t as u64) {
            candidate[i] = true;
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
    let mut is_key: Vec<bool> =
        (0..n).map(|i| candidate[i] && (uniform || spt[i] >= s.min_significant_period)).collect();
    if let Some(cap) = s.max_key_nodes {
        let keys: Vec<usize> = (0..n).filter(|&i| is_key[i]).collect();
        if keys.len() > cap {
            is_key = vec![false; n];
            for i in random_subset(keys.into_iter(), cap, s.seed, u64::MAX, &tracks.ids) {
                is_key[i] = true;
            }
        }
    }
    KeyNodes {
        id: tracks.ids.clone(),
        is_key,
        t_hat: period.iter().map(|p| p.t_hat).collect(),
        significant_period: spt,
    }
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

/// The candidates of one frame: one Gaussian of `pool` per occupied voxel, or (ablation d)
/// as many at random. `p` and `u` are the frame's `[N]` positions and uncertainties.
fn frame_candidates(
    pool: &[usize],
    p: &[[f32; 3]],
    u: &[f32],
    ids: &[u32],
    s: &KeynodeSettings,
    t: u64,
) -> Vec<usize> {
    if pool.is_empty() {
        return Vec::new();
    }
    let size = match s.voxel_size {
        Amount::Value(v) => v,
        Amount::Fraction(f) => f * bbox_diagonal(p),
    }
    .max(f64::MIN_POSITIVE);
    let mut best: HashMap<[i64; 3], usize> = HashMap::with_capacity(pool.len());
    for &i in pool {
        let better = |j: usize| match s.voxel_pick {
            VoxelPick::Random => {
                (rank_key(s.seed, t, ids[i] as u64), i) < (rank_key(s.seed, t, ids[j] as u64), j)
            }
            VoxelPick::LowestContribution => u[i].total_cmp(&u[j]).then(j.cmp(&i)).is_gt(),
        };
        best.entry(voxel(p[i], size))
            .and_modify(|j| {
                if better(*j) {
                    *j = i
                }
            })
            .or_insert(i);
    }
    match s.candidate_sampling {
        CandidateSampling::Voxel => best.into_values().collect(),
        CandidateSampling::Random => {
            random_subset(pool.iter().copied(), best.len(), s.seed, t ^ 0x5EED, ids)
        }
    }
}

/// Diagonal of the axis-aligned bounding box of `p`.
fn bbox_diagonal(p: &[[f32; 3]]) -> f64 {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for q in p {
        for k in 0..3 {
            lo[k] = lo[k].min(q[k] as f64);
            hi[k] = hi[k].max(q[k] as f64);
        }
    }
    (0..3).map(|k| (hi[k] - lo[k]).max(0.0).powi(2)).sum::<f64>().sqrt()
}

/// `usplat4d keynodes`: read the model and the uncertainty table, select, write
/// `OUT/key_nodes.parquet`.
pub fn run(p: &KeynodeParams, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("keynodes").entered();
    let settings = p.resolve();
    let model = crate::model::Model::load(&p.model)?;
    let unc = p
        .uncertainty
        .join(<crate::tables::uncertainty::UncertaintyTable as crate::tables::Table>::file_name());
    let tracks = super::graph::load_tracks(&model, &unc, ctx)?;
    let keys = select(&tracks, &settings);
    ctx.info(format!(
        "keynodes: {} key nodes of {} Gaussians ({} frames)",
        keys.num_keys(),
        tracks.len(),
        tracks.num_frames
    ));
    let prov = crate::tables::Provenance::new(
        "keynodes",
        &serde_json::json!({ "params": p, "resolved": settings }),
    );
    let out =
        p.out.join(<crate::tables::key_nodes::KeyNodesTable as crate::tables::Table>::file_name());
    crate::tables::key_nodes::write(&out, &keys, &prov)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn one_pick_per_voxel_among_confident_gaussians() {
        // 8 Gaussians at x = 0..7, voxel edge 2: voxels {0,1} {2,3} {4,5} {6,7}. The three
        // most confident are 0, 1 and 4, so voxels {0,1} and {4,5} survive.
        let tr = tracks(8, 6, |i, _| [0.1, 0.2, 5.0, 5.0, 0.3, 5.0, 5.0, 5.0][i]);
        let mut s = settings(Profile::Release);
        s.candidates_per_frame = Amount::Value(3.0);
        s.voxel_size = Amount::Value(2.0);
        s.spt_u_max = f32::INFINITY;
        let k = select(&tr, &s);
        // lowest contribution (highest u) in voxel {0,1} is 1; voxel {4,5} has only 4.
        assert_eq!(k.is_key, vec![false, true, false, false, true, false, false, false]);
        assert_eq!(k.significant_period[1], 6);
        s.voxel_pick = VoxelPick::Random;
        // a random pick per voxel and frame: the union over frames stays within the voxels
        let k = select(&tr, &s);
        assert!(k.is_key[4] && (k.is_key[0] || k.is_key[1]));
        assert_eq!(k.num_keys(), (0..8).filter(|&i| k.is_key[i] && [0, 1, 4].contains(&i)).count());
    }

    #[test]
    fn random_picks_are_seeded() {
        let tr = tracks(400, 8, |i, t| 0.01 + ((i * 7 + t * 13) % 97) as f32 / 100.0);
        let mut s = settings(Profile::Paper);
        s.candidates_per_frame = Amount::Value(200.0);
        s.voxel_size = Amount::Value(10.0);
        s.min_significant_period = 1;
        let a = select(&tr, &s);
        assert_eq!(a, select(&tr, &s));
        let b = select(&tr, &KeynodeSettings { seed: 7, ..s.clone() });
        assert_ne!(a.is_key, b.is_key);
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
        s.voxel_size = Amount::Value(0.5);
        s.candidates_per_frame = Amount::Value(2.0);
        let k = select(&tr, &s);
        assert_eq!(k.significant_period, vec![3, 6, 0, 0]);
        assert_eq!(k.is_key, vec![false, true, false, false]);
        assert_eq!(k.t_hat, vec![0, 0, 0, 0]);
        s.spt_counting = SptCounting::Total;
        let k = select(&tr, &s);
        assert_eq!(k.significant_period, vec![5, 6, 0, 0]);
        assert_eq!(k.is_key, vec![true, true, false, false]);
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
        let yaml = "model: m\nuncertainty: u\nout: o\nprofile: release\nmax-key-nodes: 0\nvoxel-size: 5%\n";
        let o: KeynodeParams = serde_saphyr::from_str(yaml).unwrap();
        assert_eq!(o.resolve().max_key_nodes, None);
        assert_eq!(o.resolve().voxel_size, Amount::Fraction(0.05));
        assert_eq!(o.resolve().voxel_pick, VoxelPick::LowestContribution);
        // release caps the number of keys at random
        let tr = tracks(50, 6, |_, _| 0.1);
        let mut s = r.clone();
        s.voxel_size = Amount::Value(0.5);
        s.max_key_nodes = Some(10);
        assert_eq!(select(&tr, &s).num_keys(), 10);
    }

    #[test]
    fn ablations_change_the_candidates() {
        let tr = tracks(300, 6, |i, _| if i < 100 { 0.1 + i as f32 * 1e-3 } else { 0.5 });
        let mut s = settings(Profile::Paper);
        s.candidates_per_frame = Amount::Value(30.0);
        s.voxel_size = Amount::Value(5.0);
        s.voxel_pick = VoxelPick::LowestContribution;
        let full = select(&tr, &s);
        // confident Gaussians are 0..30 at x = 0..30 → 6 voxels, one key each.
        assert_eq!(full.num_keys(), 6);
        assert!((0..300).all(|i| !full.is_key[i] || i < 30));
        let d = select(
            &tr,
            &KeynodeSettings { candidate_sampling: CandidateSampling::Random, ..s.clone() },
        );
        assert!((0..300).all(|i| !d.is_key[i] || i < 30));
        assert_ne!(d.is_key, full.is_key);
        let a = select(
            &tr,
            &KeynodeSettings { candidate_source: CandidateSource::Uniform, ..s.clone() },
        );
        assert!((30..300).any(|i| a.is_key[i]));
    }
}
