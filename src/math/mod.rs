//! Math shared by the renderer, the stages and the optimiser: double-precision quaternion
//! algebra with its vector-Jacobian products ([`quat64`]) and dual quaternion blending
//! ([`dqb`]).

pub mod dqb;
pub mod quat64;
