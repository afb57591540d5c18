//! Dual quaternion blending (DQB; paper Eq. 10, Kavan et al. 2007) as MoSca implements it
//! (`lib_mosca/scaffold_utils/dualquat_helper.py`, `mosca.py::__DQB_warp__`; release §5.2),
//! in f64, with the vector-Jacobian product (VJP) of every step.
//!
//! A dual quaternion is `[real | dual]` (8 values, quaternions w, x, y, z). A rigid transform
//! (unit rotation q, translation t) is `[q, ½ (0, t) ⊗ q]` (`Rt2dq`). Blending sums weighted
//! dual quaternions, then [`unit`] divides by the dual-number norm (`dq2unitdq`: real part
//! ‖p‖, dual part ⟨p, q⟩/‖p‖; a real part shorter than [`UNIT_EPS`] becomes the identity) and
//! [`to_rt`] reads R = R(p/‖p‖), t = 2 vec(q ⊗ p*) (`dq2Rt`). There is no antipodal sign fix
//! inside the blend: like pytorch3d's `matrix_to_quaternion` (v0.7.6+), each relative
//! rotation is standardised to w ≥ 0 before blending ([`relative`]).

use super::quat64::{self as q4, M3, Q, V3};

/// A dual quaternion `[real (w, x, y, z) | dual (w, x, y, z)]`.
pub type Dq = [f64; 8];

/// The identity transform.
pub const IDENTITY: Dq = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];

/// `dq2unitdq` replaces a dual quaternion whose real part is shorter than this with the
/// identity (MoSca's corner case).
pub const UNIT_EPS: f64 = 1e-4;

/// Real part.
#[inline]
pub fn real(d: &Dq) -> Q {
    [d[0], d[1], d[2], d[3]]
}

/// Dual part.
#[inline]
pub fn dual(d: &Dq) -> Q {
    [d[4], d[5], d[6], d[7]]
}

/// `[r | d]`.
#[inline]
pub fn join(r: Q, d: Q) -> Dq {
    [r[0], r[1], r[2], r[3], d[0], d[1], d[2], d[3]]
}

/// `Rt2dq` with the rotation given as a unit quaternion: `[q, ½ (0, t) ⊗ q]`.
#[inline]
pub fn from_rt(q: Q, t: V3) -> Dq {
    join(q, q4::mul(q4::pure(t), q).map(|v| 0.5 * v))
}

/// VJP of [`from_rt`]: `(g_q, g_t)`.
#[inline]
pub fn from_rt_vjp(q: Q, t: V3, g: &Dq) -> (Q, V3) {
    let g_d = dual(g).map(|v| 0.5 * v);
    let (g_t4, g_q_d) = q4::mul_vjp(q4::pure(t), q, g_d);
    let g_r = real(g);
    ([0, 1, 2, 3].map(|k| g_r[k] + g_q_d[k]), q4::vec3(g_t4))
}

/// The unit dual quaternion of a pose (unnormalised rotation `q`, position `p`), and ‖q‖.
#[inline]
pub fn from_pose(q: Q, p: V3) -> (Dq, f64) {
    let (u, n) = q4::normalize(q);
    (from_rt(u, p), n)
}

/// VJP of [`from_pose`] given the unit dual quaternion `d` it returned and ‖q‖.
#[inline]
pub fn from_pose_vjp(d: &Dq, n: f64, p: V3, g: &Dq) -> (Q, V3) {
    let u = real(d);
    let (g_u, g_p) = from_rt_vjp(u, p, g);
    (q4::normalize_vjp(u, n, g_u), g_p)
}

/// Dual quaternion product `a ⊗ b` (the transform `a ∘ b`).
#[inline]
pub fn mul(a: &Dq, b: &Dq) -> Dq {
    let (ar, ad, br, bd) = (real(a), dual(a), real(b), dual(b));
    let r = q4::mul(ar, br);
    let d1 = q4::mul(ar, bd);
    let d2 = q4::mul(ad, br);
    join(r, [d1[0] + d2[0], d1[1] + d2[1], d1[2] + d2[2], d1[3] + d2[3]])
}

/// VJP of [`mul`]: `(g_a, g_b)`.
#[inline]
pub fn mul_vjp(a: &Dq, b: &Dq, g: &Dq) -> (Dq, Dq) {
    let (ar, ad, br, bd) = (real(a), dual(a), real(b), dual(b));
    let (gr, gd) = (real(g), dual(g));
    let (ga_r1, gb_r1) = q4::mul_vjp(ar, br, gr);
    let (ga_r2, gb_d) = q4::mul_vjp(ar, bd, gd);
    let (ga_d, gb_r2) = q4::mul_vjp(ad, br, gd);
    let add = |x: Q, y: Q| [x[0] + y[0], x[1] + y[1], x[2] + y[2], x[3] + y[3]];
    (join(add(ga_r1, ga_r2), ga_d), join(add(gb_r1, gb_r2), gb_d))
}

