//! Motion regularisers of Appendix A.2 (paper) and of the release (`loss_rigidity.py`,
//! `loss_dy.py`; official-release.md §5.3) over a weighted edge list, with analytic gradients
//! to positions, rotations, edge weights and rest lengths.
//!
//! Terms, for an edge e = (i → j) with weight w_e and d_e(t) = p_j(t) − p_i(t):
//! - isometry: w_e |D_e − ‖d_e(t)‖| against a rest length D_e (fixed canonical, or trainable);
//! - rigidity with offset Δ: w_e ‖d_e(t−Δ) − R_i(t−Δ) R_i(t)ᵀ d_e(t)‖, the paper's
//!   ‖p_{j,t−Δ} − T_{i,t−Δ} T_{i,t}⁻¹ p_{j,t}‖ (the release's ‖ΔR_i(t) d(t+1) − d(t)‖ is the
//!   same with t shifted);
//! - relative rotation: w_e ‖q_j(t) q_j(t−Δ)⁻¹ − q_i(t) q_i(t−Δ)⁻¹‖₂ on unit quaternions.
//!
//! The per-Gaussian velocity and acceleration terms, in the [`MotionForm`] chosen here, are in
//! [`super::smoothness`].
//!
//! The paper normalises edge sums by 1/(k|V|) (= 1/E for a kNN graph, E = k|V| edges) and
//! sums over frames; the release averages over frames and kept edges. Every function returns
//! its (unscaled) value and adds `scale ·` its gradient into a [`TrackGrad`].
//!
//! Work layout: the Gaussians of a loss are gathered into a frame-major f64 [`Track`]
//! `[T, m]`. Terms that couple frames t−s..t are evaluated per block of ≥ s frames in two
//! parallel phases (odd blocks, then even ones) so that each task owns the gradient rows it
//! writes; per-task sums are reduced in block order, so results do not depend on the number
//! of threads.

use rayon::prelude::*;

use super::poses::{PoseGrads, Poses};
use super::sign;
use crate::math::quat64::{self as q4, M3, Q, V3};

/// Width of one gradient row: position (3), raw quaternion (4), unit quaternion (4).
const GW: usize = 11;

/// The poses of `m` Gaussians over a run of frames in f64, frame-major (`t * m + k`).
/// Terms are evaluated at the local frames `first..frames`; the frames before `first` are
/// context (read by terms that couple t−Δ..t, never a term's own t).
#[derive(Debug, Clone, Default)]
pub struct Track {
    /// Number of frames held.
    pub frames: usize,
    /// Global frame of local frame 0.
    pub start: usize,
    /// First local frame at which terms are evaluated.
    pub first: usize,
    /// m, the number of Gaussians gathered.
    pub m: usize,
    /// `[T, m, 3]` positions.
    pub p: Vec<V3>,
    /// `[T, m, 4]` raw (unnormalised) rotations.
    pub q: Vec<Q>,
    /// `[T, m, 4]` unit rotations.
    pub u: Vec<Q>,
    /// `[T, m]` norms of the raw rotations.
    pub qn: Vec<f64>,
}

impl Track {
    /// A track from f64 positions and raw rotations `[T, m]`.
    pub fn new(frames: usize, m: usize, p: Vec<V3>, q: Vec<Q>) -> Self {
        assert_eq!(p.len(), frames * m, "positions [T, m]");
        assert_eq!(q.len(), frames * m, "rotations [T, m]");
        let (u, qn) = q.iter().map(|&x| q4::normalize(x)).unzip();
        Track { frames, start: 0, first: 0, m, p, q, u, qn }
    }

    /// Gather the Gaussians `nodes` (indices into `poses`, `[m]`) from every frame.
    pub fn gather(poses: &Poses, nodes: &[u32]) -> Self {
        Self::gather_frames(poses, nodes, 0..poses.frames, 0)
    }

    /// Gather `nodes` at the global `frames`; terms start at local frame `first`.
    pub fn gather_frames(
        poses: &Poses,
        nodes: &[u32],
        frames: std::ops::Range<usize>,
        first: usize,
    ) -> Self {
        let mut track = Track::default();
        track.refill(poses, nodes, frames, first);
        track
    }

    /// [`Self::gather_frames`] into this track, reusing its buffers (a streamed pass would
    /// otherwise map, fault in and unmap tens of MB per block).
    pub fn refill(
        &mut self,
        poses: &Poses,
        nodes: &[u32],
        frames: std::ops::Range<usize>,
        first: usize,
    ) {
        let (t, m) = (frames.len(), nodes.len());
        self.p.clear();
        self.q.clear();
        self.u.clear();
        self.qn.clear();
        self.p.reserve(t * m);
        self.q.reserve(t * m);
        self.u.reserve(t * m);
        self.qn.reserve(t * m);
        for f in frames.clone() {
            let base = f * poses.n;
            for &i in nodes {
                let q = q4::q64(poses.rotation[base + i as usize]);
                let (u, qn) = q4::normalize(q);
                self.p.push(q4::v64(poses.position[base + i as usize]));
                self.q.push(q);
                self.u.push(u);
                self.qn.push(qn);
            }
        }
        (self.frames, self.start, self.first, self.m) = (t, frames.start, first, m);
    }

    #[inline]
    fn at(&self, t: usize, k: usize) -> usize {
        t * self.m + k
    }
}

/// Gradients of a [`Track`]: `[T, m]` rows of (position, raw quaternion, unit quaternion).
#[derive(Debug, Clone, Default)]
pub struct TrackGrad {
    rows: Vec<[f64; GW]>,
    m: usize,
}

