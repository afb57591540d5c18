//! Image and tracking metrics of the evaluation protocols (DyCheck, SoM, the paper's
//! synthetic benchmark): PSNR / masked mPSNR ([`psnr`]), SSIM / DyCheck's masked mSSIM
//! ([`ssim`]), LPIPS v0.1 AlexNet with its spatial map and masked mLPIPS ([`lpips`]),
//! 3D end-point error, 3D PCK and DyCheck's 2D PCK-T ([`tracking`]), and their benchmark
//! ([`bench`]).
//!
//! Images enter as [`crate::formats::png::Image`] `[H, W, 3]` values in [0, 1] that the caller
//! has already composited over the background and quantised to 8 bits
//! ([`crate::formats::png::Image::quantized`]), as DyCheck's `to_quantized_float32` does.
//! Masks are `[H, W]` values in [0, 1] (1 = the pixel counts), broadcast over channels.

#[cfg(test)]
mod dycheck_fixture;
pub mod lpips;
pub mod psnr;
pub mod ssim;
pub mod tracking;

use crate::formats::png::Image;

/// Errors of the metrics (mismatched inputs, LPIPS weights).
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Two images (or an image and its mask) have different sizes or channel counts.
    #[error("{what}: sizes differ: {a} vs {b}")]
    Size {
        /// What was compared.
        what: &'static str,
        /// Size of the first input, as `WxHxC`.
        a: String,
        /// Size of the second input.
        b: String,
    },
    /// An image is too small for the metric (SSIM needs 11x11, LPIPS 31x31).
    #[error("{what}: image {w}x{h} is smaller than the metric's minimum {min}x{min}")]
    TooSmall {
        /// The metric.
        what: &'static str,
        /// Width.
        w: usize,
        /// Height.
        h: usize,
        /// The minimum side.
        min: usize,
    },
    /// LPIPS weights are missing, malformed or do not match the pinned hash.
    #[error(transparent)]
    Weights(#[from] lpips::WeightsError),
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// Check that `a` and `b` are both `[H, W, 3]` of the same size and that `mask` (if any)
/// is `[H, W]`.
pub(crate) fn check_pair(
    what: &'static str,
    a: &Image,
    b: &Image,
    mask: Option<&[f32]>,
) -> Result<()> {
    let dims = |i: &Image| format!("{}x{}x{}", i.width, i.height, i.channels);
    if a.width != b.width || a.height != b.height || a.channels != 3 || b.channels != 3 {
        return Err(Error::Size { what, a: dims(a), b: dims(b) });
    }
    if let Some(m) = mask
        && m.len() != a.width * a.height
    {
        return Err(Error::Size { what, a: dims(a), b: format!("mask of {} pixels", m.len()) });
    }
    Ok(())
}
