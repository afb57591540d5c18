//! Velocity and acceleration of each Gaussian over time (paper Appendix A.2's L_vel and
//! L_acc; the release's `loss_dy.py`), in the form of [`MotionForm`], with analytic
//! gradients to positions and raw rotations.
//!
//! Paper (norms 1): velocity `Σ_{t≥1} Σ_i ‖p_{t−1} − p_t‖₁ + ‖std(r_t) − 1‖₁` and
//! acceleration `Σ_{t≥2} Σ_i ‖p_{t−2} − 2p_{t−1} + p_t‖₁ + ‖std(r_{t−1} r_t*) − 1‖₁` with
//! the relative rotations r_t = q_{t−1} q_t* of unit quaternions, std = the w ≥ 0
//! representative. Release: velocity `Σ ‖p_t − p_{t+1}‖²/3 + ‖q_t − q_{t+1}‖²/4` and
//! acceleration `Σ ‖2p_{t−1} − p_{t−2} − p_t‖ + ‖2q_{t−1} − q_{t−2} − q_t‖` (raw q), means
//! with the norms of [`smoothness_means`].
//!
//! Work layout: the terms couple only the frames of one Gaussian, so the (sorted) Gaussians
//! are cut into fixed chunks, and each chunk sweeps the frames in order straight from the
//! frame-major f32 poses, keeping three frames of f64 state per Gaussian (the paper form
//! two Gaussians at a time in SIMD lanes, [`crate::math::lanes`]). A chunk owns its
//! Gaussians' gradient entries (a column range of every frame row), each of which receives
//! one f32 addition once its frame is complete; chunk values are reduced in chunk order.
//! Neither depends on the number of threads, and nothing of size T × N is copied.

use rayon::prelude::*;

use super::motion::MotionForm;
use super::poses::{PoseGrads, Poses};
use crate::math::lanes::{Lanes, Mask};
use crate::math::quat64::{self as q4, Q, V3};

/// Gaussians per chunk of the sweep (a chunk's state is about 140 kB).
const CHUNK: usize = 256;

/// The norms that make the velocity and acceleration of [`smoothness`] means over `m`
/// Gaussians and the T − 1 and T − 2 frame steps of T `frames` (the release's means); the
/// paper's sums use norm 1.
pub fn smoothness_means(frames: usize, m: usize) -> (f64, f64) {
    let per = |d: usize| 1.0 / (frames.saturating_sub(d) * m).max(1) as f64;
    (per(1), per(2))
}

/// Velocity and acceleration over the Gaussians `nodes` of `poses` (distinct pose indices), `[velocity, acceleration]`, each `norm ·` its sum (unscaled), with `scale ·`
/// its gradient added to `grads`; `vel` and `acc` are `(norm, scale)`.
pub fn smoothness(
    poses: &Poses,
    nodes: &[u32],
    form: MotionForm,
    (norm_v, scale_v): (f64, f64),
    (norm_a, scale_a): (f64, f64),
    grads: &mut PoseGrads,
) -> [f64; 2] {
    let mut sorted = nodes.to_vec();
    sorted.sort_unstable();
    assert!(sorted.windows(2).all(|w| w[0] < w[1]), "smoothness: a node twice");
    let nodes = &sorted[..];
    let (nt, n) = (poses.frames, poses.n);
    if nt < 2 || nodes.is_empty() {
        return [0.0; 2];
    }
    assert!((*nodes.last().unwrap() as usize) < n, "smoothness: node out of range");
    // Each chunk's column range [lo, hi) of every frame row, split off the rows in order.
    let chunks: Vec<&[u32]> = nodes.chunks(CHUNK).collect();
    let mut rows: Vec<Vec<RowPart>> = chunks.iter().map(|_| Vec::with_capacity(nt)).collect();
    for (gp, gq) in grads.position.chunks_mut(n).zip(grads.rotation.chunks_mut(n)) {
        let (mut gp, mut gq, mut at) = (gp, gq, 0);
        for (c, ch) in chunks.iter().enumerate() {
            let (lo, hi) = (ch[0] as usize, *ch.last().unwrap() as usize + 1);
            let (_, rest_p) = std::mem::take(&mut gp).split_at_mut(lo - at);
            let (_, rest_q) = std::mem::take(&mut gq).split_at_mut(lo - at);
            let (own_p, rest_p) = rest_p.split_at_mut(hi - lo);
            let (own_q, rest_q) = rest_q.split_at_mut(hi - lo);
            rows[c].push((own_p, own_q));
            (gp, gq, at) = (rest_p, rest_q, hi);
        }
    }
    let parts: Vec<[f64; 2]> = chunks
        .into_par_iter()
        .zip(rows)
        .map(|(ch, mut rows)| {
            let lo = ch[0] as usize;
            let load = |t: usize, k: usize| {
                let i = t * n + ch[k] as usize;
                (q4::v64(poses.position[i]), q4::q64(poses.rotation[i]))
            };
            let emit = |t: usize, k: usize, g_p: V3, g_q: Q| {
                let (rp, rq) = &mut rows[t];
                let j = ch[k] as usize - lo;
                for c in 0..3 {
                    rp[j][c] += g_p[c] as f32;
                }
                for c in 0..4 {
                    rq[j][c] += g_q[c] as f32;
                }
            };
            sweep(nt, ch.len(), form, (scale_v * norm_v, scale_a * norm_a), load, emit)
        })
        .collect();
    let [v, a] = parts.iter().fold([0.0; 2], |s, p| [s[0] + p[0], s[1] + p[1]]);
    [norm_v * v, norm_a * a]
}

