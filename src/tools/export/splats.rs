//! One model frame as the Gaussians a splat viewer draws: the frame's pose of every Gaussian
//! (dynamic ones move, static ones repeat theirs), the static attributes, and the colour as
//! 3DGS spherical-harmonic coefficients in the world frame.
//!
//! Conventions (the 3DGS reference `GaussianModel` and the viewers that read its files):
//! `f_dc = (dc − 0.5) / C0` for the degree-0 RGB `dc` the gaussians table stores, and the
//! higher coefficients `[N, K, 3]` as stored. A model whose SH are evaluated in the
//! Gaussian's local frame (`ShFrame::Local`, MoSca) is rotated into the world frame per
//! frame: the world coefficients reproduce `Σ_k Y_k(Rᵀd)·rest_k` for every direction d,
//! solved by least squares on a fixed set of 64 directions (exact up to rounding, since a
//! rotation maps each band of the basis onto itself).

use crate::math::quat;
use crate::model::{FrameState, Gaussians};
use crate::render::ShFrame;
use crate::render::sh::{self, C0};

/// One frame's Gaussians in 3DGS terms, `[N]` each (canonical order), activated values.
#[derive(Debug, Clone, PartialEq)]
pub struct Splats {
    /// World positions.
    pub position: Vec<[f32; 3]>,
    /// Unit rotations `w, x, y, z` (local-to-world).
    pub rotation: Vec<[f32; 4]>,
    /// Linear scales along the local axes, world units.
    pub scale: Vec<[f32; 3]>,
    /// Opacity in [0, 1].
    pub opacity: Vec<f32>,
    /// Degree-0 SH coefficient per channel (`f_dc`).
    pub f_dc: Vec<[f32; 3]>,
    /// SH degree shared by all Gaussians.
    pub sh_degree: u8,
    /// Higher coefficients in the world frame, `[N, K, 3]` flattened (K = (degree+1)² − 1).
    pub sh_rest: Vec<f32>,
}

impl Splats {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.position.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }

    /// Higher-order coefficients per Gaussian, K.
    pub fn num_rest(&self) -> usize {
        sh::num_basis(self.sh_degree) - 1
    }

    /// The Gaussians of frame `state` of a model with static attributes `g` whose SH are
    /// evaluated in `frame`.
    pub fn from_frame(g: &Gaussians, frame: ShFrame, state: &FrameState) -> Splats {
        let rotation: Vec<[f32; 4]> = state
            .rotation
            .iter()
            .map(|q| quat::normalize(*q).map_or([1.0, 0.0, 0.0, 0.0], |(u, _)| u))
            .collect();
        let k3 = g.sh_rest_len();
        let sh_rest = match frame {
            ShFrame::World => g.sh_rest.clone(),
            ShFrame::Local if k3 == 0 => Vec::new(),
            ShFrame::Local => {
                let fit = BandFit::new(g.sh_degree);
                let mut out = Vec::with_capacity(g.sh_rest.len());
                for (rest, q) in g.sh_rest.chunks_exact(k3).zip(&rotation) {
                    out.extend(fit.to_world(rest, *q));
                }
                out
            }
        };
        Splats {
            position: state.position.clone(),
            rotation,
            scale: g.scale.clone(),
            opacity: g.opacity.clone(),
            f_dc: g.color.iter().map(|c| c.map(|v| ((v as f64 - 0.5) / C0) as f32)).collect(),
            sh_degree: g.sh_degree,
            sh_rest,
        }
    }
}

/// Least-squares fit of world-frame SH coefficients to values sampled on fixed directions.
struct BandFit {
    degree: u8,
    /// Sample directions `[D, 3]` (a Fibonacci sphere).
    dirs: Vec<[f32; 3]>,
    /// Pseudo-inverse `[K, D]` of the basis matrix `A[d][k] = Y_{k+1}(dir_d)`.
    pinv: Vec<Vec<f64>>,
}

impl BandFit {
    /// Directions sampled: well above the 15 unknowns of degree 3.
    const DIRECTIONS: usize = 64;

