//! Math shared by the renderer, the stages and the optimiser: quaternions and their
//! vector-Jacobian products ([`quat`]).

pub mod quat;