/// A chunk's part of one frame's position and rotation gradient rows.
type RowPart<'a> = (&'a mut [[f32; 3]], &'a mut [[f32; 4]]);

/// `L` Gaussians at one frame of a [`sweep`]: their poses in f64 and the gradients so far.
#[derive(Debug, Clone, Copy)]
struct Slot<const L: usize> {
    p: [Lanes<L>; 3],
    /// Raw rotation, its unit quaternion and 1/norm (0 for a zero q).
    q: [Lanes<L>; 4],
    u: [Lanes<L>; 4],
    qn: Lanes<L>,
    /// d/dp, d/d(raw q) and d/d(unit q).
    gp: [Lanes<L>; 3],
    gq: [Lanes<L>; 4],
    gu: [Lanes<L>; 4],
}

impl<const L: usize> Default for Slot<L> {
    fn default() -> Self {
        let z = Lanes::default();
        Slot { p: [z; 3], q: [z; 4], u: [z; 4], qn: z, gp: [z; 3], gq: [z; 4], gu: [z; 4] }
    }
}

/// The sums of [`smoothness`] over `m` Gaussians and `frames` frames (unnormalised
/// `[velocity, acceleration]`), frames in order: `load(t, k)` gives Gaussian k's position
/// and raw rotation at frame t, and `emit(t, k, g_p, g_q)` receives its gradient there
/// (`k_v, k_a` = scale · norm of each term), once per (t, k) when frame t is complete.
/// The paper form runs two Gaussians at a time in the lanes of [`Lanes`]; the release
/// form, lighter and bound by its loads, one (measured faster so).
fn sweep(
    frames: usize,
    m: usize,
    form: MotionForm,
    k: (f64, f64),
    load: impl Fn(usize, usize) -> (V3, Q),
    emit: impl FnMut(usize, usize, V3, Q),
) -> [f64; 2] {
    match form {
        MotionForm::Paper => sweep_lanes::<2>(frames, m, form, k, load, emit),
        MotionForm::Release => sweep_lanes::<1>(frames, m, form, k, load, emit),
    }
}

