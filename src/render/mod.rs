//! The differentiable Gaussian rasterizer (being written).

pub mod bench;
