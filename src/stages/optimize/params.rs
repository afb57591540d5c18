//! Every parameter of `usplat4d optimize` in one place: the CLI/YAML struct
//! ([`OptimizeParams`], unset values take the profile's defaults) and the resolved settings
//! ([`OptimizeSettings`]) with the paper and release values side by side and the row of
//! official-release.md Sec. 11 (or the section) each comes from. Where the paper gives no
//! value, the paper profile takes the release's (the rule).

use std::path::PathBuf;

use super::graph_loss::{AnchorMetric, GraphSettings, Reduction};
use super::image_loss::ImageLossWeights;
use crate::stages::params::Profile;

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

/// Parameters of `usplat4d optimize`; unset values take the profile's defaults.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct OptimizeParams {
    /// Model directory to start from (gaussians.parquet + trajectories.parquet).
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: PathBuf,
    /// Scene directory (training cameras and images).
    #[arg(long, value_name = "SCENE_DIR")]
    pub scene: PathBuf,
    /// Output model directory (plus training_log.parquet; key_nodes and edges with usplat4d).
    #[arg(long, value_name = "MODEL_DIR")]
    pub out: PathBuf,
    /// Objective.
    #[arg(long, value_enum)]
    pub recipe: Recipe,
    /// Directory holding uncertainty.parquet (usplat4d recipe).
    #[arg(long, value_name = "DIR")]
    #[serde(default)]
    pub uncertainty: Option<PathBuf>,
    /// Directory holding key_nodes.parquet (usplat4d recipe).
    #[arg(long, value_name = "DIR")]
    #[serde(default)]
    pub keynodes: Option<PathBuf>,
    /// Directory holding edges.parquet (usplat4d recipe).
    #[arg(long, value_name = "DIR")]
    #[serde(default)]
    pub edges: Option<PathBuf>,
    /// Optimisation steps [paper and release: 1600 for MoSca].
    #[arg(long)]
    pub steps: u32,
    /// Which defaults the unset parameters take.
    #[arg(long, value_enum, default_value_t = Profile::Paper, help_heading = "Method")]
    #[serde(default)]
    pub profile: Profile,
    /// Training frames per step, a seeded permutation per epoch [8].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub batch_frames: Option<usize>,
    /// Seed of the frame order and the random edge subsets.
    #[arg(long, default_value_t = 0, help_heading = "Method")]
    #[serde(default)]
    pub seed: u64,
    /// Write a checkpoint (beside the output, `OUT.ckpt/`) every this many steps, 0 for
    /// none; a run started again resumes from it [100].
    #[arg(long, help_heading = "Run")]
    #[serde(default)]
    pub checkpoint_every: Option<u32>,
    /// Testing only: abort the process right after the checkpoint of this step.
    #[arg(long, hide = true)]
    #[serde(default)]
    pub abort_after_step: Option<u32>,
    /// Ablation (c) of the paper's Table 3: anchor and DQB terms without U.
    #[arg(long, help_heading = "Ablations")]
    #[serde(default)]
    pub no_loss_weighting: bool,
    /// Learning rate of the per-frame positions [1.6e-4; release row 57].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_position: Option<f32>,
    /// Learning rate of the per-frame rotations [5e-2; release row 57].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_rotation: Option<f32>,
    /// Learning rate of the log-scales [5e-3; MoSca lr_s, Sec. 5.3].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_scale: Option<f32>,
    /// Learning rate of the opacity logits [5e-2; MoSca lr_o].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_opacity: Option<f32>,
    /// Learning rate of the degree-0 colour [2.5e-3; MoSca lr_sph].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_color: Option<f32>,
    /// Learning rate of the higher SH coefficients [1.25e-4; MoSca lr_sph / 20].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_sh_rest: Option<f32>,
    /// Learning rate of the graph's own tensors (edge weights, source poses, θ) [1e-4; row 57].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_graph: Option<f32>,
    /// Learning rate of the learned canonical edge lengths [1.6e-4; `dists_key`, row 57].
    #[arg(long, help_heading = "Learning rates")]
    #[serde(default)]
    pub lr_lengths: Option<f32>,
    /// λ of the SSIM term in L_rgb [paper 0.2 (SoM), release 0.1; `image_loss` docs].
    #[arg(long, help_heading = "L_rgb")]
    #[serde(default)]
    pub lambda_ssim: Option<f32>,
    /// Weight of the mask/alpha term [paper 1 (SoM), release 0].
    #[arg(long, help_heading = "L_rgb")]
    #[serde(default)]
    pub lambda_mask: Option<f32>,
    /// Weight of the scale/shift-invariant depth term [paper 0.5 (SoM), release 0.1].
    #[arg(long, help_heading = "L_rgb")]
    #[serde(default)]
    pub lambda_depth: Option<f32>,
    /// Weight of the 2D track term [paper 2 (SoM), release 0.1 (iPhone cfg)].
    #[arg(long, help_heading = "L_rgb")]
    #[serde(default)]
    pub lambda_track: Option<f32>,
    /// Weight of the whole graph loss (its DQB and key-motion terms) [paper 1, release 2;
    /// row 44]. The key rigidity block's λs follow the profile's motion form (rows 45-50).
    #[arg(long, help_heading = "Graph")]
    #[serde(default)]
    pub lambda_graph: Option<f32>,
    /// Weight of the key anchor ‖p − p°‖ in fine-tuning [paper 1, release 0 (prep only);
    /// rows 39-40].
    #[arg(long, help_heading = "Graph")]
    #[serde(default)]
    pub key_anchor_weight: Option<f32>,
    /// Weight of the non-key anchor ‖p − p°‖ [paper 1, release 0; row 41].
    #[arg(long, help_heading = "Graph")]
    #[serde(default)]
    pub nonkey_anchor_weight: Option<f32>,
    /// Metric of the anchor and DQB deviations [paper paper-literal, release release;
    /// rows 15-17]; `--no-loss-weighting` makes it euclidean.
    #[arg(long, value_enum, help_heading = "Graph")]
    #[serde(default)]
    pub anchor_metric: Option<AnchorMetric>,
    /// Reduction of the anchor and DQB sums over (t, i) [paper sum (Σ_t Σ_i as Eqs. 9 and
    /// 11 are written), release mean].
    #[arg(long, value_enum, help_heading = "Graph")]
    #[serde(default)]
    pub graph_reduction: Option<Reduction>,
    /// Depth ratio r_z of U [paper 0.01, release 0.1; row 15].
    #[arg(long, help_heading = "Graph")]
    #[serde(default)]
    pub r_z: Option<f32>,
    /// λ_vel of the usplat4d recipe [paper 0.01, release 100; row 52]; the vanilla recipe
    /// uses App. A.2's 0.01.
    #[arg(long, help_heading = "Motion")]
    #[serde(default)]
    pub lambda_vel: Option<f32>,
    /// λ_acc of the usplat4d recipe [paper 0.01, release 1; row 53]; vanilla 0.01.
    #[arg(long, help_heading = "Motion")]
    #[serde(default)]
    pub lambda_acc: Option<f32>,
    /// Fraction of the key-key edges kept each step [paper 1, release 0.8; row 51].
    #[arg(long, help_heading = "Motion")]
    #[serde(default)]
    pub edge_keep_ratio: Option<f32>,
    /// Neighbours of the vanilla recipe's kNN motion graph [8].
    #[arg(long, help_heading = "Motion")]
    #[serde(default)]
    pub knn_k: Option<usize>,
    /// Density control starts at this fraction of the steps [paper 0.1, release 0.01; row 59].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub density_start: Option<f32>,
    /// Density control ends at this fraction of the steps [0.8; both profiles].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub density_end: Option<f32>,
    /// Densify and prune every this many steps [300; release Sec. 5.3].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub densify_every: Option<u32>,
    /// Reset opacities every this many steps, 0 for never [1000; release Sec. 5.3].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub opacity_reset_every: Option<u32>,
    /// Mean screen-space (NDC) position-gradient norm above which a Gaussian is densified
    /// [2e-4; release Sec. 5.3].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub densify_grad: Option<f32>,
    /// Largest scale, as a fraction of the scene extent, of a Gaussian that is cloned (larger
    /// ones are split) [0.01; release percent_dense].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub percent_dense: Option<f32>,
    /// Prune Gaussians whose opacity falls below this [0.01; release Sec. 5.3].
    #[arg(long, help_heading = "Density control")]
    #[serde(default)]
    pub prune_opacity: Option<f32>,
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
    /// Density control schedule and thresholds.
    pub density: DensitySettings,
}