/// [`sweep`] with `L` Gaussians per block (the last block padded with identity poses that
/// are never emitted), each lane with the arithmetic of one Gaussian; the sums add the
/// Gaussians' terms in order.
fn sweep_lanes<const L: usize>(
    frames: usize,
    m: usize,
    form: MotionForm,
    (kv, ka): (f64, f64),
    load: impl Fn(usize, usize) -> (V3, Q),
    mut emit: impl FnMut(usize, usize, V3, Q),
) -> [f64; 2] {
    let (mut v, mut a) = (0.0, 0.0);
    if frames < 2 || m == 0 {
        return [v, a];
    }
    let nb = m.div_ceil(L);
    let lanes = |b: usize| (0..L).filter(move |l| b * L + l < m);
    let (kv, ka) = (Lanes::<L>::splat(kv), Lanes::<L>::splat(ka));
    let (zero, one, two) = (Lanes::<L>::splat(0.0), Lanes::<L>::splat(1.0), Lanes::<L>::splat(2.0));
    // Three frames of state (ring by t mod 3), and per block the relative rotation r_{t−1}
    // with its gradient so far (paper form).
    let mut st = vec![Slot::<L>::default(); 3 * nb];
    let mut r_prev = vec![[zero; 4]; nb];
    let mut g_prev = vec![[zero; 4]; nb];
    let mut flush = |st: &[Slot<L>], t: usize| {
        for b in 0..nb {
            let s = &st[(t % 3) * nb + b];
            // normalize's VJP (g − u⟨u, g⟩)/‖q‖, by the reciprocal norm kept in `qn`
            let d = q4::dot4(s.u, s.gu);
            let gq = [0, 1, 2, 3].map(|c| s.gq[c] + (s.gu[c] - s.u[c] * d) * s.qn);
            for l in lanes(b) {
                emit(t, b * L + l, s.gp.map(|x| x.0[l]), gq.map(|x| x.0[l]));
            }
        }
    };
    // per Gaussian of a block: its two velocity and two acceleration terms, added to v and
    // a in the scalar order
    let mut sums = vec![[zero; 4]; nb];
    for t in 0..frames {
        let s0 = (t % 3) * nb;
        for b in 0..nb {
            let (mut p, mut q) = ([zero; 3], [zero, zero, zero, zero]);
            q[0] = one;
            for l in lanes(b) {
                let (pl, ql) = load(t, b * L + l);
                for c in 0..3 {
                    p[c].0[l] = pl[c];
                }
                for c in 0..4 {
                    q[c].0[l] = ql[c];
                }
            }
            // q/‖q‖ (zero q: identity, zero gradient) and 1/‖q‖
            let len = q4::dot4(q, q).sqrt();
            let pos = len.gt0();
            let inv = one / len;
            let u = [0, 1, 2, 3]
                .map(|c| Lanes::<L>::select(pos, q[c] * inv, [one, zero, zero, zero][c]));
            let qn = Lanes::<L>::select(pos, inv, zero);
            st[s0 + b] = Slot { p, q, u, qn, ..Slot::default() };
        }
        if t == 0 {
            continue;
        }
        let (s1, s2) = (((t - 1) % 3) * nb, ((t + 1) % 3) * nb);
        // One loop per form (each keeps its own registers). Frames t−2 (a stale slot when
        // t = 1, unused then), t−1, t of block b.
        match form {
            MotionForm::Paper => {
                for b in 0..nb {
                    let [x2, x1, x0] = three(&mut st, s2 + b, s1 + b, s0 + b);
                    let [v1, v2, a1, a2] = &mut sums[b];
                    let d = sub(x1.p, x0.p);
                    *v1 = l1(d);
                    let gd = d.map(|x| kv * sign_l(x));
                    add(&mut x1.gp, gd);
                    add(&mut x0.gp, gd.map(|x| -x));
                    let r_t = q4::mul(x1.u, q4::conj(x0.u));
                    let (dev, s) = deviation(r_t);
                    *v2 = l1(dev);
                    let mut g_t = dev.map(|x| kv * s * sign_l(x));
                    if t >= 2 {
                        let d = [0, 1, 2].map(|c| x2.p[c] - two * x1.p[c] + x0.p[c]);
                        *a1 = l1(d);
                        let gd = d.map(|x| ka * sign_l(x));
                        add(&mut x2.gp, gd);
                        add(&mut x1.gp, gd.map(|x| -two * x));
                        add(&mut x0.gp, gd);
                        let (dev, s) = deviation(q4::mul(r_prev[b], q4::conj(r_t)));
                        *a2 = l1(dev);
                        let gr = dev.map(|x| ka * s * sign_l(x));
                        let (g_r1, g_r2c) = q4::mul_vjp(r_prev[b], q4::conj(r_t), gr);
                        add(&mut g_prev[b], g_r1);
                        add(&mut g_t, q4::conj(g_r2c));
                        // r_{t−1} = u_{t−2} u_{t−1}* has no more terms: chain it.
                        let (ga, gbc) = q4::mul_vjp(x2.u, q4::conj(x1.u), g_prev[b]);
                        add(&mut x2.gu, ga);
                        add(&mut x1.gu, q4::conj(gbc));
                    }
                    r_prev[b] = r_t;
                    g_prev[b] = g_t;
                }
            }
            MotionForm::Release => {
                for b in 0..nb {
                    let [x2, x1, x0] = three(&mut st, s2 + b, s1 + b, s0 + b);
                    let [v1, v2, a1, a2] = &mut sums[b];
                    let (three, four) = (Lanes::<L>::splat(3.0), Lanes::<L>::splat(4.0));
                    let d = sub(x0.p, x1.p);
                    let dq = [0, 1, 2, 3].map(|c| x0.q[c] - x1.q[c]);
                    *v1 = sq(d) / three;
                    *v2 = sq(dq) / four;
                    let gd = d.map(|x| kv * two * x / three);
                    let gq = dq.map(|x| kv * two * x / four);
                    add(&mut x0.gp, gd);
                    add(&mut x1.gp, gd.map(|x| -x));
                    add(&mut x0.gq, gq);
                    add(&mut x1.gq, gq.map(|x| -x));
                    if t >= 2 {
                        let d = [0, 1, 2].map(|c| x2.p[c] - two * x1.p[c] + x0.p[c]);
                        let dq = [0, 1, 2, 3].map(|c| x2.q[c] - two * x1.q[c] + x0.q[c]);
                        let (lp, lq) = (sq(d).sqrt(), sq(dq).sqrt());
                        *a1 = lp + lq;
                        *a2 = zero;
                        // the L2 norms' gradients, where they are > 0
                        let gd = d.map(|x| ka * x / lp);
                        add_where(lp.gt0(), &mut x2.gp, gd);
                        add_where(lp.gt0(), &mut x1.gp, gd.map(|x| -two * x));
                        add_where(lp.gt0(), &mut x0.gp, gd);
                        let gq = dq.map(|x| ka * x / lq);
                        add_where(lq.gt0(), &mut x2.gq, gq);
                        add_where(lq.gt0(), &mut x1.gq, gq.map(|x| -two * x));
                        add_where(lq.gt0(), &mut x0.gq, gq);
                    }
                }
            }
        }
        for (b, [v1, v2, a1, a2]) in sums.iter().enumerate() {
            for l in lanes(b) {
                v += v1.0[l];
                v += v2.0[l];
                if t >= 2 {
                    a += a1.0[l];
                    a += a2.0[l];
                }
            }
        }
        if t >= 2 {
            flush(&st, t - 2);
        }
    }
    if form == MotionForm::Paper {
        // the last r_{T−1} = u_{T−2} u_{T−1}*
        let (s1, s0) = (((frames - 2) % 3) * nb, ((frames - 1) % 3) * nb);
        for b in 0..nb {
            let [x1, x0] = st.get_disjoint_mut([s1 + b, s0 + b]).expect("distinct slots");
            let (ga, gbc) = q4::mul_vjp(x1.u, q4::conj(x0.u), g_prev[b]);
            add(&mut x1.gu, ga);
            add(&mut x0.gu, q4::conj(gbc));
        }
    }
    flush(&st, frames - 2);
    flush(&st, frames - 1);
    [v, a]
}