/// Quaternion conjugate of both parts: the inverse of a unit dual quaternion.
#[inline]
pub fn conj(d: &Dq) -> Dq {
    [d[0], -d[1], -d[2], -d[3], d[4], -d[5], -d[6], -d[7]]
}

/// The relative transform `T_dst ∘ T_src⁻¹` of two unit dual quaternions (a key's motion
/// from its source frame to the target frame, `__compute_delta_Rt_ji__` then `Rt2dq`),
/// negated when its real part has w < 0 (pytorch3d's standardisation); and that sign.
#[inline]
pub fn relative(dst: &Dq, src: &Dq) -> (Dq, f64) {
    let e = mul(dst, &conj(src));
    if e[0] < 0.0 { (e.map(|v| -v), -1.0) } else { (e, 1.0) }
}

/// VJP of [`relative`] given its sign: `(g_dst, g_src)`.
#[inline]
pub fn relative_vjp(dst: &Dq, src: &Dq, sign: f64, g: &Dq) -> (Dq, Dq) {
    let g = g.map(|v| sign * v);
    let (g_dst, g_csrc) = mul_vjp(dst, &conj(src), &g);
    (g_dst, conj(&g_csrc))
}

/// The dual-number norm `(‖p‖, ⟨p, q⟩ / max(‖p‖, 1e-8))` (`dq2dualnorm`).
pub fn dual_norm(d: &Dq) -> (f64, f64) {
    let a = q4::norm(real(d));
    (a, q4::dot4(real(d), dual(d)) / a.max(1e-8))
}

/// `dq2unitdq`: `d` divided by its dual-number norm, so that ‖p‖ = 1 and ⟨p, q⟩ = 0; the
/// identity when ‖p‖ < [`UNIT_EPS`].
pub fn unit(d: &Dq) -> Dq {
    let (p, q) = (real(d), dual(d));
    let a = q4::norm(p);
    if a < UNIT_EPS {
        return IDENTITY;
    }
    let c = q4::dot4(p, q);
    let (ia, ia3) = (1.0 / a, 1.0 / (a * a * a));
    join(p.map(|v| v * ia), [0, 1, 2, 3].map(|k| q[k] * ia - p[k] * c * ia3))
}

/// VJP of [`unit`] (0 in the identity branch).
pub fn unit_vjp(d: &Dq, g: &Dq) -> Dq {
    let (p, q) = (real(d), dual(d));
    let a = q4::norm(p);
    if a < UNIT_EPS {
        return [0.0; 8];
    }
    let (gp_, gq_) = (real(g), dual(g));
    let c = q4::dot4(p, q);
    let h = q4::dot4(p, gq_);
    let (ia, ia3, ia5) = (1.0 / a, 1.0 / a.powi(3), 1.0 / a.powi(5));
    // p' = p / a
    let u = p.map(|v| v * ia);
    let gpn = q4::normalize_vjp(u, a, gp_);
    // q' = q / a − p c / a³, c = ⟨p, q⟩
    let qg = q4::dot4(q, gq_);
    let mut out = [0.0; 8];
    for k in 0..4 {
        out[k] =
            gpn[k] - qg * p[k] * ia3 - c * gq_[k] * ia3 - h * q[k] * ia3 + 3.0 * c * h * p[k] * ia5;
        out[4 + k] = gq_[k] * ia - h * p[k] * ia3;
    }
    out
}

/// `dq2Rt`: R = R(p / ‖p‖) (pytorch3d's `quaternion_to_matrix` normalises) and
/// t = 2 vec(q ⊗ p*), for a unit dual quaternion.
pub fn to_rt(d: &Dq) -> (M3, V3) {
    let (p, q) = (real(d), dual(d));
    let (u, _) = q4::normalize(p);
    let t = q4::vec3(q4::mul(q, q4::conj(p)));
    (q4::to_rotmat(u), t.map(|v| 2.0 * v))
}

