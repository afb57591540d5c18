//! Math shared by the renderer, the importers, the stages and the optimiser: quaternions and
//! their vector-Jacobian products ([`quat`] in f32, [`quat64`] in f64, with the rotation
//! matrix / quaternion conversions of the upstream sign conventions), dual quaternion
//! blending ([`dqb`]), continuous 6D rotations ([`rot6d`]) and f64 lanes for vectorised
//! sweeps, with the L1 terms' sign ([`lanes`]).

pub mod dqb;
pub mod lanes;
pub mod quat;
pub mod quat64;
pub mod rot6d;
