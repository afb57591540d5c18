//! Every parameter of `usplat4d optimize`, declared once with
//! [`stage_params!`](crate::stage_params): its help, paper and release values and the row of
//! official-release.md Sec. 11 (or the section) it comes from. The macro generates the CLI
//! struct [`OptimizeParams`] (unset values take the profile's defaults) and the flat
//! [`OptimizeValues`]; [`OptimizeParams::settings`] groups those into the resolved
//! [`OptimizeSettings`] (learning rates, L_rgb, the graph objective, density control) that
//! the training loop reads and the provenance records. Where the paper gives no value, the
//! paper profile takes the release's (the rule).

use std::path::PathBuf;

use super::graph_loss::{AnchorMetric, GraphInit, GraphSettings, MetricFrame, Reduction};
use super::image_loss::ImageLossWeights;
use super::nonkey_weights::NonkeyWeights;
use crate::stages::params::{Profile, check};

/// Which objective is optimised.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Recipe {
    /// The base models' continuation: L_rgb, density control and kNN motion-locality terms
    /// among all Gaussians (the paper's fairness baseline).
    Vanilla,
    /// L_rgb + L_key + L_non-key on the uncertainty-aware graph (paper Eq. 11).
    Usplat4d,
}

crate::stage_params! {
    /// Parameters of `usplat4d optimize`; unset values take the profile's defaults.
    pub struct OptimizeParams;
    /// The parameters' values: the profile's defaults with the given ones applied
    /// ([`OptimizeParams::settings`] groups them into [`OptimizeSettings`]).
    pub struct OptimizeValues;
    inputs {
        /// Model directory to start from (gaussians.parquet + trajectories.parquet).
        #[arg(long, value_name = "MODEL_DIR")]
        model: PathBuf,
        /// Scene directory (training cameras and images).
        #[arg(long, value_name = "SCENE_DIR")]
        scene: PathBuf,
        /// Output model directory (plus training_log.parquet; key_nodes and edges with usplat4d).
        #[arg(long, value_name = "MODEL_DIR")]
        out: PathBuf,
        /// Objective.
        #[arg(long, value_enum)]
        recipe: Recipe,
        /// Directory holding uncertainty.parquet (usplat4d recipe).
        #[arg(long, value_name = "DIR")]
        uncertainty: Option<PathBuf>,
        /// Directory holding key_nodes.parquet (usplat4d recipe).
        #[arg(long, value_name = "DIR")]
        keynodes: Option<PathBuf>,
        /// Directory holding edges.parquet (usplat4d recipe).
        #[arg(long, value_name = "DIR")]
        edges: Option<PathBuf>,
        /// Optimisation steps [paper and release: 1600 for MoSca].
        #[arg(long)]
        steps: u32,
        /// Testing only: abort the process right after the checkpoint of this step.
        #[arg(long, hide = true)]
        abort_after_step: Option<u32>,
        /// Ablation (c) of the paper's Table 3: anchor and DQB terms without U.
        #[arg(long, help_heading = "Ablations")]
        no_loss_weighting: bool,
    }
    params {
        heading "Method" {
            /// Training frames per step, a seeded permutation per epoch.
            batch_frames: usize => usize [check::parsed] { paper "8", release "8" },
        }
        heading "Run" {
            /// Write a checkpoint (beside the output, `OUT.ckpt/`) every this many steps, 0 for
            /// none; a run started again resumes from it.
            checkpoint_every: u32 => Option<u32> [check::parsed] { paper "100", release "100" },
        }
        heading "Learning rates" as lr: LearningRates {
            /// Learning rate of the per-frame positions (the paper gives none: the release's).
            lr_position: f32 => f32 [check::non_negative32] { paper "1.6e-4", release "1.6e-4", row "57" },
            /// Learning rate of the per-frame rotations.
            lr_rotation: f32 => f32 [check::non_negative32] { paper "5e-2", release "5e-2", row "57" },
            /// Learning rate of the log-scales (MoSca lr_s, official-release §5.3).
            lr_scale: f32 => f32 [check::non_negative32] { paper "5e-3", release "5e-3" },
            /// Learning rate of the opacity logits (MoSca lr_o).
            lr_opacity: f32 => f32 [check::non_negative32] { paper "5e-2", release "5e-2" },
            /// Learning rate of the degree-0 colour (MoSca lr_sph).
            lr_color: f32 => f32 [check::non_negative32] { paper "2.5e-3", release "2.5e-3" },
            /// Learning rate of the higher SH coefficients (MoSca lr_sph / 20, 2.5e-3 / 20 in
            /// f32).
            lr_sh_rest: f32 => f32 [check::non_negative32] { paper "1.2499999e-4", release "1.2499999e-4" },
            /// Learning rate of the graph's own tensors (edge weights, source poses, θ).
            lr_graph: f32 => f32 [check::non_negative32] { paper "1e-4", release "1e-4", row "57" },
            /// Learning rate of the learned canonical edge lengths (`dists_key`).
            lr_lengths: f32 => f32 [check::non_negative32] { paper "1.6e-4", release "1.6e-4", row "57" },
        }
        heading "L_rgb" {
            /// λ of the SSIM term in L_rgb (paper: SoM's; `image_loss` docs).
            lambda_ssim: f64 => f64 [check::parsed] { paper "0.2", release "0.1" },
            /// Weight of the mask/alpha term (paper: SoM's).
            lambda_mask: f64 => f64 [check::parsed] { paper "1", release "0" },
            /// Weight of the scale/shift-invariant depth term (paper: SoM's).
            lambda_depth: f64 => f64 [check::parsed] { paper "0.5", release "0.1" },
            /// Weight of the 2D track term (paper: SoM's; release: the iPhone config).
            lambda_track: f64 => f64 [check::parsed] { paper "2", release "0.1" },
            /// How a step combines its batch frames' image terms: `mean` (one view's scale, as
            /// the base models weigh L_rgb; MoSca fits one view a step) or `sum` (the release's
            /// `photometric_fit` adds its 8 views' losses; §5.3).
            image_batch: Reduction => Reduction [check::choice] { paper "mean", release "sum" },
            /// The 2D track term acts at steps that are multiples of this (paper: Shape of
            /// Motion's, every step; release: MoSca's `track_loss_interval`, iPhone config).
            track_every: usize => usize [check::count] { paper "1", release "3" },
            /// Steps without the track term after the start and after each opacity reset
            /// (release: MoSca's `track_loss_protect_steps`).
            track_pause: u32 => u32 [check::parsed] { paper "0", release "100" },
            /// Whether a step that carries the track term adds to density control's gradient
            /// statistics (release: no, MoSca's `record_flag` with its `native_add3` renderer).
            track_density_stats: bool => bool [check::parsed] { paper "true", release "false" },
        }
        heading "Graph" {
            /// Weight of the whole graph loss (its DQB and key-motion terms); the key rigidity
            /// block's λs follow the profile's motion form (rows 45-50).
            lambda_graph: f64 => f64 [check::parsed] { paper "1", release "2", row "44" },
            /// Weight of the key anchor ‖p − p°‖ in fine-tuning (release: prep only; rows 39-40).
            key_anchor_weight: f64 => f64 [check::parsed] { paper "1", release "0", row "39" },
            /// Weight of the non-key anchor ‖p − p°‖.
            nonkey_anchor_weight: f64 => f64 [check::parsed] { paper "1", release "0", row "41" },
            /// Metric of the anchor and DQB deviations (paper-literal, release, euclidean; rows
            /// 15-17); `--no-loss-weighting` makes it euclidean.
            anchor_metric: AnchorMetric => AnchorMetric [check::choice]
                { paper "paper-literal", release "release", row "15" },
            /// Which frame's U weighs a non-key's anchor and DQB terms at frame t: `each` (U_{w,t,i},
            /// as L_key's Eq. 9) or `most-reliable` (Eq. 11's U_{w,i}, read as the u and camera of
            /// the non-key's t̂_i at every t; README "Deliberate readings").
            nonkey_metric_frame: MetricFrame => MetricFrame [check::choice]
                { paper "each", release "each" },
            /// Reduction of the graph objective's sums over frames and Gaussians: the anchor and
            /// DQB terms and App. A.2's key edge, velocity and acceleration terms (sum: Σ_t Σ_i as
            /// Eqs. 9 and 11 are written; mean: as the release and the base models average).
            graph_reduction: Reduction => Reduction [check::choice] { paper "sum", release "mean" },
            /// Log-base of the non-key DQB blend weights, before the trainable per-key sharpness θ
            /// and per-edge offsets Δw of both profiles (`table`: the edges table's weights, so
            /// w ∝ w_table^|θ|; `current`: exp(−λ d²)^|θ| with d the distance to the key at the
            /// non-key's t̂ in the current positions, recomputed each step as the release does).
            nonkey_weights: NonkeyWeights => NonkeyWeights [check::choice]
                { paper "table", release "current", row "32" },
            /// Weight of the L2 penalty mean(Δw²) on the non-key weight offsets within L_non-key
            /// (scaled by λ_graph; the paper has no Δw: the release's).
            nonkey_dweight_l2: f64 => f64 [check::parsed]
                { paper "1e-5", release "1e-5", row "42" },
            /// Add trainable per-non-key offsets (Δp, Δq) to the DQB output, the release's
            /// `per_nonkeyGaussian_dxyz_dxyzw` (the paper's DQB has none).
            nonkey_pose_offsets: bool => bool [check::parsed]
                { paper "false", release "true", row "36" },
            /// Weight of the L2 penalty mean(offset²) on those offsets within L_non-key (scaled by
            /// λ_graph).
            nonkey_offset_l2: f64 => f64 [check::parsed] { paper "1e-3", release "1e-3", row "42" },
            /// Weight of L^{motion,non-key}'s edge terms: App. A.2's isometry, rigidity and
            /// relative rotation (λ_iso, λ_rigid, λ_rot) over each non-key's key edges E_i with
            /// the edges table's weights (scaled by λ_graph; the release's L_nonkey has none).
            nonkey_motion_weight: f64 => f64 [check::parsed] { paper "1", release "0", row "55" },
            /// Multiplier of the non-keys' DQB terms (the position term, and the release's
            /// rotation term) within λ_graph: an ablation, 0 leaves each non-key to its anchor
            /// and edge terms.
            dqb_weight: f64 => f64 [check::non_negative] { paper "1", release "1" },
            /// Multiplier of the key edge terms of L^{motion,key} (isometry, rigidity, relative
            /// rotation over key-key edges) within λ_graph: an ablation.
            key_motion_weight: f64 => f64 [check::non_negative] { paper "1", release "1" },
            /// Depth ratio r_z of U.
            r_z: f64 => f64 [check::parsed] { paper "0.01", release "0.1", row "15" },
        }
        heading "Motion" {
            /// λ_vel of the usplat4d recipe (the vanilla recipe's is `--vanilla-vel`).
            lambda_vel: f64 => f64 [check::parsed] { paper "0.01", release "100", row "52" },
            /// λ_acc of the usplat4d recipe (the vanilla recipe's is `--vanilla-acc`).
            lambda_acc: f64 => f64 [check::parsed] { paper "0.01", release "1", row "53" },
            /// Fraction of the key-key edges kept each step.
            edge_keep_ratio: f64 => f64 [check::parsed] { paper "1", release "0.8", row "51" },
            /// Neighbours of the vanilla recipe's kNN motion graph.
            knn_k: usize => usize [check::parsed] { paper "8", release "8" },
            /// λ_iso = λ_rigid of the vanilla recipe's mean kNN isometry and rigidity terms: the
            /// base model's, MoSca's photometric-phase ARAP weight (USplat4D's App. A.2: 1).
            vanilla_knn: f64 => f64 [check::non_negative] { paper "10", release "10" },
            /// λ_vel of the vanilla recipe's mean velocity term: MoSca's photometric-phase
            /// weight (USplat4D's App. A.2: 0.01).
            vanilla_vel: f64 => f64 [check::non_negative] { paper "5", release "5" },
            /// λ_acc of the vanilla recipe's mean acceleration term: MoSca's photometric-phase
            /// weight (USplat4D's App. A.2: 0.01).
            vanilla_acc: f64 => f64 [check::non_negative] { paper "5", release "5" },
        }
        heading "Graph initialisation" {
            /// Iteration cap of each fit of the graph initialisation before fine-tuning (the
            /// non-keys' DQB source poses, then the keys; then the non-keys follow their keys'
            /// DQB), 0 for none (official-release §5.1; the paper names no procedure, and on
            /// the drifting priors it cost accuracy: README "Deliberate readings").
            graph_init_iters: u32 => u32 [check::parsed] { paper "0", release "10000", row "37" },
            /// Adam's starting learning rate of the graph initialisation (plateau schedule).
            graph_init_lr: f32 => f32 [check::parsed] { paper "0.1", release "0.1", row "37" },
            /// Fraction of the key edges kept per iteration of the key fit.
            graph_init_edge_keep: f64 => f64 [check::parsed]
                { paper "0.7", release "0.7", row "38" },
            /// Frames per iteration of the non-key fit.
            graph_init_batch: usize => usize [check::count] { paper "30", release "30", row "37" },
            /// Weight of the keys' acceleration term in the key fit.
            graph_init_acc: f64 => f64 [check::parsed] { paper "0.1", release "0.1", row "37" },
        }
        heading "Density control" as density: DensitySettings {
            /// Density control starts at this fraction of the steps.
            density_start: f32 => f32 [check::fraction] { paper "0.1", release "0.01", row "59" },
            /// Density control ends at this fraction of the steps.
            density_end: f32 => f32 [check::fraction] { paper "0.8", release "0.8", row "59" },
            /// Densify and prune every this many steps (official-release §5.3).
            densify_every: u32 => u32 [check::parsed] { paper "300", release "300" },
            /// Reset opacities every this many steps, 0 for never (official-release §5.3).
            opacity_reset_every: u32 => Option<u32> [check::parsed]
                { paper "1000", release "1000" },
            /// Mean screen-space (NDC) position-gradient norm above which a Gaussian is densified
            /// (official-release §5.3).
            densify_grad: f32 => f32 [check::parsed] { paper "2e-4", release "2e-4" },
            /// Largest scale, as a fraction of the scene extent, of a Gaussian that is cloned
            /// (larger ones are split; release percent_dense).
            percent_dense: f32 => f32 [check::parsed] { paper "0.01", release "0.01" },
            /// Prune Gaussians whose opacity falls below this (official-release §5.3).
            prune_opacity: f32 => f32 [check::parsed] { paper "0.01", release "0.01" },
        }
    }
    copied {
        heading "Method" {
            /// Seed of the frame order and the random edge subsets.
            seed: u64 [check::parsed] { default "0" },
        }
    }
}

