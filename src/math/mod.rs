//! Math shared by the renderer, the stages and the optimiser: quaternions and their
//! vector-Jacobian products ([`quat`] in f32, [`quat64`] in f64) and dual quaternion
//! blending ([`dqb`]).

pub mod dqb;
pub mod quat;
pub mod quat64;
