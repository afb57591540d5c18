//! L_rgb (paper App. A.3): the photometric L1 term on the composited colour.

use crate::render::{ImageGrads, RenderOutput};

/// Ground truth of one training frame.
#[derive(Debug, Clone, Copy)]
pub struct Truth<'a> {
    /// `[H, W, 3]` colour over the render's background.
    pub rgb: &'a [f32],
}

/// Weights of L_rgb's terms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RgbWeights {
    /// Weight of the L1 term.
    pub l1: f32,
}

/// Named loss terms of one frame and the image cotangents of their weighted sum.
pub fn rgb_loss(
    out: &RenderOutput,
    truth: &Truth,
    w: &RgbWeights,
) -> (Vec<(&'static str, f64)>, ImageGrads) {
    let n = out.color.len().max(1) as f64;
    let mut l1 = 0.0f64;
    let mut g = vec![0.0f32; out.color.len()];
    let s = w.l1 / n as f32;
    for (k, (c, t)) in out.color.iter().zip(truth.rgb).enumerate() {
        let d = c - t;
        l1 += d.abs() as f64;
        g[k] = s * d.signum();
    }
    (vec![("l1", l1 / n)], ImageGrads { color: g, ..ImageGrads::default() })
}