impl TrackGrad {
    /// Zero gradients for a track.
    pub fn zeros(track: &Track) -> Self {
        TrackGrad { rows: vec![[0.0; GW]; track.frames * track.m], m: track.m }
    }

    /// Zero gradients for `track`, reusing this buffer.
    pub fn reset(&mut self, track: &Track) {
        self.rows.clear();
        self.rows.resize(track.frames * track.m, [0.0; GW]);
        self.m = track.m;
    }

    /// d loss / d position of Gaussian k at frame t.
    pub fn position(&self, t: usize, k: usize) -> V3 {
        let r = &self.rows[t * self.m + k];
        [r[0], r[1], r[2]]
    }

    /// d loss / d raw rotation of Gaussian k at frame t (both paths, through the norm).
    pub fn rotation(&self, track: &Track, t: usize, k: usize) -> Q {
        let i = t * self.m + k;
        let r = &self.rows[i];
        let gu = q4::normalize_vjp(track.u[i], track.qn[i], [r[7], r[8], r[9], r[10]]);
        [r[3] + gu[0], r[4] + gu[1], r[5] + gu[2], r[6] + gu[3]]
    }

    /// Add the gradients into `grads` (`[T, n]`) at the Gaussians `nodes` (`[m]`, as
    /// gathered) and the track's global frames.
    pub fn scatter(&self, track: &Track, nodes: &[u32], n: usize, grads: &mut PoseGrads) {
        for t in 0..track.frames {
            let (a, b) = ((track.start + t) * n, (track.start + t + 1) * n);
            self.add_frame(track, nodes, t, &mut grads.position[a..b], &mut grads.rotation[a..b]);
        }
    }

    /// Add local frame `t`'s gradients into one frame's rows `[n]` of positions and rotations.
    fn add_frame(
        &self,
        track: &Track,
        nodes: &[u32],
        t: usize,
        position: &mut [[f32; 3]],
        rotation: &mut [[f32; 4]],
    ) {
        for (k, &i) in nodes.iter().enumerate() {
            let (gp, gq) = (self.position(t, k), self.rotation(track, t, k));
            for c in 0..3 {
                position[i as usize][c] += gp[c] as f32;
            }
            for c in 0..4 {
                rotation[i as usize][c] += gq[c] as f32;
            }
        }
    }
}

/// Rows (Gaussian × frame) of one block of [`stream_frames`]: about 48 MB of track and
/// gradients.
const BLOCK_ROWS: usize = 1 << 18;

/// Rows gathered by one wave of blocks evaluated in parallel, unless the threads outnumber
/// the blocks that fit (then one block per thread).
const WAVE_ROWS: usize = 1 << 20;

/// Evaluate `f` (which returns K term values and adds its gradients into the [`TrackGrad`])
/// on the Gaussians `nodes` of `poses`, one block of frames at a time: each block holds its
/// frames plus `context` frames before them (terms coupling t−Δ..t need Δ ≤ `context`); its
/// gradients are added into `grads` (its own frames in parallel, they are disjoint, then its
/// context frames in block order) and its values in block order. Memory is a few blocks (at
/// least one per thread), not `[T, m]`; the block layout depends on T and m only, so the
/// result does not depend on the number of threads.
pub fn stream_frames<const K: usize>(
    poses: &Poses,
    nodes: &[u32],
    context: usize,
    grads: &mut PoseGrads,
    f: impl Fn(&Track, &mut TrackGrad) -> [f64; K] + Sync,
) -> [f64; K] {
    stream_frames_in(poses, nodes, context, (BLOCK_ROWS, WAVE_ROWS), grads, f)
}

/// [`stream_frames`] with blocks of about `block_rows` rows (at least 4 frames) and waves of
/// at most `wave_rows` rows (at least one block).
fn stream_frames_in<const K: usize>(
    poses: &Poses,
    nodes: &[u32],
    context: usize,
    (block_rows, wave_rows): (usize, usize),
    grads: &mut PoseGrads,
    f: impl Fn(&Track, &mut TrackGrad) -> [f64; K] + Sync,
) -> [f64; K] {
    let (nt, m) = (poses.frames, nodes.len());
    let mut total = [0.0; K];
    if nt == 0 || m == 0 {
        return total;
    }
    let b = (block_rows / m).max(4);
    let blocks: Vec<std::ops::Range<usize>> =
        (0..nt).step_by(b).map(|lo| lo..(lo + b).min(nt)).collect();
    // Blocks per wave: as many as fit in WAVE_ROWS (at most 8) but at least one per thread,
    // since a block is about two sequential tasks (a 16-core host ran 3 blocks at a time
    // otherwise); rounded down to a multiple of the threads so that no thread idles through
    // a wave (3 blocks on 2 threads take as long as 4). Waves only bound memory: every
    // gradient row still receives its own block's values before the next block's context
    // values, so the result is the same.
    let threads = rayon::current_num_threads().max(1);
    let fit = (wave_rows / ((b + context) * m)).clamp(1, 8).max(threads);
    let wave = if fit >= threads { fit - fit % threads } else { fit };
    let mut pool: Vec<(Track, TrackGrad, [f64; K])> = Vec::new();
    for w in blocks.chunks(wave) {
        // The blocks' buffers are reused from wave to wave.
        pool.resize_with(w.len(), || (Track::default(), TrackGrad::default(), [0.0; K]));
        w.par_iter().zip(pool.par_iter_mut()).for_each(|(r, (tr, g, v))| {
            let a = r.start.saturating_sub(context);
            tr.refill(poses, nodes, a..r.end, r.start - a);
            g.reset(tr);
            *v = f(tr, g);
        });
        let parts = &pool;
        // Each block's own frames are disjoint: added in parallel over frames; then the
        // context frames, in block order.
        let owner = |f: usize| {
            parts.iter().position(|(tr, _, _)| f >= tr.start + tr.first && f < tr.start + tr.frames)
        };
        grads
            .position
            .par_chunks_mut(poses.n)
            .zip(grads.rotation.par_chunks_mut(poses.n))
            .enumerate()
            .for_each(|(f, (gp, gq))| {
                if let Some(b) = owner(f) {
                    let (tr, g, _) = &parts[b];
                    g.add_frame(tr, nodes, f - tr.start, gp, gq);
                }
            });
        for (tr, g, v) in parts {
            for t in 0..tr.first {
                let f = tr.start + t;
                let (a, b) = (f * poses.n, (f + 1) * poses.n);
                g.add_frame(tr, nodes, t, &mut grads.position[a..b], &mut grads.rotation[a..b]);
            }
            for (t, x) in total.iter_mut().zip(v) {
                *t += x;
            }
        }
    }
    total
}

