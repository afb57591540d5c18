//! File formats read by the importers: pickle streams ([`pickle`]), PyTorch checkpoints
//! ([`torch`]), numpy `.npy`/`.npz` arrays ([`npz`]) and the dense arrays they decode to
//! ([`array`]).

pub mod array;
pub mod npz;
pub mod pickle;
pub mod torch;
