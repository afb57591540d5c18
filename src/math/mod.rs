//! Math shared by the renderer, the importers, the stages and the optimiser: quaternions and
//! their vector-Jacobian products ([`quat`] in f32, [`quat64`] in f64), dual quaternion
//! blending ([`dqb`]), continuous 6D rotations ([`rot6d`]) and rotation-matrix / quaternion
//! conversions with upstream sign conventions ([`rotmat`]).

pub mod dqb;
pub mod quat;
pub mod quat64;
pub mod rot6d;
pub mod rotmat;