/// Adam learning rates (constant; official-release.md Sec. 5.3 and row 57).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct LearningRates {
    /// Per-frame positions `[T, N, 3]`.
    pub position: f32,
    /// Per-frame rotations `[T, N, 4]`.
    pub rotation: f32,
    /// Log-scales `[N, 3]`.
    pub scale: f32,
    /// Opacity logits `[N]`.
    pub opacity: f32,
    /// Degree-0 colour `[N, 3]`.
    pub color: f32,
    /// Higher SH coefficients `[N, K, 3]`.
    pub sh_rest: f32,
    /// The graph's own tensors.
    pub graph: f32,
    /// Learned canonical edge lengths.
    pub lengths: f32,
}

/// Density control (paper App. B "Training"; release Sec. 5.3, rows 59-60).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct DensitySettings {
    /// First active step as a fraction of the steps.
    pub start: f32,
    /// End of the active window as a fraction of the steps.
    pub end: f32,
    /// Densify/prune period, steps.
    pub every: u32,
    /// Opacity reset period, steps (`None`: never).
    pub opacity_reset_every: Option<u32>,
    /// Mean NDC position-gradient norm threshold.
    pub grad: f32,
    /// Clone/split boundary as a fraction of the scene extent.
    pub percent_dense: f32,
    /// Opacity pruning threshold.
    pub prune_opacity: f32,
}