/// Mutable references to the distinct slots `c` (t−2), `b` (t−1) and `a` (t).
#[inline]
fn three<const L: usize>(st: &mut [Slot<L>], c: usize, b: usize, a: usize) -> [&mut Slot<L>; 3] {
    st.get_disjoint_mut([c, b, a]).expect("distinct slots")
}

/// The relative rotation's deviation from the identity, `std(r) − 1`, and the sign applied
/// (per lane).
#[inline]
fn deviation<const L: usize>(r: [Lanes<L>; 4]) -> ([Lanes<L>; 4], Lanes<L>) {
    let neg = r[0].lt0();
    let r = r.map(|x| Lanes::<L>::select(neg, -x, x));
    (
        [r[0] - Lanes::<L>::splat(1.0), r[1], r[2], r[3]],
        Lanes::<L>::select(neg, Lanes::<L>::splat(-1.0), Lanes::<L>::splat(1.0)),
    )
}

/// [`crate::math::lanes::sign`] per lane ([`Lanes::sign`], the same bits).
#[inline]
fn sign_l<const L: usize>(x: Lanes<L>) -> Lanes<L> {
    x.sign()
}

#[inline]
fn sub<const L: usize>(a: [Lanes<L>; 3], b: [Lanes<L>; 3]) -> [Lanes<L>; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Σ |x_c|, per lane.
#[inline]
fn l1<const L: usize, const D: usize>(x: [Lanes<L>; D]) -> Lanes<L> {
    x.into_iter().map(Lanes::<L>::abs).reduce(|s, v| s + v).expect("D > 0")
}

/// Σ x_c², per lane.
#[inline]
fn sq<const L: usize, const D: usize>(x: [Lanes<L>; D]) -> Lanes<L> {
    x.into_iter().map(|v| v * v).reduce(|s, v| s + v).expect("D > 0")
}

#[inline]
fn add<T: Copy + std::ops::Add<Output = T>, const D: usize>(a: &mut [T; D], b: [T; D]) {
    for c in 0..D {
        a[c] = a[c] + b[c];
    }
}

/// `a += b` in the lanes where `c` (all of them, nearly always).
#[inline]
fn add_where<const L: usize, const D: usize>(c: Mask<L>, a: &mut [Lanes<L>; D], b: [Lanes<L>; D]) {
    if c.all() {
        add(a, b);
    } else {
        for k in 0..D {
            a[k] = Lanes::<L>::select(c, a[k] + b[k], a[k]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::quat64::tests::TestRng;

    /// Random f64 poses `[T, m]` (rotations away from zero norm).
    fn case(seed: u64, t: usize, m: usize) -> (Vec<V3>, Vec<Q>) {
        let mut rng = TestRng(seed);
        let p = (0..t * m).map(|_| rng.v()).collect();
        let q = (0..t * m).map(|_| rng.q().map(|x| x + 0.6)).collect();
        (p, q)
    }

    /// `norm_v · v + norm_a · a` of the f64 sweep, and its gradients `[T, m]`.
    fn run(
        form: MotionForm,
        (t, m): (usize, usize),
        p: &[V3],
        q: &[Q],
        (nv, na): (f64, f64),
    ) -> (f64, Vec<V3>, Vec<Q>) {
        let (mut gp, mut gq) = (vec![[0.0; 3]; t * m], vec![[0.0; 4]; t * m]);
        let mut seen = vec![0u32; t * m];
        let [v, a] = sweep(
            t,
            m,
            form,
            (nv, na),
            |f, k| (p[f * m + k], q[f * m + k]),
            |f, k, g_p, g_q| {
                seen[f * m + k] += 1;
                add(&mut gp[f * m + k], g_p);
                add(&mut gq[f * m + k], g_q);
            },
        );
        assert!(t < 2 || seen.iter().all(|&c| c == 1), "one gradient per (t, k): {seen:?}");
        (nv * v + na * a, gp, gq)
    }

    #[test]
    fn smoothness_matches_finite_differences() {
        let h = 1e-6;
        for form in [MotionForm::Paper, MotionForm::Release] {
            for (t, m) in [(2, 3), (3, 2), (7, 4)] {
                let (p, q) = case(5 + t as u64, t, m);
                let norms = (0.6, 0.8);
                let (_, gp, gq) = run(form, (t, m), &p, &q, norms);
                let mut fails = Vec::new();
                for idx in 0..t * m {
                    for c in 0..7 {
                        let f = |d: f64| {
                            let (mut p2, mut q2) = (p.clone(), q.clone());
                            if c < 3 {
                                p2[idx][c] += d
                            } else {
                                q2[idx][c - 3] += d
                            }
                            run(form, (t, m), &p2, &q2, norms).0
                        };
                        let fd = (f(h) - f(-h)) / (2.0 * h);
                        let an = if c < 3 { gp[idx][c] } else { gq[idx][c - 3] };
                        if (an - fd).abs() > 1e-5 * (1.0 + fd.abs()) {
                            fails.push(format!("{form:?} T={t} [{idx}][{c}]: {an} vs FD {fd}"));
                        }
                    }
                }
                assert!(fails.is_empty(), "{}", fails.join("\n"));
            }
        }
    }

    /// The paper form's values are the documented sums, evaluated directly.
    #[test]
    fn paper_smoothness_values_are_the_documented_sums() {
        let (t, m) = (20, 4);
        let (p, q) = case(3, t, m);
        let u = |f: usize, k: usize| q4::normalize(q[f * m + k]).0;
        let pos = |f: usize, k: usize| p[f * m + k];
        let dev = |r: Q| {
            let r = if r[0] < 0.0 { r.map(|x| -x) } else { r };
            (r[0] - 1.0).abs() + r[1].abs() + r[2].abs() + r[3].abs()
        };
        let rel = |f: usize, k: usize| q4::mul(u(f - 1, k), q4::conj(u(f, k)));
        let (mut v, mut a) = (0.0, 0.0);
        for k in 0..m {
            for f in 1..t {
                v += (0..3).map(|c| (pos(f - 1, k)[c] - pos(f, k)[c]).abs()).sum::<f64>();
                v += dev(rel(f, k));
                if f >= 2 {
                    let d = |c: usize| pos(f - 2, k)[c] - 2.0 * pos(f - 1, k)[c] + pos(f, k)[c];
                    a += (0..3).map(|c| d(c).abs()).sum::<f64>();
                    a += dev(q4::mul(rel(f - 1, k), q4::conj(rel(f, k))));
                }
            }
        }
        let got = run(MotionForm::Paper, (t, m), &p, &q, (0.5, 0.0)).0;
        assert!((got - 0.5 * v).abs() < 1e-12 * (1.0 + v), "{got} vs {v}");
        let got = run(MotionForm::Paper, (t, m), &p, &q, (0.0, 0.25)).0;
        assert!((got - 0.25 * a).abs() < 1e-12 * (1.0 + a), "{got} vs {a}");
    }

    /// On f32 poses, over Gaussians spread across several chunks: the f64 sweep's values
    /// and gradients (added once to the existing ones), the same bits on 1, 2 or 3 threads,
    /// and nothing written outside the nodes.
    #[test]
    fn poses_sweep_equals_the_f64_sweep_whatever_the_thread_count() {
        let (t, n) = (6, 1500);
        let nodes: Vec<u32> = (0..n as u32).filter(|i| i % 7 != 3 && i % 11 != 0).collect();
        let m = nodes.len();
        assert!(m > 3 * CHUNK);
        let (p, q) = case(17, t, n);
        let mut poses = Poses::identity(t, n);
        for k in 0..t * n {
            poses.position[k] = p[k].map(|x| x as f32);
            poses.rotation[k] = q[k].map(|x| x as f32);
        }
        let mut start = PoseGrads::zeros(t, n);
        start.position.iter_mut().enumerate().for_each(|(k, g)| g[1] = k as f32 * 1e-3);
        for form in [MotionForm::Paper, MotionForm::Release] {
            let (norms, scales) = ((0.3, 0.2), (0.7, 1.3));
            let eval = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                let mut g = start.clone();
                let v = pool.install(|| {
                    smoothness(
                        &poses,
                        &nodes,
                        form,
                        (norms.0, scales.0),
                        (norms.1, scales.1),
                        &mut g,
                    )
                });
                (v, g)
            };
            let (v, g) = eval(2);
            let pick = |x: usize| (x / m) * n + nodes[x % m] as usize;
            let p64: Vec<V3> = (0..t * m).map(|x| q4::v64(poses.position[pick(x)])).collect();
            let q64: Vec<Q> = (0..t * m).map(|x| q4::q64(poses.rotation[pick(x)])).collect();
            let sums = [(1.0, 0.0), (0.0, 1.0)].map(|u| run(form, (t, m), &p64, &q64, u).0);
            for c in 0..2 {
                let want = [norms.0, norms.1][c] * sums[c];
                assert!((v[c] - want).abs() < 1e-12 * want, "{form:?} {v:?} vs {want}");
            }
            let k = (norms.0 * scales.0, norms.1 * scales.1);
            let (_, gp, gq) = run(form, (t, m), &p64, &q64, k);
            let mut want = start.clone();
            for x in 0..t * m {
                for c in 0..3 {
                    want.position[pick(x)][c] += gp[x][c] as f32;
                }
                for c in 0..4 {
                    want.rotation[pick(x)][c] += gq[x][c] as f32;
                }
            }
            assert_eq!(g, want, "{form:?}: the f64 sweep's gradients, added once");
            for threads in [1, 3] {
                let (v2, g2) = eval(threads);
                assert_eq!(v2.map(f64::to_bits), v.map(f64::to_bits), "{threads} threads");
                assert_eq!(g2, g, "{form:?}: {threads} threads");
            }
        }
    }
}