/// Resolved settings of `usplat4d optimize` (recorded in the output's provenance and in the
/// checkpoint's fingerprint).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct OptimizeSettings {
    /// Objective.
    pub recipe: Recipe,
    /// The profile the defaults came from.
    pub profile: Profile,
    /// Optimisation steps.
    pub steps: u32,
    /// Training frames per step.
    pub batch_frames: usize,
    /// Seed.
    pub seed: u64,
    /// Checkpoint period (`None`: no checkpoints).
    pub checkpoint_every: Option<u32>,
    /// Ablation (c): no U in the anchor and DQB terms.
    pub no_loss_weighting: bool,
    /// Learning rates, one Adam group each.
    pub lr: LearningRates,
    /// L_rgb's terms, weights and forms (`image_loss`, App. A.3).
    pub image: ImageLossWeights,
    /// The usplat4d recipe's graph objective (rows 15-17, 39-55).
    pub graph: GraphSettings,
    /// kNN of the vanilla motion graph.
    pub knn_k: usize,
    /// λ_iso = λ_rigid, λ_vel, λ_acc of the vanilla recipe's mean terms.
    pub vanilla_weights: [f64; 3],
    /// Density control schedule and thresholds.
    pub density: DensitySettings,
    /// When the 2D track term acts.
    pub track: TrackSchedule,
}