/// Edges over a track's Gaussians (compact indices `0..m`), `[E]` each. Edges from one source
/// should be contiguous (kNN lists are): per-source quantities are computed once per run.
#[derive(Debug, Clone, Copy)]
pub struct EdgeSet<'a> {
    /// Source i of each edge.
    pub src: &'a [u32],
    /// Destination j of each edge.
    pub dst: &'a [u32],
    /// Weight w_e of each edge.
    pub w: &'a [f64],
}

impl EdgeSet<'_> {
    /// Number of edges E.
    pub fn len(&self) -> usize {
        self.src.len()
    }

    /// Whether there are no edges.
    pub fn is_empty(&self) -> bool {
        self.src.is_empty()
    }
}

/// Gradients of per-edge inputs, `[E]` each (empty when not requested).
#[derive(Debug, Clone, Default)]
pub struct EdgeGrad {
    /// d loss / d w_e.
    pub w: Vec<f64>,
    /// d loss / d D_e (isometry rest lengths).
    pub rest: Vec<f64>,
}

impl EdgeGrad {
    /// Zeros for `e` edges.
    pub fn zeros(e: usize) -> Self {
        EdgeGrad { w: vec![0.0; e], rest: vec![0.0; e] }
    }
}

/// What the edge terms [`rigidity`], [`relative_rotation`] and [`isometry`] share: the track
/// and its edges they are evaluated on, and the gradients they add to (the edges' when
/// `g_edges` is given).
pub struct EdgeTerms<'a> {
    /// The Gaussians' poses.
    pub track: &'a Track,
    /// The edges over them.
    pub edges: EdgeSet<'a>,
    /// Gradients of the track.
    pub g: &'a mut TrackGrad,
    /// Gradients of the edges' weights and rest lengths, when wanted.
    pub g_edges: Option<&'a mut EdgeGrad>,
}

/// Which variant of the velocity and acceleration terms (profile row 54).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum MotionForm {
    /// Appendix A.2: Σ_t Σ_i ‖p_{t−1} − p_t‖₁ + ‖q_{t−1} q_t⁻¹ − 1‖₁ and
    /// ‖p_{t−2} − 2p_{t−1} + p_t‖₁ + ‖q_{t−2} q_{t−1}⁻¹ (q_{t−1} q_t⁻¹)⁻¹ − 1‖₁. The paper
    /// writes the L1 norm of the relative rotation itself, which is ≥ 1 for every unit
    /// quaternion and smallest away from the identity; we read it as the relative rotation's
    /// deviation from the identity (w ≥ 0 representative), which is what smoothness means.
    Paper,
    /// `loss_dy.py`: mean((p_t − p_{t+1})²) + mean((q_t − q_{t+1})²) over all components,
    /// and mean ‖2p_t − p_{t−1} − p_{t+1}‖ + mean ‖2q_t − q_{t−1} − q_{t+1}‖ (raw q).
    Release,
}

/// Per-block task layout of terms coupling frames t−span..=t: the blocks of `size ≥ span`
/// frames, in two phases whose tasks own disjoint gradient rows.
fn block_size(span: usize) -> usize {
    span.max(8)
}

/// Run `f(t, base, rows)` for every t in `span.max(t_min)..frames`, where `rows` are the
/// gradient rows of frames `base..` and include frames t−span..=t. Returns the per-task
/// results in a fixed order (phase, block).
fn frame_windows<R: Send>(
    g: &mut TrackGrad,
    frames: usize,
    span: usize,
    t_min: usize,
    f: impl Fn(std::ops::Range<usize>, usize, &mut [[f64; GW]]) -> R + Sync,
) -> Vec<R> {
    let m = g.m;
    let b = block_size(span);
    let t_lo = span.max(t_min);
    let mut out = Vec::new();
    if m == 0 || frames <= t_lo {
        return out;
    }
    // Phase 1: regions [2rb, 2rb + 2b) handle t in block 2r+1 (region 0 also block 0);
    // phase 0: regions [b + 2rb, b + 2rb + 2b) handle t in block 2r+2. t − span ≥ the
    // region's start since b ≥ span, and the regions of one phase are disjoint.
    for phase in [1usize, 0] {
        let skip = if phase == 1 { 0 } else { b };
        if skip * m > g.rows.len() {
            continue;
        }
        let tasks: Vec<R> = g.rows[skip * m..]
            .par_chunks_mut(2 * b * m)
            .enumerate()
            .filter_map(|(r, rows)| {
                let base = skip + 2 * r * b;
                // The t handled: the second block of the region, plus (phase 1, region 0)
                // the first block when span = 0 lets a frame pair with itself.
                let first = if phase == 1 && r == 0 { 0 } else { base + b };
                let lo = first.max(t_lo);
                let hi = (base + 2 * b).min(frames);
                (lo < hi).then(|| f(lo..hi, base, rows))
            })
            .collect();
        out.extend(tasks);
    }
    out
}

