//! Math shared by the importers and the stages: continuous 6D rotations ([`rot6d`]) and
//! rotation-matrix / quaternion conversions with upstream sign conventions ([`rotmat`]).

pub mod rot6d;
pub mod rotmat;
