//! Small helpers every layer may use: the seeded generator ([`rng`]), atomic file writes
//! ([`fs`]) and order statistics ([`stats`]) and image filters ([`filter`]).

pub mod filter;
pub mod fs;
pub mod rng;
pub mod stats;