/// Per-task result of an edge term: value and per-edge gradients.
struct Partial {
    value: f64,
    g_w: Vec<f64>,
    g_rest: Vec<f64>,
}

impl Partial {
    /// Zero, with per-edge gradients of `ne` weights when `want_e` (and of the rest
    /// lengths when `rest` too).
    fn new(want_e: bool, ne: usize, rest: bool) -> Self {
        let zeros = |on: bool| if on { vec![0.0; ne] } else { Vec::new() };
        Partial { value: 0.0, g_w: zeros(want_e), g_rest: zeros(want_e && rest) }
    }
}

impl Partial {
    /// Add edge e's value `norm·w·len` and its weight gradient; returns the factor
    /// `scale·norm·w/len` of the gradient with respect to the residual, when len > 0.
    #[inline]
    fn add_edge(&mut self, e: usize, w: f64, len: f64, norm: f64, scale: f64) -> Option<f64> {
        self.value += norm * w * len;
        if !self.g_w.is_empty() {
            self.g_w[e] += scale * norm * len;
        }
        (len > 0.0).then(|| scale * norm * w / len)
    }

    /// Add edge e's isometry value `norm·w·|‖d‖ − D|` and its weight and rest-length
    /// gradients; returns `scale ·` its gradient with respect to d, when not zero.
    #[inline]
    fn add_isometry(
        &mut self,
        e: usize,
        w: f64,
        rest: f64,
        d: V3,
        norm: f64,
        scale: f64,
    ) -> Option<V3> {
        let len = norm3(d);
        let r = len - rest;
        self.value += norm * w * r.abs();
        let s = sign(r);
        if !self.g_w.is_empty() {
            self.g_w[e] += scale * norm * r.abs();
            self.g_rest[e] -= scale * norm * w * s;
        }
        (len > 0.0 && s != 0.0).then(|| {
            let k = scale * norm * w * s / len;
            d.map(|x| x * k)
        })
    }
}

/// An edge term coupling frames t−Δ and t (Δ ≥ 1): `frame(part, t − Δ, t, base, rows)`
/// adds frame t's value and gradients, tasks as [`frame_windows`] lays them out; returns the
/// value, per-edge gradients added to `g_edges` in task order.
fn offset_term(
    on: &mut EdgeTerms,
    delta: usize,
    frame: impl Fn(&mut Partial, usize, usize, usize, &mut [[f64; GW]]) + Sync,
) -> f64 {
    assert!(delta >= 1, "offset Δ ≥ 1");
    let (want_e, ne, track) = (on.g_edges.is_some(), on.edges.len(), on.track);
    let parts = frame_windows(on.g, track.frames, delta, track.first, |ts, base, rows| {
        let mut part = Partial::new(want_e, ne, false);
        for t in ts {
            frame(&mut part, t - delta, t, base, rows);
        }
        part
    });
    reduce(parts, on.g_edges.as_deref_mut())
}

/// The runs of edges that share a source, `(source, its edges)` in edge order (edges
/// grouped by source, as kNN lists and the key-key edges are).
pub fn by_source(src: &[u32]) -> impl Iterator<Item = (usize, std::ops::Range<usize>)> + '_ {
    let mut e = 0;
    std::iter::from_fn(move || {
        (e < src.len()).then(|| {
            let first = e;
            while e < src.len() && src[e] == src[first] {
                e += 1;
            }
            (src[first] as usize, first..e)
        })
    })
}

fn reduce(parts: Vec<Partial>, g_edges: Option<&mut EdgeGrad>) -> f64 {
    let mut value = 0.0;
    let mut ge = g_edges;
    for p in parts {
        value += p.value;
        if let Some(ge) = ge.as_deref_mut() {
            for (a, b) in ge.w.iter_mut().zip(&p.g_w) {
                *a += b;
            }
            for (a, b) in ge.rest.iter_mut().zip(&p.g_rest) {
                *a += b;
            }
        }
    }
    value
}

/// What the rigidity terms need of an edge source i between frames t0 and t1: its unit
/// rotations a, b, their relative rotation c = a b* and its matrix, and its positions.
struct SourceMotion {
    a: Q,
    b: Q,
    c: Q,
    rm: M3,
    pi0: V3,
    pi1: V3,
}

impl SourceMotion {
    #[inline]
    fn of(track: &Track, i: usize, t0: usize, t1: usize) -> Self {
        let (a, b) = (track.u[track.at(t0, i)], track.u[track.at(t1, i)]);
        let c = q4::mul(a, q4::conj(b));
        let (pi0, pi1) = (track.p[track.at(t0, i)], track.p[track.at(t1, i)]);
        SourceMotion { a, b, c, rm: q4::to_rotmat(c), pi0, pi1 }
    }
}

#[inline]
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
fn norm3(a: V3) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

#[inline]
fn add_to(row: &mut [f64; GW], off: usize, v: &[f64]) {
    for (c, x) in v.iter().enumerate() {
        row[off + c] += x;
    }
}

