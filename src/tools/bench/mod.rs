//! `usplat4d bench ...`: timings of the renderer, the graph stages, the metrics and the
//! uncertainty stage (release builds only give meaningful numbers).

pub mod graph;
pub mod metrics;
pub mod render;
pub mod uncertainty;
