//! The in-memory [`Tracks`] of the graph stages: positions and uncertainties of the graph's
//! Gaussians over all frames, loaded frame by frame from a model and an uncertainty table,
//! or generated ([`synthetic_tracks`], for tests and `bench graph`).
//!
//! Memory: `N·T·(12 + 4 + 1)` bytes (positions, u, reliable flag); for N = 200,000
//! Gaussians and T = 475 frames that is 1.6 GB, the largest array of the graph stages.

use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};

use crate::model::Model;
use crate::stages::params::{Shared, check};
use crate::tables::Table;
use crate::tables::uncertainty::{UncertaintyReader, UncertaintyTable};
use crate::util::rng::Rng;

/// Positions and uncertainties of the graph's Gaussians over all frames, Gaussian-major.
#[derive(Debug, Clone, Default)]
pub struct Tracks {
    /// `gaussian_id` of each graph node `[N]` (the uncertainty table's order).
    pub ids: Vec<u32>,
    /// Number of frames T.
    pub num_frames: usize,
    /// World positions `[N, T]`: `positions[i * T + t]`.
    pub positions: Vec<[f32; 3]>,
    /// Scalar uncertainty u_{i,t} `[N, T]` (φ when unreliable).
    pub u: Vec<f32>,
    /// Whether u_{i,t} is a measured value (converged and seen, Eq. 5's 𝟙_{i,t} = 1) `[N, T]`.
    pub reliable: Vec<bool>,
}

impl Tracks {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Position of Gaussian `i` at frame `t`.
    pub fn pos(&self, i: usize, t: usize) -> [f32; 3] {
        self.positions[i * self.num_frames + t]
    }

    /// u of Gaussian `i` at frame `t`.
    pub fn u(&self, i: usize, t: usize) -> f32 {
        self.u[i * self.num_frames + t]
    }

    /// Whether Gaussian `i` is reliable (converged and seen) at frame `t`.
    pub fn reliable(&self, i: usize, t: usize) -> bool {
        self.reliable[i * self.num_frames + t]
    }

    /// Check that the arrays agree with N and T.
    pub fn check(&self) -> Result<(), String> {
        let nt = self.len() * self.num_frames;
        if self.positions.len() != nt || self.u.len() != nt || self.reliable.len() != nt {
            return Err(format!(
                "tracks of {} Gaussians x {} frames hold {} positions, {} u, {} flags",
                self.len(),
                self.num_frames,
                self.positions.len(),
                self.u.len(),
                self.reliable.len()
            ));
        }
        Ok(())
    }
}

/// Which Gaussians the graph stages (`keynodes`, `edges`) take as nodes (issue 15 item 1).
/// `uncertainty` renders every Gaussian either way, so a static background still occludes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum GraphScope {
    /// The dynamic Gaussians (both profiles, as the release, which builds its graph on the
    /// foreground model only): a large, well-observed static background would otherwise fill
    /// the confident pool and the key budget, and dynamic non-keys would follow static keys.
    Dynamic,
    /// Every Gaussian of the uncertainty table.
    All,
}

/// `--graph-scope` of `keynodes` and `edges`, declared once for both (profile row 3).
pub const GRAPH_SCOPE: Shared<GraphScope> = Shared {
    doc: &[
        "Gaussians taken into the graph (dynamic, all): the others get the key-node role",
        "`unlinked`, no edges, and are nobody's neighbour.",
    ],
    parse: check::choice,
    paper: "dynamic",
    release: "dynamic",
    row: "3",
};