/// When the 2D track term acts (MoSca's `track_loss_interval` and `track_loss_protect_steps`)
/// and whether its steps feed density control.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TrackSchedule {
    /// The term acts at steps that are multiples of this.
    pub every: usize,
    /// Steps without it after the start and after each opacity reset.
    pub pause: u32,
    /// Whether a step that carries it adds to the density statistics.
    pub density_stats: bool,
}

impl TrackSchedule {
    /// Whether the track term acts at `step`, the latest opacity reset before it being at
    /// step `last_reset` (0 when there was none: MoSca counts the pause from the start).
    pub fn active(&self, step: u32, last_reset: u32) -> bool {
        (step as usize).is_multiple_of(self.every.max(1))
            && (self.pause == 0 || step > last_reset + self.pause)
    }
}

impl DensitySettings {
    /// Whether density control acts at `step` (0-based) of `steps`: inside [start, end) and
    /// on the period.
    pub fn active(&self, step: u32, steps: u32) -> bool {
        let (lo, hi) = (self.density_start * steps as f32, self.density_end * steps as f32);
        let s = step as f32;
        s >= lo && s < hi && step > 0 && step.is_multiple_of(self.densify_every.max(1))
    }

    /// The latest step before `step` at which opacities were reset, 0 if none.
    pub fn last_reset_before(&self, step: u32, steps: u32) -> u32 {
        let Some(k) = self.opacity_reset_every.map(|k| k.max(1)) else { return 0 };
        // resets fall on multiples of k: look at those below `step`, latest first
        (1..step.div_ceil(k)).rev().map(|j| j * k).find(|&r| self.reset(r, steps)).unwrap_or(0)
    }

