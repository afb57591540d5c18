//! The optimisation stage `usplat4d optimize` (paper Sec. 4.3, Appendix A.2-A.3 and B;
//! release §5, §9-§11): trainable per-frame poses, L_rgb through the differentiable
//! renderer, the motion regularisers of Appendix A.2 and the USplat4D graph losses (L_key,
//! L_non-key), Adam, density control, checkpoints. [`params`] lists every parameter with its
//! paper and release values; [`train`] is the loop.

pub mod adam;
pub mod checkpoint;
pub mod density;
pub mod graph_loss;
pub mod image_loss;
pub mod motion;
pub mod nonkey_weights;
pub mod objective;
pub mod params;
pub mod poses;
pub mod smoothness;
pub mod state;
pub mod step;
pub mod timing;
pub mod train;

pub use params::OptimizeParams;
pub use train::run;

pub use crate::math::lanes::sign;
