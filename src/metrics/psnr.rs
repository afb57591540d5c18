//! PSNR and DyCheck's masked mPSNR (`dycheck/core/metrics/image.py::compute_psnr`).
//!
//! `mPSNR = −10·log10(masked_mean((a − b)², m))` with
//! `masked_mean(x, m) = Σ(x·m) / max(Σm, 1e-6)`, the `[H, W]` mask broadcast over the 3
//! channels (so Σm counts each pixel three times). Without a mask it is the plain PSNR of
//! the mean squared error over all `H·W·3` values, for a data range of 1. Identical images
//! (or an all-zero mask) give `+inf`.

use super::{Result, check_pair};
use crate::formats::png::Image;

/// PSNR (dB) of `a` against `b`, both `[H, W, 3]` in [0, 1]; `mask` `[H, W]` weights the
/// pixels (DyCheck's mPSNR) when given.
pub fn psnr(a: &Image, b: &Image, mask: Option<&[f32]>) -> Result<f64> {
    check_pair("psnr", a, b, mask)?;
    let (mut sse, mut weight) = (0.0f64, 0.0f64);
    for (i, (pa, pb)) in a.data.chunks_exact(3).zip(b.data.chunks_exact(3)).enumerate() {
        let m = mask.map_or(1.0, |m| m[i] as f64);
        for c in 0..3 {
            let d = pa[c] as f64 - pb[c] as f64;
            sse += d * d * m;
        }
        weight += 3.0 * m;
    }
    Ok(-10.0 * (sse / weight.max(1e-6)).log10())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, data: Vec<f32>) -> Image {
        Image { width: w, height: h, channels: 3, data }
    }

    #[test]
    fn identical_is_infinite() {
        let a = img(2, 1, vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
        assert_eq!(psnr(&a, &a, None).unwrap(), f64::INFINITY);
    }

    #[test]
    fn hand_computed_case() {
        // One value differs by 0.5 out of 6: MSE = 0.25 / 6, PSNR = 10·log10(24).
        let a = img(2, 1, vec![0.0; 6]);
        let mut bd = vec![0.0; 6];
        bd[4] = 0.5;
        let b = img(2, 1, bd);
        let want = 10.0 * 24f64.log10();
        assert!((psnr(&a, &b, None).unwrap() - want).abs() < 1e-9);
        // Masking out the differing pixel gives +inf; masking out the other one gives
        // MSE = 0.25 / 3.
        assert_eq!(psnr(&a, &b, Some(&[1.0, 0.0])).unwrap(), f64::INFINITY);
        let want = 10.0 * 12f64.log10();
        assert!((psnr(&a, &b, Some(&[0.0, 1.0])).unwrap() - want).abs() < 1e-9);
        // An all-zero mask: masked_mean is 0 / 1e-6 = 0.
        assert_eq!(psnr(&a, &b, Some(&[0.0, 0.0])).unwrap(), f64::INFINITY);
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let a = img(2, 1, vec![0.0; 6]);
        let b = img(1, 2, vec![0.0; 6]);
        assert_eq!(
            psnr(&a, &b, None).unwrap_err().to_string(),
            "psnr: sizes differ: 2x1x3 vs 1x2x3"
        );
        let e = psnr(&a, &a, Some(&[1.0])).unwrap_err().to_string();
        assert_eq!(e, "psnr: sizes differ: 2x1x3 vs mask of 1 pixels");
    }
}
