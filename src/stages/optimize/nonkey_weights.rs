//! The blend weights w'_{uk} of a non-key's DQB (paper Eq. 10, "normalized edge weights";
//! official-release.md §4.2 `cal_weight_edges2` and `cal_DQB_nonkeyGaussian`, profile row 32)
//! with the release's trainable parts, one non-key (row) at a time:
//!
//! w_uk = clamp(exp(|θ_k| · L_uk), 1e-10, 1e10),  ŵ_uk = w_uk / Σ_k w_uk,
//! w'_uk = |ŵ_uk + Δw_uk| / Σ_k |ŵ_uk + Δw_uk|,
//!
//! θ_k a trainable per-key sharpness (`weight_param_key`, init 1) and Δw_u trainable per-edge
//! offsets (`per_nonkeyGaussian_dweight`, init 0). The log-base L_uk is [`NonkeyWeights`]'s:
//! the edges table's weight (fixed) or −λ‖p_u(t̂_u) − p_k(t̂_u)‖² from the current positions.
//! A row whose Σ|ŵ + Δw| is 0 blends uniformly, with zero gradient; a clamped w_uk passes no
//! gradient (as torch's clamp).

use super::sign;

/// The log-base L_uk of the non-key blend weights (profile row 32).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum NonkeyWeights {
    /// ln of the edges table's normalised weight (fixed): w_uk ∝ w_table^{|θ_k|}, the table's
    /// weights at θ = 1, Δw = 0 (the paper's "normalized edge weights", with the release's
    /// trainable θ and Δw).
    Table,
    /// −λ‖p_u(t̂_u) − p_k(t̂_u)‖² from the current positions at the non-key's t̂_u, with the
    /// edges table's λ and distance unit, recomputed each step with gradients to those
    /// positions (the release's training: exp(−d²)^{100|θ_k|}).
    Current,
}

/// The edges stage's metadata (`usplat4d.graph`, JSON) → λ / unit², the factor of −d² in L_uk
/// of [`NonkeyWeights::Current`] that reproduces the table's weights at θ = 1.
pub fn lambda_from_graph_metadata(json: &str) -> Result<f64, String> {
    let v: serde_json::Value =
        serde_json::from_str(json).map_err(|e| format!("graph metadata is not JSON: {e}"))?;
    let get = |key: &str| {
        v.get(key)
            .and_then(serde_json::Value::as_f64)
            .filter(|x| x.is_finite() && *x > 0.0)
            .ok_or_else(|| format!("graph metadata has no positive number '{key}'"))
    };
    let (lambda, unit) = (get("nonkey-weight-sharpness")?, get("nonkey-distance-unit")?);
    Ok(lambda / (unit * unit))
}

/// The smallest and largest w_uk before normalising (release `torch.clamp`).
const CLAMP: (f64, f64) = (1e-10, 1e10);

/// One row's inputs, `[k]` each (k edges of one non-key).
#[derive(Debug, Clone, Copy)]
pub struct Row<'a> {
    /// The log-bases L_uk.
    pub l: &'a [f64],
    /// θ of each edge's key.
    pub theta: &'a [f64],
    /// The offsets Δw_uk.
    pub dw: &'a [f64],
}

/// Forward of one row: the weights w' `[k]`.
pub fn row(r: Row, out: &mut [f64]) {
    let Row { l, theta, dw } = r;
    let k = l.len();
    let mut s = 0.0;
    for j in 0..k {
        out[j] = clamped(theta[j].abs() * l[j]);
        s += out[j];
    }
    let mut a = 0.0;
    for j in 0..k {
        out[j] = (out[j] / s + dw[j]).abs();
        a += out[j];
    }
    for o in out.iter_mut() {
        *o = if a > 0.0 { *o / a } else { 1.0 / k as f64 };
    }
}

/// `exp(x)`, 0 for NaN (|θ| = 0 with L = −∞, a zero table weight).
fn raw(x: f64) -> f64 {
    let w = x.exp();
    if w.is_nan() { 0.0 } else { w }
}

/// `clamp(exp(x))`.
fn clamped(x: f64) -> f64 {
    raw(x).clamp(CLAMP.0, CLAMP.1)
}