    /// Whether opacities are reset at `step` (inside the active window only).
    pub fn reset(&self, step: u32, steps: u32) -> bool {
        let (lo, hi) = (self.density_start * steps as f32, self.density_end * steps as f32);
        let s = step as f32;
        match self.opacity_reset_every {
            Some(k) => s >= lo && s < hi && step > 0 && step.is_multiple_of(k.max(1)),
            None => false,
        }
    }
}

impl OptimizeSettings {
    /// The defaults of `profile` for `recipe` (the declared values of [`OptimizeParams`]:
    /// official-release.md Sec. 11 rows 39-60 and Sec. 5.3; paper App. A.2, A.3 and B),
    /// `steps` 0.
    pub fn defaults(profile: Profile, recipe: Recipe) -> Self {
        Self::group(OptimizeValues::defaults(profile), recipe, 0, false)
    }

    /// The settings of the parameters' values `v`: the learning rates and density control
    /// as they are, L_rgb's and the graph objective's over their profile's defaults (which
    /// hold the forms that have no option).
    fn group(v: OptimizeValues, recipe: Recipe, steps: u32, no_loss_weighting: bool) -> Self {
        let g = GraphSettings::defaults(v.profile);
        // λ_graph scales the graph loss's weights relative to the profile's own λ_graph.
        let lg = v.lambda_graph / OptimizeValues::defaults(v.profile).lambda_graph;
        OptimizeSettings {
            recipe,
            profile: v.profile,
            steps,
            batch_frames: v.batch_frames,
            seed: v.seed,
            checkpoint_every: v.checkpoint_every,
            no_loss_weighting,
            lr: v.lr(),
            image: ImageLossWeights {
                ssim_lambda: v.lambda_ssim,
                mask: v.lambda_mask,
                depth: v.lambda_depth,
                track: v.lambda_track,
                batch: v.image_batch,
                ..ImageLossWeights::defaults(v.profile)
            },
            graph: GraphSettings {
                anchor_metric: if no_loss_weighting {
                    AnchorMetric::Euclidean
                } else {
                    v.anchor_metric
                },
                nonkey_metric_frame: v.nonkey_metric_frame,
                r_xyz: [g.r_xyz[0], g.r_xyz[1], v.r_z],
                reduction: v.graph_reduction,
                key_anchor: v.key_anchor_weight,
                nonkey_anchor: v.nonkey_anchor_weight,
                dqb: lg * g.dqb * v.dqb_weight,
                dqb_rotation: lg * g.dqb_rotation * v.dqb_weight,
                key_motion: lg * g.key_motion * v.key_motion_weight,
                nonkey_motion: lg * v.nonkey_motion_weight,
                lambda_vel_acc: [v.lambda_vel, v.lambda_acc],
                edge_keep_ratio: v.edge_keep_ratio,
                init: GraphInit {
                    max_iters: v.graph_init_iters,
                    lr: v.graph_init_lr,
                    edge_keep_ratio: v.graph_init_edge_keep,
                    batch_frames: v.graph_init_batch,
                    acceleration: v.graph_init_acc,
                },
                nonkey_weights: v.nonkey_weights,
                nonkey_dweight_l2: v.lambda_graph * v.nonkey_dweight_l2,
                nonkey_pose_offsets: v.nonkey_pose_offsets,
                nonkey_offset_l2: v.lambda_graph * v.nonkey_offset_l2,
                ..g
            },
            knn_k: v.knn_k,
            vanilla_weights: [v.vanilla_knn, v.vanilla_vel, v.vanilla_acc],
            density: v.density(),
            track: TrackSchedule {
                every: v.track_every,
                pause: v.track_pause,
                density_stats: v.track_density_stats,
            },
        }
    }
}