/// Diagonal of the axis-aligned bounding box of the positions `p` `[N, 3]` (0 for none).
pub fn bbox_diagonal(p: &[[f32; 3]]) -> f64 {
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

/// The tracks of the Gaussians in a [`GraphScope`], and where they sit in the uncertainty
/// table.
#[derive(Debug, Clone)]
pub struct ScopedTracks {
    /// The in-scope Gaussians' tracks.
    pub tracks: Tracks,
    /// `gaussian_id` of every row of the uncertainty table `[N_table]`.
    pub table_ids: Vec<u32>,
    /// Row in the uncertainty table of each in-scope Gaussian `[N]`, ascending.
    pub table_rows: Vec<usize>,
}

/// What the graph stages (`keynodes`, `edges`) read the graph's Gaussians from: a model and
/// its uncertainty table.
#[derive(Debug, Clone, clap::Args, serde::Serialize)]
pub struct GraphInputs {
    /// Model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: PathBuf,
    /// Directory holding uncertainty.parquet.
    #[arg(long, value_name = "DIR")]
    pub uncertainty: PathBuf,
}

impl GraphInputs {
    /// Load the model, and the tracks of its Gaussians in `scope` ([`load_tracks`]).
    pub fn load(
        &self,
        scope: GraphScope,
        ctx: &crate::context::Context,
    ) -> anyhow::Result<(Model, ScopedTracks)> {
        let model = Model::load(&self.model)?;
        let unc = self.uncertainty.join(UncertaintyTable::file_name());
        let scoped = load_tracks(&model, &unc, scope, ctx)?;
        Ok((model, scoped))
    }
}

/// Load the tracks of the Gaussians of `uncertainty_file` in `scope` from `model`, frame by
/// frame. The table lists every Gaussian of the model or (release `scope dynamic-only`) its
/// dynamic ones.
pub fn load_tracks(
    model: &Model,
    uncertainty_file: &Path,
    scope: GraphScope,
    ctx: &crate::context::Context,
) -> anyhow::Result<ScopedTracks> {
    let unc = UncertaintyReader::open(uncertainty_file)?;
    let nt = unc.num_frames();
    if nt != model.num_frames() {
        anyhow::bail!(
            "{}: {nt} frames, but the model {} has {}",
            uncertainty_file.display(),
            model.dir.display(),
            model.num_frames()
        );
    }
    let num_dynamic = model.gaussians.dynamic.iter().filter(|d| **d).count();
    if unc.ids().len() != model.gaussians.len() && unc.ids().len() != num_dynamic {
        anyhow::bail!(
            "{}: {} rows per frame, expected one per Gaussian of the model {} ({}) or one per \
             dynamic Gaussian ({num_dynamic})",
            uncertainty_file.display(),
            unc.ids().len(),
            model.dir.display(),
            model.gaussians.len()
        );
    }
    let index: std::collections::HashMap<u32, usize> =
        model.gaussians.id.iter().enumerate().map(|(i, id)| (*id, i)).collect();
    let rows: Vec<usize> = unc
        .ids()
        .iter()
        .enumerate()
        .map(|(row, id)| {
            index.get(id).copied().ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: column 'gaussian_id', row {row}: Gaussian {id} is not in the model {}",
                    uncertainty_file.display(),
                    model.dir.display()
                )
            })
        })
        .collect::<anyhow::Result<_>>()?;
    let table_rows: Vec<usize> = (0..rows.len())
        .filter(|&r| scope == GraphScope::All || model.gaussians.dynamic[rows[r]])
        .collect();
    let rows: Vec<usize> = table_rows.iter().map(|&r| rows[r]).collect();
    let n = rows.len();
    let mut tracks = Tracks {
        ids: table_rows.iter().map(|&r| unc.ids()[r]).collect(),
        num_frames: nt,
        positions: vec![[0.0; 3]; n * nt],
        u: vec![0.0; n * nt],
        reliable: vec![false; n * nt],
    };
    let bar = ctx.progress(nt as u64, "load tracks");
    for t in 0..nt {
        let state = model.frame(t)?;
        let f = unc.frame(t)?;
        for (i, (&row, &r)) in rows.iter().zip(&table_rows).enumerate() {
            tracks.positions[i * nt + t] = state.position[row];
            tracks.u[i * nt + t] = f.u[r];
            tracks.reliable[i * nt + t] = f.converged[r] && f.n_pixels[r] > 0;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(ScopedTracks { tracks, table_ids: unc.ids().to_vec(), table_rows })
}

/// A synthetic scene of `groups` rigid blobs: the tracks, the training cameras' R_cw `[T]`
/// and the group of each Gaussian `[N]`; 30% of the Gaussians start hidden (see
/// [`synthetic_tracks_hidden`]).
pub fn synthetic_tracks(
    n: usize,
    nt: usize,
    groups: usize,
    seed: u64,
) -> (Tracks, Vec<DMat3>, Vec<u32>) {
    synthetic_tracks_hidden(n, nt, groups, 0.3, seed)
}

/// [`synthetic_tracks`] where a fraction `hidden` of the Gaussians starts unreliable
/// (u = φ) and each frame flips a Gaussian's visibility with probability 0.05 (never when
/// `hidden` is 0).
pub fn synthetic_tracks_hidden(
    n: usize,
    nt: usize,
    groups: usize,
    hidden: f64,
    seed: u64,
) -> (Tracks, Vec<DMat3>, Vec<u32>) {
    let flip = if hidden > 0.0 { 0.05 } else { 0.0 };
    let mut rng = Rng::new(seed);
    let groups = groups.max(1);
    let motion: Vec<(DVec3, DVec3, DVec3, f64)> = (0..groups)
        .map(|g| {
            let angle = std::f64::consts::TAU * g as f64 / groups as f64;
            let centre = DVec3::new(3.0 * angle.cos(), 3.0 * angle.sin(), rng.normal() * 0.3);
            let vel = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.01;
            let axis = DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize_or(DVec3::Z);
            (centre, vel, axis, 0.01 + 0.02 * rng.uniform())
        })
        .collect();
    let mut tracks = Tracks { ids: (0..n as u32).collect(), num_frames: nt, ..Default::default() };
    tracks.positions.reserve(n * nt);
    tracks.u.reserve(n * nt);
    tracks.reliable.reserve(n * nt);
    let mut group = Vec::with_capacity(n);
    for _ in 0..n {
        let g = (rng.next_u64() % groups as u64) as usize;
        group.push(g as u32);
        let (centre, vel, axis, omega) = motion[g];
        let offset = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.6;
        let base_u = (0.05 * (0.7 * rng.normal()).exp()) as f32;
        let mut is_hidden = rng.uniform() < hidden;
        for t in 0..nt {
            let rot = DQuat::from_axis_angle(axis, omega * t as f64);
            let p = centre + vel * t as f64 + rot * offset;
            tracks.positions.push(p.as_vec3().to_array());
            if rng.uniform() < flip {
                is_hidden = !is_hidden;
            }
            let u = base_u * (0.3 * rng.normal()).exp() as f32;
            tracks.u.push(if is_hidden { 1e8 } else { u });
            tracks.reliable.push(!is_hidden);
        }
    }
    let rotations = (0..nt)
        .map(|t| {
            let a = 0.01 * t as f64;
            let eye = DVec3::new(8.0 * a.cos(), 8.0 * a.sin(), 2.0);
            let f = (-eye).normalize();
            let r = f.cross(DVec3::Z).normalize();
            let d = f.cross(r);
            // rows of R_cw are the camera axes (x right, y down, z forward) in world
            DMat3::from_cols(r, d, f).transpose()
        })
        .collect();
    (tracks, rotations, group)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An uncertainty table of another model's size is blamed itself, not the key nodes
    /// that a later check would find disagreeing with it.
    #[test]
    fn an_uncertainty_table_of_another_size_names_itself() {
        use crate::tables::uncertainty::{UncertaintyFrame, UncertaintyWriter};
        let dir = tempfile::tempdir().unwrap();
        let (_, model_dir) = crate::datasets::demo::write_demo_scene(dir.path(), 2).unwrap();
        let model = Model::load(&model_dir).unwrap();
        let ids = &model.gaussians.id[..10];
        let path = dir.path().join("uncertainty.parquet");
        let mut w = UncertaintyWriter::create(&path, ids, &Default::default()).unwrap();
        for t in 0..2 {
            w.write(&UncertaintyFrame {
                frame: t,
                sum_w2: vec![1.0; 10],
                sum_w: vec![1.0; 10],
                n_pixels: vec![1; 10],
                converged: vec![true; 10],
                u: vec![1.0; 10],
            })
            .unwrap();
        }
        w.finish().unwrap();
        let err = load_tracks(&model, &path, GraphScope::All, &crate::context::Context::quiet())
            .unwrap_err();
        assert_eq!(
            err.to_string(),
            format!(
                "{}: 10 rows per frame, expected one per Gaussian of the model {} (576) or one \
                 per dynamic Gaussian (576)",
                path.display(),
                model_dir.display()
            )
        );
    }
}