/// Gradients of [`row`] given the cotangent `g` of w' `[k]`: adds to `g_l`, `g_theta` (per
/// edge, to be summed per key) and `g_dw`. `tmp` is scratch space of at least 2k values.
pub fn row_vjp(
    r: Row,
    g: &[f64],
    tmp: &mut [f64],
    g_l: &mut [f64],
    g_theta: &mut [f64],
    g_dw: &mut [f64],
) {
    let Row { l, theta, dw } = r;
    let k = l.len();
    let (w, v) = tmp[..2 * k].split_at_mut(k);
    let mut s = 0.0;
    for j in 0..k {
        w[j] = raw(theta[j].abs() * l[j]);
        s += w[j].clamp(CLAMP.0, CLAMP.1);
    }
    let mut a = 0.0;
    for j in 0..k {
        v[j] = w[j].clamp(CLAMP.0, CLAMP.1) / s + dw[j];
        a += v[j].abs();
    }
    if a == 0.0 {
        return;
    }
    // w' = |v| / Σ|v|: g_v = sign(v) (g − ⟨g, w'⟩) / Σ|v|, and g_Δw = g_ŵ = g_v
    let dot: f64 = (0..k).map(|j| g[j] * v[j].abs() / a).sum();
    for j in 0..k {
        v[j] = sign(v[j]) * (g[j] - dot) / a;
        g_dw[j] += v[j];
    }
    // ŵ = w / Σ w: g_w = (g_ŵ − ⟨g_ŵ, ŵ⟩) / Σ w, passed where the clamp is inactive
    let dot2: f64 = (0..k).map(|j| v[j] * w[j].clamp(CLAMP.0, CLAMP.1) / s).sum();
    for j in 0..k {
        if !(CLAMP.0..=CLAMP.1).contains(&w[j]) {
            continue;
        }
        let g_a = (v[j] - dot2) / s * w[j];
        g_l[j] += g_a * theta[j].abs();
        g_theta[j] += g_a * l[j] * sign(theta[j]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_sharpness_and_no_offsets_give_the_normalised_base() {
        let table = [0.5f64, 0.3, 0.2];
        let l = table.map(f64::ln);
        let mut out = [0.0; 3];
        row(Row { l: &l, theta: &[1.0; 3], dw: &[0.0; 3] }, &mut out);
        for j in 0..3 {
            assert!((out[j] - table[j]).abs() < 1e-15, "{out:?}");
        }
        // the release's exp(−d²)^(100 θ): very far keys are clamped, not zero
        let l = [-0.01, -1.0, -2.0].map(|d2| 100.0 * d2);
        row(Row { l: &l, theta: &[1.0; 3], dw: &[0.0; 3] }, &mut out);
        assert!((out[1] - 1e-10 / (1e-10 + 1e-10 + (-1.0f64).exp())).abs() < 1e-20);
        // all offsets cancelling the weights: uniform
        row(Row { l: &[0.0, 0.0], theta: &[1.0; 2], dw: &[-0.5, -0.5] }, &mut out[..2]);
        assert_eq!(out[..2], [0.5, 0.5]);
    }

    #[test]
    fn row_vjp_matches_finite_differences() {
        let l = [-0.3, -1.1, -0.05, -2.0];
        let theta = [1.2, -0.7, 0.9, 1.0];
        let dw = [0.01, -0.05, 0.2, -0.02];
        let g = [0.3, -1.0, 0.5, 2.0];
        let f = |l: &[f64], th: &[f64], dw: &[f64]| {
            let mut out = [0.0; 4];
            row(Row { l, theta: th, dw }, &mut out);
            out.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
        };
        let (mut gl, mut gt, mut gd) = ([0.0; 4], [0.0; 4], [0.0; 4]);
        let r = Row { l: &l, theta: &theta, dw: &dw };
        row_vjp(r, &g, &mut [0.0; 8], &mut gl, &mut gt, &mut gd);
        let h = 1e-6;
        let fd = |which: usize, j: usize| {
            let mut x = [l, theta, dw];
            x[which][j] += h;
            let fp = f(&x[0], &x[1], &x[2]);
            x[which][j] -= 2.0 * h;
            let fm = f(&x[0], &x[1], &x[2]);
            (fp - fm) / (2.0 * h)
        };
        for j in 0..4 {
            for (which, a) in [(0, gl[j]), (1, gt[j]), (2, gd[j])] {
                let d = fd(which, j);
                assert!((a - d).abs() < 1e-7 * (1.0 + d.abs()), "{which} {j}: {a} vs {d}");
            }
        }
    }

    #[test]
    fn graph_metadata_gives_lambda_over_unit_squared() {
        let m = r#"{"nonkey-weight-sharpness": 100.0, "nonkey-distance-unit": 2.0}"#;
        assert_eq!(lambda_from_graph_metadata(m), Ok(25.0));
        let e = lambda_from_graph_metadata(r#"{"nonkey-weight-sharpness": 100.0}"#);
        assert_eq!(e, Err("graph metadata has no positive number 'nonkey-distance-unit'".into()));
    }
}