/// Rigidity with offset Δ ≥ 1: `norm · Σ_{t=Δ}^{T−1} Σ_e w_e ‖d_e(t−Δ) − R_i(t−Δ) R_i(t)ᵀ d_e(t)‖`.
pub fn rigidity(on: &mut EdgeTerms, delta: usize, norm: f64, scale: f64) -> f64 {
    let (track, edges, m) = (on.track, on.edges, on.track.m);
    offset_term(on, delta, |part, t0, t1, base, rows| {
        for (i, run) in by_source(edges.src) {
            let SourceMotion { a, b, c, rm, pi0, pi1 } = SourceMotion::of(track, i, t0, t1);
            let mut g_rm: M3 = [[0.0; 3]; 3];
            let (mut g_pi0, mut g_pi1) = ([0.0; 3], [0.0; 3]);
            for e in run {
                let j = edges.dst[e] as usize;
                let d0 = sub(track.p[track.at(t0, j)], pi0);
                let d1 = sub(track.p[track.at(t1, j)], pi1);
                let r = sub(d0, q4::mat_vec(&rm, d1));
                if let Some(k) = part.add_edge(e, edges.w[e], norm3(r), norm, scale) {
                    let gr = r.map(|x| x * k);
                    let gd1 = q4::mat_t_vec(&rm, gr).map(|x| -x);
                    q4::add_outer(&mut g_rm, gr.map(|x| -x), d1);
                    add_to(&mut rows[(t0 - base) * m + j], 0, &gr);
                    add_to(&mut rows[(t1 - base) * m + j], 0, &gd1);
                    for c in 0..3 {
                        g_pi0[c] -= gr[c];
                        g_pi1[c] -= gd1[c];
                    }
                }
            }
            let g_c = q4::to_rotmat_vjp(c, &g_rm);
            let (g_a, g_bc) = q4::mul_vjp(a, q4::conj(b), g_c);
            add_to(&mut rows[(t0 - base) * m + i], 0, &g_pi0);
            add_to(&mut rows[(t1 - base) * m + i], 0, &g_pi1);
            add_to(&mut rows[(t0 - base) * m + i], 7, &g_a);
            add_to(&mut rows[(t1 - base) * m + i], 7, &q4::conj(g_bc));
        }
    })
}

/// Relative rotation with offset Δ ≥ 1:
/// `norm · Σ_{t=Δ}^{T−1} Σ_e w_e ‖q_j(t) q_j(t−Δ)* − q_i(t) q_i(t−Δ)*‖₂` (unit quaternions).
pub fn relative_rotation(on: &mut EdgeTerms, delta: usize, norm: f64, scale: f64) -> f64 {
    let (track, edges, m) = (on.track, on.edges, on.track.m);
    offset_term(on, delta, |part, t0, t1, base, rows| {
        // Each Gaussian's q(t) q(t−Δ)* once, and the gradient reaching it from all its
        // edges (the VJP of the product is linear: chained once per Gaussian).
        let ends = |k: usize| (track.u[track.at(t1, k)], track.u[track.at(t0, k)]);
        let rel: Vec<Q> = (0..m)
            .map(|k| {
                let (a, b) = ends(k);
                q4::mul(a, q4::conj(b))
            })
            .collect();
        let mut g_rel = vec![[0.0; 4]; m];
        for (i, run) in by_source(edges.src) {
            for e in run {
                let j = edges.dst[e] as usize;
                let r = [0, 1, 2, 3].map(|c| rel[j][c] - rel[i][c]);
                if let Some(k) = part.add_edge(e, edges.w[e], q4::norm(r), norm, scale) {
                    for c in 0..4 {
                        g_rel[j][c] += r[c] * k;
                        g_rel[i][c] -= r[c] * k;
                    }
                }
            }
        }
        for (k, gr) in g_rel.iter().enumerate() {
            if *gr != [0.0; 4] {
                let (a, b) = ends(k);
                let (ga, gbc) = q4::mul_vjp(a, q4::conj(b), *gr);
                add_to(&mut rows[(t1 - base) * m + k], 7, &ga);
                add_to(&mut rows[(t0 - base) * m + k], 7, &q4::conj(gbc));
            }
        }
    })
}

/// Isometry: `norm · Σ_{t=0}^{T−1} Σ_e w_e |D_e − ‖d_e(t)‖|` with rest lengths `rest` `[E]`.
pub fn isometry(on: &mut EdgeTerms, rest: &[f64], norm: f64, scale: f64) -> f64 {
    let (track, edges) = (on.track, on.edges);
    isometry_until(track, edges, rest, (norm, scale), track.frames, on.g, on.g_edges.as_deref_mut())
}

/// [`isometry`] at the frames before `end` only.
fn isometry_until(
    track: &Track,
    edges: EdgeSet,
    rest: &[f64],
    (norm, scale): (f64, f64),
    end: usize,
    g: &mut TrackGrad,
    g_edges: Option<&mut EdgeGrad>,
) -> f64 {
    assert_eq!(rest.len(), edges.len(), "one rest length per edge");
    let m = track.m;
    let want_e = g_edges.is_some();
    let ne = edges.len();
    let parts = frame_windows(g, end, 0, track.first, |ts, base, rows| {
        let mut part = Partial::new(want_e, ne, true);
        for t in ts {
            for e in 0..ne {
                let (i, j) = (edges.src[e] as usize, edges.dst[e] as usize);
                let d = sub(track.p[track.at(t, j)], track.p[track.at(t, i)]);
                let gd = part.add_isometry(e, edges.w[e], rest[e], d, norm, scale);
                if let Some(gd) = gd {
                    add_to(&mut rows[(t - base) * m + j], 0, &gd);
                    add_to(&mut rows[(t - base) * m + i], 0, &gd.map(|x| -x));
                }
            }
        }
        part
    });
    reduce(parts, g_edges)
}