    fn new(degree: u8) -> BandFit {
        let n = Self::DIRECTIONS;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let dirs: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = golden * i as f64;
                [(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]
            })
            .collect();
        let k = sh::num_basis(degree) - 1;
        let a: Vec<[f32; 16]> = dirs.iter().map(|d| sh::basis_values(degree, *d)).collect();
        // normal equations (AᵀA) X = Aᵀ over all K functions at once (a discrete set of
        // directions does not keep the bands orthogonal, so they are fitted jointly)
        let mut ata = vec![vec![0.0f64; k]; k];
        for row in &a {
            for i in 0..k {
                for j in 0..k {
                    ata[i][j] += row[i + 1] as f64 * row[j + 1] as f64;
                }
            }
        }
        let inv = invert(ata);
        let pinv = (0..k)
            .map(|i| {
                a.iter().map(|row| (0..k).map(|j| inv[i][j] * row[j + 1] as f64).sum()).collect()
            })
            .collect();
        BandFit { degree, dirs, pinv }
    }

    /// World-frame coefficients `[K, 3]` of local-frame coefficients `rest` of a Gaussian
    /// with unit rotation `q`: `Σ_k Y_k(d)·out_k = Σ_k Y_k(Rᵀd)·rest_k` for every d.
    fn to_world(&self, rest: &[f32], q: [f32; 4]) -> Vec<f32> {
        let r = quat::to_rotmat(q);
        let values: Vec<[f32; 3]> = self
            .dirs
            .iter()
            .map(|d| {
                let local = r.transpose() * glam::Vec3::from_array(*d);
                sh::eval_unclamped(self.degree, [0.0; 3], rest, local.to_array())
            })
            .collect();
        let mut out = vec![0.0f32; rest.len()];
        for (k, p) in self.pinv.iter().enumerate() {
            for c in 0..3 {
                let v: f64 = p.iter().zip(&values).map(|(w, val)| w * val[c] as f64).sum();
                out[k * 3 + c] = v as f32;
            }
        }
        out
    }
}

/// Inverse of a small symmetric positive-definite matrix by Gauss-Jordan elimination.
fn invert(mut a: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    let n = a.len();
    let mut inv: Vec<Vec<f64>> =
        (0..n).map(|i| (0..n).map(|j| if i == j { 1.0 } else { 0.0 }).collect()).collect();
    for col in 0..n {
        let pivot =
            (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).unwrap_or(col);
        a.swap(col, pivot);
        inv.swap(col, pivot);
        let p = a[col][col];
        for j in 0..n {
            a[col][j] /= p;
            inv[col][j] /= p;
        }
        for i in 0..n {
            if i != col {
                let f = a[i][col];
                for j in 0..n {
                    a[i][j] -= f * a[col][j];
                    inv[i][j] -= f * inv[col][j];
                }
            }
        }
    }
    inv
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Local-frame SH rotated into the world frame give the colour the renderer computes
    /// for the local model, in every direction (degree 3, arbitrary rotations).
    #[test]
    fn local_sh_rotated_to_world_give_the_same_colour() {
        let mut rng = crate::util::rng::Rng::new(7);
        let fit = BandFit::new(3);
        for _ in 0..20 {
            let rest: Vec<f32> = (0..45).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            let q = quat::normalize(std::array::from_fn(|_| rng.range_f32(-1.0, 1.0))).unwrap().0;
            let world = fit.to_world(&rest, q);
            let r = quat::to_rotmat(q);
            for _ in 0..20 {
                let d = glam::Vec3::new(
                    rng.range_f32(-1.0, 1.0),
                    rng.range_f32(-1.0, 1.0),
                    rng.range_f32(-1.0, 1.0),
                )
                .normalize();
                let local = sh::eval_unclamped(3, [0.5; 3], &rest, (r.transpose() * d).into());
                let w = sh::eval_unclamped(3, [0.5; 3], &world, d.into());
                for c in 0..3 {
                    assert!((local[c] - w[c]).abs() < 1e-4, "{local:?} vs {w:?}");
                }
            }
        }
    }

    /// World-frame SH pass through unchanged; `f_dc` inverts `dc = 0.5 + C0·f_dc`.
    #[test]
    fn world_sh_are_kept_and_dc_is_the_3dgs_coefficient() {
        let (mut g, frames) = crate::model::sample_model();
        g.sh_degree = 1;
        g.sh_rest = (0..g.len() * 9).map(|i| i as f32 * 0.01).collect();
        let s = Splats::from_frame(&g, ShFrame::World, &frames[0]);
        assert_eq!(s.sh_rest, g.sh_rest);
        for (f, c) in s.f_dc.iter().zip(&g.color) {
            for k in 0..3 {
                assert!(((0.5 + C0 * f[k] as f64) as f32 - c[k]).abs() < 1e-6);
            }
        }
    }
}