impl DensitySettings {
    /// Whether density control acts at `step` (0-based) of `steps`: inside [start, end) and
    /// on the period.
    pub fn active(&self, step: u32, steps: u32) -> bool {
        let (lo, hi) = (self.start * steps as f32, self.end * steps as f32);
        let s = step as f32;
        s >= lo && s < hi && step > 0 && step.is_multiple_of(self.every.max(1))
    }

    /// Whether opacities are reset at `step` (inside the active window only).
    pub fn reset(&self, step: u32, steps: u32) -> bool {
        let (lo, hi) = (self.start * steps as f32, self.end * steps as f32);
        let s = step as f32;
        match self.opacity_reset_every {
            Some(k) => s >= lo && s < hi && step > 0 && step.is_multiple_of(k.max(1)),
            None => false,
        }
    }
}

impl OptimizeSettings {
    /// The defaults of `profile` for `recipe` (official-release.md Sec. 11 rows 39-60 and
    /// Sec. 5.3; paper App. A.2, A.3 and B).
    pub fn defaults(profile: Profile, recipe: Recipe) -> Self {
        let paper = profile == Profile::Paper;
        let pr = |p: f32, r: f32| if paper { p } else { r };
        OptimizeSettings {
            recipe,
            profile,
            steps: 0,
            batch_frames: 8,
            seed: 0,
            checkpoint_every: Some(100),
            no_loss_weighting: false,
            lr: LearningRates {
                position: 1.6e-4,
                rotation: 5e-2,
                scale: 5e-3,
                opacity: 5e-2,
                color: 2.5e-3,
                sh_rest: 2.5e-3 / 20.0,
                graph: 1e-4,
                lengths: 1.6e-4,
            },
            image: ImageLossWeights::defaults(profile),
            graph: GraphSettings::defaults(profile),
            knn_k: 8,
            density: DensitySettings {
                start: pr(0.10, 0.01),
                end: 0.8,
                every: 300,
                opacity_reset_every: Some(1000),
                grad: 2e-4,
                percent_dense: 0.01,
                prune_opacity: 0.01,
            },
        }
    }
}

impl OptimizeParams {
    /// The graph objective's settings: the profile's, with the overrides applied.
    fn graph_settings(&self, d: &OptimizeSettings) -> GraphSettings {
        let g = &d.graph;
        let base_lambda = if self.profile == Profile::Paper { 1.0 } else { 2.0 };
        let lg = self.lambda_graph.map_or(1.0, |l| l as f64 / base_lambda);
        let f = |v: Option<f32>, d: f64| v.map_or(d, f64::from);
        GraphSettings {
            anchor_metric: if self.no_loss_weighting {
                AnchorMetric::Euclidean
            } else {
                self.anchor_metric.unwrap_or(g.anchor_metric)
            },
            r_xyz: [g.r_xyz[0], g.r_xyz[1], f(self.r_z, g.r_xyz[2])],
            reduction: self.graph_reduction.unwrap_or(g.reduction),
            key_anchor: f(self.key_anchor_weight, g.key_anchor),
            nonkey_anchor: f(self.nonkey_anchor_weight, g.nonkey_anchor),
            dqb: lg * g.dqb,
            dqb_rotation: lg * g.dqb_rotation,
            key_motion: lg * g.key_motion,
            lambda_vel_acc: [
                f(self.lambda_vel, g.lambda_vel_acc[0]),
                f(self.lambda_acc, g.lambda_vel_acc[1]),
            ],
            edge_keep_ratio: f(self.edge_keep_ratio, g.edge_keep_ratio),
            ..g.clone()
        }
    }

