//! `usplat4d optimize` (paper Sec. 4.3, Appendix A.2-A.3): the vanilla and USplat4D
//! recipes. [`image_loss`] is L_rgb, the image-space loss of one rendered training frame.

pub mod image_loss;