impl OptimizeParams {
    /// The profile's defaults with the given values applied, grouped and checked.
    pub fn settings(&self) -> anyhow::Result<OptimizeSettings> {
        let v = self.resolve()?;
        let s = OptimizeSettings::group(v, self.recipe, self.steps, self.no_loss_weighting);
        if s.batch_frames == 0 {
            anyhow::bail!("batch-frames must be at least 1");
        }
        if s.density.densify_every == 0 {
            anyhow::bail!("densify-every must be at least 1");
        }
        if !(0.0..=1.0).contains(&s.graph.edge_keep_ratio) {
            anyhow::bail!("edge-keep-ratio must be in [0, 1], got {}", s.graph.edge_keep_ratio);
        }
        if s.recipe == Recipe::Usplat4d {
            for (flag, v) in [
                ("--uncertainty", &self.uncertainty),
                ("--keynodes", &self.keynodes),
                ("--edges", &self.edges),
            ] {
                if v.is_none() {
                    anyhow::bail!("the usplat4d recipe needs {flag} DIR");
                }
            }
        }
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles_differ_where_the_release_table_says() {
        let p = OptimizeSettings::defaults(Profile::Paper, Recipe::Usplat4d);
        let r = OptimizeSettings::defaults(Profile::Release, Recipe::Usplat4d);
        assert_eq!((p.graph.key_motion, r.graph.key_motion), (1.0, 200.0));
        assert_eq!((p.graph.lambda_vel_acc, r.graph.lambda_vel_acc), ([0.01, 0.01], [100.0, 1.0]));
        assert_eq!((p.density.density_start, r.density.density_start), (0.10, 0.01));
        // the release's photometric_fit adds its 8 views' image losses, takes the track loss
        // every 3rd step after a pause, and records no density statistics then
        assert_eq!((p.image.batch, r.image.batch), (Reduction::Mean, Reduction::Sum));
        let (pt, rt) = (p.track, r.track);
        assert_eq!((pt.every, pt.pause, pt.density_stats), (1, 0, true));
        assert_eq!((rt.every, rt.pause, rt.density_stats), (3, 100, false));
        assert_eq!(p.lr, r.lr, "the paper gives no learning rates: both use the release's");
    }

    /// The release's track schedule over 1,600 steps: every 3rd step, none in the first 100
    /// steps nor in the 100 after the opacity reset at step 1,000.
    #[test]
    fn release_track_schedule_pauses_after_the_start_and_each_reset() {
        let r = OptimizeSettings::defaults(Profile::Release, Recipe::Usplat4d);
        let on = |step: u32| r.track.active(step, r.density.last_reset_before(step, 1600));
        assert_eq!(r.density.last_reset_before(1000, 1600), 0);
        assert_eq!(r.density.last_reset_before(1001, 1600), 1000);
        let steps: Vec<u32> = (0..1600).filter(|&t| on(t)).collect();
        assert_eq!(steps.first(), Some(&102));
        assert!(steps.iter().all(|t| t % 3 == 0 && !(1000..=1100).contains(t)));
        assert!(on(999) && on(1101) && !on(1002));
        let p = OptimizeSettings::defaults(Profile::Paper, Recipe::Usplat4d);
        assert!((0..1600).all(|t| p.track.active(t, p.density.last_reset_before(t, 1600))));
    }

    #[test]
    fn declared_values_are_the_objectives_defaults() {
        for profile in [Profile::Paper, Profile::Release] {
            let s = OptimizeSettings::defaults(profile, Recipe::Usplat4d);
            assert_eq!(s.graph, GraphSettings::defaults(profile), "{profile:?}");
            assert_eq!(s.image, ImageLossWeights::defaults(profile), "{profile:?}");
        }
    }

    #[test]
    fn given_values_override_the_profile() {
        let args = ["--model", "m", "--scene", "s", "--out", "o", "--steps", "10"];
        let parse = |extra: &[&str]| {
            let all: Vec<&str> = args.iter().chain(extra).copied().collect();
            crate::util::parse_args::<OptimizeParams>(&all).unwrap().settings()
        };
        let s =
            parse(&["--recipe", "vanilla", "--profile", "release", "--lambda-graph", "3"]).unwrap();
        let r = GraphSettings::defaults(Profile::Release);
        assert_eq!((s.graph.dqb, s.graph.key_motion), (1.5 * r.dqb, 1.5 * r.key_motion));
        let s = parse(&[
            "--recipe",
            "vanilla",
            "--profile",
            "release",
            "--dqb-weight",
            "0.5",
            "--key-motion-weight",
            "0",
            "--vanilla-vel",
            "4",
        ])
        .unwrap();
        let g = (s.graph.dqb, s.graph.dqb_rotation, s.graph.key_motion);
        assert_eq!(g, (0.5 * r.dqb, 0.5 * r.dqb_rotation, 0.0));
        let v = OptimizeSettings::defaults(Profile::Release, Recipe::Vanilla).vanilla_weights;
        assert_eq!(s.vanilla_weights, [v[0], 4.0, v[2]]);
        let s = parse(&[
            "--recipe",
            "vanilla",
            "--no-loss-weighting",
            "--checkpoint-every",
            "0",
            "--r-z",
            "0.5",
        ])
        .unwrap();
        assert_eq!(s.graph.anchor_metric, AnchorMetric::Euclidean);
        assert_eq!((s.checkpoint_every, s.graph.r_xyz[2]), (None, 0.5));
        for flag in ["--lr-position=-1", "--dqb-weight=-1", "--vanilla-acc=-1"] {
            let bad = ["--recipe", "vanilla", flag];
            let e =
                crate::util::parse_args::<OptimizeParams>(&[&args[..], &bad].concat()).unwrap_err();
            assert!(e.to_string().contains(flag.split('=').next().unwrap()), "{e}");
        }
        let e = parse(&["--recipe", "vanilla", "--batch-frames", "0"]).unwrap_err();
        assert!(e.to_string().contains("batch-frames"), "{e}");
        let e = parse(&["--recipe", "usplat4d", "--uncertainty", "u"]).unwrap_err();
        assert!(e.to_string().contains("--keynodes"), "{e}");
    }

    #[test]
    fn density_schedule_windows() {
        let r = OptimizeSettings::defaults(Profile::Release, Recipe::Vanilla).density;
        // release: 1% .. 80% of 1600 steps, every 300, reset every 1000
        let on: Vec<u32> = (0..1600).filter(|&s| r.active(s, 1600)).collect();
        assert_eq!(on, vec![300, 600, 900, 1200]);
        assert!(r.reset(1000, 1600) && !r.reset(1500, 1600));
        let p = OptimizeSettings::defaults(Profile::Paper, Recipe::Vanilla).density;
        let d = DensitySettings { densify_every: 10, ..p };
        let on: Vec<u32> = (0..100).filter(|&s| d.active(s, 100)).collect();
        assert_eq!(on, vec![10, 20, 30, 40, 50, 60, 70], "off for the first 10% and last 20%");
    }
}