/// VJP of [`to_rt`].
pub fn to_rt_vjp(d: &Dq, g_r: &M3, g_t: V3) -> Dq {
    let (p, q) = (real(d), dual(d));
    let (u, n) = q4::normalize(p);
    let g4 = q4::pure(g_t.map(|v| 2.0 * v));
    let (g_q, g_pc) = q4::mul_vjp(q, q4::conj(p), g4);
    let g_u = q4::to_rotmat_vjp(u, g_r);
    let g_pn = q4::normalize_vjp(u, n, g_u);
    let g_p = q4::conj(g_pc);
    join([0, 1, 2, 3].map(|k| g_p[k] + g_pn[k]), g_q)
}

/// The result of warping one point: position and rotation (unit, w ≥ 0) at the target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Warped {
    /// Warped position `R src_p + t`.
    pub p: V3,
    /// Warped rotation `p_B ⊗ src_q/‖src_q‖`, standardised to w ≥ 0.
    pub q: Q,
}

/// Blend the relative transforms `rel[k]` (from [`relative`]) with weights `w[k]` (not
/// renormalised here), make the sum a unit dual quaternion and apply it to the source pose
/// (`src_p`, unnormalised `src_q`): MoSca's `__DQB_warp__` body after `Rt2dq`.
pub fn warp(rel: &[Dq], w: &[f64], src_p: V3, src_q: Q) -> Warped {
    Warp::new(&blend(rel, w), src_p, src_q).out
}

/// `Σ_k w_k rel_k`.
#[inline]
pub fn blend(rel: &[Dq], w: &[f64]) -> Dq {
    let mut b = [0.0; 8];
    for (d, &wk) in rel.iter().zip(w) {
        for c in 0..8 {
            b[c] += wk * d[c];
        }
    }
    b
}

/// Cotangents of [`warp`]'s inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarpGrad {
    /// Cotangent of the blended (not yet unit) dual quaternion: `g_rel[k] = w_k · g_blend`
    /// and `g_w[k] = ⟨rel_k, g_blend⟩`.
    pub blend: Dq,
    /// Cotangent of `src_p`.
    pub src_p: V3,
    /// Cotangent of `src_q` (unnormalised).
    pub src_q: Q,
}

/// VJP of [`warp`] for the output cotangents `g_p`, `g_q`.
pub fn warp_vjp(rel: &[Dq], w: &[f64], src_p: V3, src_q: Q, g_p: V3, g_q: Q) -> WarpGrad {
    Warp::new(&blend(rel, w), src_p, src_q).vjp(g_p, g_q)
}

/// One warp of a source pose by a blended dual quaternion, keeping what its VJP reuses, so a
/// loss computes the forward pass once: [`Warp::new`] then [`Warp::vjp`].
#[derive(Debug, Clone, Copy)]
pub struct Warp {
    /// The output.
    pub out: Warped,
    b: Dq,
    ub: Dq,
    r: M3,
    src_p: V3,
    sq: Q,
    sn: f64,
    pb: Q,
    pn: f64,
}

impl Warp {
    /// Warp (`src_p`, unnormalised `src_q`) by the blend `b` (see [`warp`]).
    #[inline]
    pub fn new(b: &Dq, src_p: V3, src_q: Q) -> Self {
        let ub = unit(b);
        let (r, t) = to_rt(&ub);
        let mp = q4::mat_vec(&r, src_p);
        let (sq, sn) = q4::normalize(src_q);
        let (pb, pn) = q4::normalize(real(&ub));
        let out = Warped {
            p: [mp[0] + t[0], mp[1] + t[1], mp[2] + t[2]],
            q: q4::standardize(q4::mul(pb, sq)),
        };
        Warp { out, b: *b, ub, r, src_p, sq, sn, pb, pn }
    }

    /// VJP for the output cotangents `g_p`, `g_q`.
    #[inline]
    pub fn vjp(&self, g_p: V3, g_q: Q) -> WarpGrad {
        let prod = q4::mul(self.pb, self.sq);
        let sign = if prod[0] < 0.0 { -1.0 } else { 1.0 };
        let g_prod = g_q.map(|v| sign * v);
        let (g_pb, g_sq) = q4::mul_vjp(self.pb, self.sq, g_prod);
        let mut g_r = [[0.0; 3]; 3];
        q4::add_outer(&mut g_r, g_p, self.src_p);
        let g_src_p = q4::mat_t_vec(&self.r, g_p);
        let mut g_ub = to_rt_vjp(&self.ub, &g_r, g_p);
        let g_pr = q4::normalize_vjp(self.pb, self.pn, g_pb);
        for k in 0..4 {
            g_ub[k] += g_pr[k];
        }
        WarpGrad {
            blend: unit_vjp(&self.b, &g_ub),
            src_p: g_src_p,
            src_q: q4::normalize_vjp(self.sq, self.sn, g_sq),
        }
    }
}

#[cfg(test)]
mod tests;
