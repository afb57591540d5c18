//! Image and tracking metrics (being written).

pub mod bench;
pub mod lpips;
