//! Shared machinery of the graph stages (`keynodes`, `edges`, `segment`, `bench graph`):
//! the in-memory [`tracks::Tracks`], the anisotropic uncertainty of the paper's Eq. 6
//! ([`metric`]), the exact accelerated neighbour searches ([`search`]) and spectral
//! clustering ([`spectral`]).
//!
//! Memory: the tracks are the largest array of the graph stages (see [`tracks`]); the edge
//! search adds O(K·T) for K key nodes and O(N·k) edges.

pub mod metric;
pub mod search;
pub mod spectral;
pub mod tracks;
