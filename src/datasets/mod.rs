//! Datasets: the synthetic extreme-view benchmark rendered from animated glTF models, and
//! the DyCheck iPhone loader.

pub mod demo;
pub mod dycheck;
pub mod synth;