/// [`isometry`] and [`rigidity`] with Δ = 1 in one pass over the edges, which share the
/// edge vectors d_e(t): `[isometry, rigidity]`, the values and gradients of the two calls
/// (`iso` and `rigid` are their `(norm, scale)`), summed in another order.
pub fn isometry_rigidity(
    track: &Track,
    edges: EdgeSet,
    rest: &[f64],
    (norm_i, scale_i): (f64, f64),
    (norm_r, scale_r): (f64, f64),
    g: &mut TrackGrad,
    g_edges: Option<&mut EdgeGrad>,
) -> [f64; 2] {
    assert_eq!(rest.len(), edges.len(), "one rest length per edge");
    let (m, ne, want_e) = (track.m, edges.len(), g_edges.is_some());
    let mut g_edges = g_edges;
    // Frame 0 has an isometry term and no rigidity term.
    let iso0 = if track.first == 0 {
        let ge = g_edges.as_deref_mut();
        isometry_until(track, edges, rest, (norm_i, scale_i), 1.min(track.frames), g, ge)
    } else {
        0.0
    };
    let parts = frame_windows(g, track.frames, 1, track.first, |ts, base, rows| {
        let mut iso = Partial::new(want_e, ne, true);
        let mut rig = Partial::new(want_e, ne, false);
        for t1 in ts {
            let (t0, r0, r1) = (t1 - 1, (t1 - 1 - base) * m, (t1 - base) * m);
            for (i, run) in by_source(edges.src) {
                let SourceMotion { a, b, c, rm, pi0, pi1 } = SourceMotion::of(track, i, t0, t1);
                let mut g_rm: M3 = [[0.0; 3]; 3];
                let (mut g_pi0, mut g_pi1) = ([0.0; 3], [0.0; 3]);
                for e in run {
                    let (j, w) = (edges.dst[e] as usize, edges.w[e]);
                    let d0 = sub(track.p[track.at(t0, j)], pi0);
                    let d1 = sub(track.p[track.at(t1, j)], pi1);
                    let mut g_d1 = [0.0; 3];
                    let r = sub(d0, q4::mat_vec(&rm, d1));
                    if let Some(k) = rig.add_edge(e, w, norm3(r), norm_r, scale_r) {
                        let gr = r.map(|x| x * k);
                        g_d1 = q4::mat_t_vec(&rm, gr).map(|x| -x);
                        q4::add_outer(&mut g_rm, gr.map(|x| -x), d1);
                        add_to(&mut rows[r0 + j], 0, &gr);
                        for c in 0..3 {
                            g_pi0[c] -= gr[c];
                        }
                    }
                    if let Some(gd) = iso.add_isometry(e, w, rest[e], d1, norm_i, scale_i) {
                        for c in 0..3 {
                            g_d1[c] += gd[c];
                        }
                    }
                    add_to(&mut rows[r1 + j], 0, &g_d1);
                    for c in 0..3 {
                        g_pi1[c] -= g_d1[c];
                    }
                }
                let g_c = q4::to_rotmat_vjp(c, &g_rm);
                let (g_a, g_bc) = q4::mul_vjp(a, q4::conj(b), g_c);
                add_to(&mut rows[r0 + i], 0, &g_pi0);
                add_to(&mut rows[r1 + i], 0, &g_pi1);
                add_to(&mut rows[r0 + i], 7, &g_a);
                add_to(&mut rows[r1 + i], 7, &q4::conj(g_bc));
            }
        }
        (iso, rig)
    });
    let (iso, rig): (Vec<Partial>, Vec<Partial>) = parts.into_iter().unzip();
    let iso = iso0 + reduce(iso, g_edges.as_deref_mut());
    [iso, reduce(rig, g_edges)]
}

