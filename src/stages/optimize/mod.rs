//! The optimisation stage (paper Sec. 4.3, Appendix A.2-A.3; release §5, §9-§11): trainable
//! per-frame poses, the motion regularisers of Appendix A.2 and the USplat4D graph losses
//! (L_key, Eq. 9; L_non-key, Eq. 11).

pub mod graph_loss;
pub mod motion;
pub mod poses;
