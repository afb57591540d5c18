//! Constants of the rasterizer shared by projection, tiling, forward and backward (and
//! mirrored by the GPU shaders).
//!
//! Relation between the three alpha/transmittance constants:
//! - a Gaussian contributes to a pixel only if its `alpha >= ALPHA_THRESHOLD` (1/255, one
//!   8-bit step), so its screen extent is the ellipse where `o·exp(-σ) >= ALPHA_THRESHOLD`,
//!   i.e. `σ <= ln(255·o)` ("opacity-aware extent"), and Gaussians with `o < ALPHA_THRESHOLD`
//!   are culled outright;
//! - `alpha` is clamped to `alpha_max` (`MAX_ALPHA` by default, 0.99 or 0.999), so one
//!   Gaussian multiplies the transmittance by at least `1 - alpha_max` and T stays > 0, which
//!   the backward pass needs to divide by `1 - alpha`;
//! - blending stops before the Gaussian that would bring the transmittance to `T_THRESHOLD`
//!   (1e-4) or below; everything behind would change the 8-bit colour by less than
//!   `T_THRESHOLD < ALPHA_THRESHOLD`.

/// Smallest alpha that contributes to a pixel.
pub const ALPHA_THRESHOLD: f32 = 1.0 / 255.0;
/// Default upper clamp of alpha (3DGS/gsplat use 0.99, the release's fork 0.999).
pub const MAX_ALPHA: f32 = 0.99;
/// Blending stops when the next transmittance would be at or below this.
pub const T_THRESHOLD: f32 = 1e-4;
/// Tile side in pixels (tiles are `TILE_SIZE x TILE_SIZE`).
pub const TILE_SIZE: u32 = 16;
/// Variance added to the 2D covariance (the EWA low-pass filter), pixels².
pub const COV_BLUR: f32 = 0.3;
/// Half-width of the accepted projection window beyond the image, as a fraction of the
/// half field of view (gsplat's 1.3 tan(fov/2) clamp of the Jacobian).
pub const FOV_MARGIN: f32 = 0.3;