/// The vanilla recipe's motion-locality graph: each of the `positions` `[m, 3]` (the dynamic
/// Gaussians at the canonical frame) linked to its k nearest others, uniform weight 1/k, and
/// rest lengths at that frame. Edges are grouped by source, nearest first; compact indices.
pub fn knn_edges(positions: &[[f32; 3]], k: usize) -> (Vec<u32>, Vec<u32>, Vec<f64>, Vec<f64>) {
    use kiddo::{ImmutableKdTree, SquaredEuclidean};
    let m = positions.len();
    let k = k.min(m.saturating_sub(1));
    let (mut src, mut dst, mut rest) = (Vec::new(), Vec::new(), Vec::new());
    let Some(kk) = std::num::NonZero::new(k + 1) else {
        return (src, dst, Vec::new(), rest);
    };
    let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(positions) else {
        return (src, dst, Vec::new(), rest);
    };
    let lists: Vec<Vec<u32>> = positions
        .par_iter()
        .enumerate()
        .map(|(i, q)| {
            let res = tree.query(q).nearest_n::<SquaredEuclidean<f32>>(kk).execute();
            res.iter().map(|r| r.item).filter(|&j| j as usize != i).take(k).collect()
        })
        .collect();
    for (i, list) in lists.iter().enumerate() {
        for &j in list {
            src.push(i as u32);
            dst.push(j);
            rest.push(norm3(sub(q4::v64(positions[j as usize]), q4::v64(positions[i]))));
        }
    }
    let w = vec![1.0 / k.max(1) as f64; src.len()];
    (src, dst, w, rest)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::quat64::tests::TestRng;

    /// A random track of `m` Gaussians over `t` frames and a kNN-like edge list grouped by
    /// source.
    fn case(seed: u64, t: usize, m: usize) -> (Track, Vec<u32>, Vec<u32>, Vec<f64>, Vec<f64>) {
        let mut rng = TestRng(seed);
        let p = (0..t * m).map(|_| rng.v()).collect();
        let q = (0..t * m).map(|_| rng.q().map(|x| x + 0.6)).collect();
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for i in 0..m as u32 {
            for d in 1..3u32 {
                src.push(i);
                dst.push((i + d) % m as u32);
            }
        }
        let w = src.iter().map(|_| 0.5 + 0.4 * rng.next()).collect();
        let rest = src.iter().map(|_| 1.0 + 0.3 * rng.next()).collect();
        (Track::new(t, m, p, q), src, dst, w, rest)
    }

    /// Every term at once: value and gradients (positions, raw rotations, w, rest).
    fn all_terms(
        tr: &Track,
        src: &[u32],
        dst: &[u32],
        w: &[f64],
        rest: &[f64],
    ) -> (f64, TrackGrad, EdgeGrad) {
        let e = EdgeSet { src, dst, w };
        let mut g = TrackGrad::zeros(tr);
        let mut ge = EdgeGrad::zeros(src.len());
        let on = &mut EdgeTerms { track: tr, edges: e, g: &mut g, g_edges: Some(&mut ge) };
        let mut v = rigidity(on, 1, 0.3, 1.0);
        v += 0.7 * rigidity(on, 3, 0.2, 0.7);
        v += relative_rotation(on, 2, 0.5, 1.0);
        v += isometry(on, rest, 0.4, 1.0);
        (v, g, ge)
    }

    #[test]
    fn every_motion_term_matches_finite_differences() {
        let (t, m) = (7, 5);
        let (tr, src, dst, w, rest) = case(5, t, m);
        let (_, g, ge) = all_terms(&tr, &src, &dst, &w, &rest);
        let h = 1e-6;
        let mut fails = Vec::new();
        let mut worst = 0.0f64;
        let mut check = |what: String, analytic: f64, f: &dyn Fn(f64) -> f64| {
            let fd = (f(h) - f(-h)) / (2.0 * h);
            let err = (analytic - fd).abs();
            worst = worst.max(err);
            if err > 1e-5 * (1.0 + fd.abs()) {
                fails.push(format!("{what}: analytic {analytic} fd {fd}"));
            }
        };
        for f in 0..t {
            for k in 0..m {
                let idx = f * m + k;
                for c in 0..3 {
                    check(format!("p[{f},{k},{c}]"), g.position(f, k)[c], &|d| {
                        let mut p = tr.p.clone();
                        p[idx][c] += d;
                        all_terms(&Track::new(t, m, p, tr.q.clone()), &src, &dst, &w, &rest).0
                    });
                }
                for c in 0..4 {
                    check(format!("q[{f},{k},{c}]"), g.rotation(&tr, f, k)[c], &|d| {
                        let mut q = tr.q.clone();
                        q[idx][c] += d;
                        all_terms(&Track::new(t, m, tr.p.clone(), q), &src, &dst, &w, &rest).0
                    });
                }
            }
        }
        for e in 0..src.len() {
            check(format!("w[{e}]"), ge.w[e], &|d| {
                let mut w2 = w.clone();
                w2[e] += d;
                all_terms(&tr, &src, &dst, &w2, &rest).0
            });
            check(format!("rest[{e}]"), ge.rest[e], &|d| {
                let mut r2 = rest.clone();
                r2[e] += d;
                all_terms(&tr, &src, &dst, &w, &r2).0
            });
        }
        eprintln!("motion terms: max |analytic − FD| = {worst:.2e}");
        assert!(fails.is_empty(), "{}", fails.join("\n"));
    }

    /// Poses `[T, n]` holding the track's Gaussian k at pose index `nodes[k]` (identity
    /// elsewhere).
    fn poses_of(tr: &Track, n: usize, nodes: &[u32]) -> Poses {
        let (t, m) = (tr.frames, tr.m);
        let mut poses = Poses::identity(t, n);
        for f in 0..t {
            for (k, &i) in nodes.iter().enumerate() {
                poses.position[f * n + i as usize] = tr.p[f * m + k].map(|x| x as f32);
                poses.rotation[f * n + i as usize] = tr.q[f * m + k].map(|x| x as f32);
            }
        }
        poses
    }

    /// `terms` on the gathered track of `nodes` over all frames: the values and the pose
    /// gradients that a streamed evaluation must reproduce.
    fn on_whole_track<const K: usize>(
        poses: &Poses,
        nodes: &[u32],
        terms: impl Fn(&Track, &mut TrackGrad) -> [f64; K],
    ) -> ([f64; K], PoseGrads) {
        let whole = Track::gather(poses, nodes);
        let mut g = TrackGrad::zeros(&whole);
        let want = terms(&whole, &mut g);
        let mut want_g = PoseGrads::zeros(poses.frames, poses.n);
        g.scatter(&whole, nodes, poses.n, &mut want_g);
        (want, want_g)
    }

    #[test]
    fn streamed_frame_blocks_equal_the_whole_track() {
        let (t, m) = (23, 6);
        let (tr, src, dst, w, rest) = case(11, t, m);
        let (n, nodes) = (9, [7u32, 0, 3, 8, 2, 5]);
        let poses = poses_of(&tr, n, &nodes);
        let e = EdgeSet { src: &src, dst: &dst, w: &w };
        let terms = |tr: &Track, g: &mut TrackGrad| {
            let on = &mut EdgeTerms { track: tr, edges: e, g, g_edges: None };
            [
                rigidity(on, 1, 0.3, 1.0),
                rigidity(on, 3, 0.2, 0.7),
                relative_rotation(on, 2, 0.5, 1.0),
                isometry(on, &rest, 0.4, 1.0),
            ]
        };
        let (want, want_g) = on_whole_track(&poses, &nodes, terms);
        // blocks of 4 frames plus 3 frames of context, waves of at most 3 blocks
        let mut got_g = PoseGrads::zeros(t, n);
        let layout = (4 * m, 3 * 7 * m);
        let got = stream_frames_in(&poses, &nodes, 3, layout, &mut got_g, terms);
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{got:?} vs {want:?}");
        }
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        assert!(close(got_g.position.as_flattened(), want_g.position.as_flattened()));
        assert!(close(got_g.rotation.as_flattened(), want_g.rotation.as_flattened()));
        assert!(want_g.position[7][0] != 0.0, "gradients reach the poses");
        // 6 blocks in waves of 3 blocks (1 or 3 threads), 2 (2 threads) or one per thread
        // (4 and 8 threads): the same bits.
        for threads in [1, 2, 3, 4, 8] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut g = PoseGrads::zeros(t, n);
            let v = pool.install(|| stream_frames_in(&poses, &nodes, 3, layout, &mut g, terms));
            assert_eq!(v.map(f64::to_bits), got.map(f64::to_bits), "{threads} threads");
            assert_eq!(g, got_g, "{threads} threads");
        }
    }

    /// The fused pass equals its two terms, on a whole track and on blocks with context.
    #[test]
    fn fused_isometry_rigidity_equals_the_two_terms() {
        let (t, m) = (23, 6);
        let (tr, src, dst, w, rest) = case(13, t, m);
        let e = EdgeSet { src: &src, dst: &dst, w: &w };
        let (iso, rig) = ((0.4, 0.7), (0.3, 1.3));
        let (n, nodes) = (9, [7u32, 0, 3, 8, 2, 5]);
        let poses = poses_of(&tr, n, &nodes);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * (1.0 + b.abs());
        for first in [0, 2] {
            let tr = Track { first, ..tr.clone() };
            let (mut g1, mut g2) = (TrackGrad::zeros(&tr), TrackGrad::zeros(&tr));
            let (mut e1, mut e2) = (EdgeGrad::zeros(src.len()), EdgeGrad::zeros(src.len()));
            let on = &mut EdgeTerms { track: &tr, edges: e, g: &mut g1, g_edges: Some(&mut e1) };
            let want = [isometry(on, &rest, iso.0, iso.1), rigidity(on, 1, rig.0, rig.1)];
            let got = isometry_rigidity(&tr, e, &rest, iso, rig, &mut g2, Some(&mut e2));
            assert!(close(got[0], want[0]) && close(got[1], want[1]), "{got:?} vs {want:?}");
            assert!(want[0] > 0.0 && want[1] > 0.0);
            let flat = |g: &TrackGrad| g.rows.iter().flatten().copied().collect::<Vec<f64>>();
            assert!(flat(&g2).iter().zip(flat(&g1)).all(|(a, b)| close(*a, b)), "first {first}");
            assert!(e2.w.iter().zip(&e1.w).all(|(a, b)| close(*a, *b)));
            assert!(e2.rest.iter().zip(&e1.rest).all(|(a, b)| close(*a, *b)));
        }
        // streamed in blocks of 4 frames with one frame of context
        let terms =
            |tr: &Track, g: &mut TrackGrad| isometry_rigidity(tr, e, &rest, iso, rig, g, None);
        let (want, want_g) = on_whole_track(&poses, &nodes, terms);
        let mut got_g = PoseGrads::zeros(t, n);
        let got = stream_frames_in(&poses, &nodes, 1, (4 * m, 3 * 5 * m), &mut got_g, terms);
        assert!(close(got[0], want[0]) && close(got[1], want[1]), "{got:?} vs {want:?}");
        let near = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        assert!(near(got_g.position.as_flattened(), want_g.position.as_flattened()));
        assert!(near(got_g.rotation.as_flattened(), want_g.rotation.as_flattened()));
    }

    #[test]
    fn knn_edges_link_each_point_to_its_nearest_others() {
        let pts: Vec<[f32; 3]> = (0..10).map(|i| [i as f32 * i as f32, 0.0, 0.0]).collect();
        let (src, dst, w, rest) = knn_edges(&pts, 2);
        assert_eq!(src.len(), 20);
        assert_eq!((src[0], dst[0], dst[1]), (0, 1, 2));
        assert_eq!((src[10], dst[10], dst[11]), (5, 4, 6));
        assert!((w[0] - 0.5).abs() < 1e-12 && (rest[10] - 9.0).abs() < 1e-9);
    }

    #[test]
    fn motion_terms_do_not_depend_on_the_thread_count() {
        let (tr, src, dst, w, rest) = case(9, 40, 30);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (v, g, ge) = all_terms(&tr, &src, &dst, &w, &rest);
                (
                    v.to_bits(),
                    g.rows.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>(),
                    ge.w,
                )
            })
        };
        assert_eq!(run(1), run(3));
    }
}