    /// The profile's defaults with the overrides applied, checked.
    pub fn resolve(&self) -> anyhow::Result<OptimizeSettings> {
        let d = OptimizeSettings::defaults(self.profile, self.recipe);
        let or = |v: Option<f32>, d: f32| v.unwrap_or(d);
        let s = OptimizeSettings {
            recipe: self.recipe,
            profile: self.profile,
            steps: self.steps,
            batch_frames: self.batch_frames.unwrap_or(d.batch_frames),
            seed: self.seed,
            checkpoint_every: match self.checkpoint_every {
                Some(0) => None,
                Some(k) => Some(k),
                None => d.checkpoint_every,
            },
            no_loss_weighting: self.no_loss_weighting,
            lr: LearningRates {
                position: or(self.lr_position, d.lr.position),
                rotation: or(self.lr_rotation, d.lr.rotation),
                scale: or(self.lr_scale, d.lr.scale),
                opacity: or(self.lr_opacity, d.lr.opacity),
                color: or(self.lr_color, d.lr.color),
                sh_rest: or(self.lr_sh_rest, d.lr.sh_rest),
                graph: or(self.lr_graph, d.lr.graph),
                lengths: or(self.lr_lengths, d.lr.lengths),
            },
            image: ImageLossWeights {
                ssim_lambda: self.lambda_ssim.map_or(d.image.ssim_lambda, f64::from),
                mask: self.lambda_mask.map_or(d.image.mask, f64::from),
                depth: self.lambda_depth.map_or(d.image.depth, f64::from),
                track: self.lambda_track.map_or(d.image.track, f64::from),
                ..d.image
            },
            graph: self.graph_settings(&d),
            knn_k: self.knn_k.unwrap_or(d.knn_k),
            density: DensitySettings {
                start: or(self.density_start, d.density.start),
                end: or(self.density_end, d.density.end),
                every: self.densify_every.unwrap_or(d.density.every),
                opacity_reset_every: match self.opacity_reset_every {
                    Some(0) => None,
                    Some(k) => Some(k),
                    None => d.density.opacity_reset_every,
                },
                grad: or(self.densify_grad, d.density.grad),
                percent_dense: or(self.percent_dense, d.density.percent_dense),
                prune_opacity: or(self.prune_opacity, d.density.prune_opacity),
            },
        };
        if s.batch_frames == 0 {
            anyhow::bail!("batch-frames must be at least 1");
        }
        if s.density.every == 0 {
            anyhow::bail!("densify-every must be at least 1");
        }
        let lrs = [
            ("lr-position", s.lr.position),
            ("lr-rotation", s.lr.rotation),
            ("lr-scale", s.lr.scale),
            ("lr-opacity", s.lr.opacity),
            ("lr-color", s.lr.color),
            ("lr-sh-rest", s.lr.sh_rest),
            ("lr-graph", s.lr.graph),
            ("lr-lengths", s.lr.lengths),
        ];
        for (name, v) in lrs {
            if !(v.is_finite() && v >= 0.0) {
                anyhow::bail!("{name} must be a non-negative number, got {v}");
            }
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
        assert_eq!((p.density.start, r.density.start), (0.10, 0.01));
        assert_eq!(p.lr, r.lr, "the paper gives no learning rates: both use the release's");
    }

    #[test]
    fn density_schedule_windows() {
        let r = OptimizeSettings::defaults(Profile::Release, Recipe::Vanilla).density;
        // release: 1% .. 80% of 1600 steps, every 300, reset every 1000
        let on: Vec<u32> = (0..1600).filter(|&s| r.active(s, 1600)).collect();
        assert_eq!(on, vec![300, 600, 900, 1200]);
        assert!(r.reset(1000, 1600) && !r.reset(1500, 1600));
        let p = OptimizeSettings::defaults(Profile::Paper, Recipe::Vanilla).density;
        let d = DensitySettings { every: 10, ..p };
        let on: Vec<u32> = (0..100).filter(|&s| d.active(s, 100)).collect();
        assert_eq!(on, vec![10, 20, 30, 40, 50, 60, 70], "off for the first 10% and last 20%");
    }
}
