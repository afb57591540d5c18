//! Four f64 lanes ([`F4`]) for loops that apply the same arithmetic to many independent
//! items (the smoothness sweep's Gaussians): the generic quaternion functions of
//! [`super::quat64`] run on them unchanged, and the compiler turns the lane-by-lane
//! operations into vector instructions. Each lane's result has the bits of the same scalar
//! expression (IEEE operations, in the same order), so a lane loop is interchangeable with
//! its scalar form.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Lanes per [`F4`].
pub const LANES: usize = 4;

/// Four f64 values, operated on lane by lane.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct F4(pub [f64; LANES]);

impl F4 {
    /// `x` in every lane.
    #[inline]
    pub fn splat(x: f64) -> Self {
        F4([x; LANES])
    }

    /// `f` applied to every lane.
    #[inline]
    pub fn map(self, f: impl Fn(f64) -> f64) -> Self {
        F4(self.0.map(f))
    }

    /// Per lane: `a` where `c`, else `b`.
    #[inline]
    pub fn select(c: [bool; LANES], a: Self, b: Self) -> Self {
        F4(std::array::from_fn(|l| if c[l] { a.0[l] } else { b.0[l] }))
    }

    /// Per lane: `self < 0`.
    #[inline]
    pub fn lt0(self) -> [bool; LANES] {
        self.0.map(|x| x < 0.0)
    }

    /// Per lane: `self > 0`.
    #[inline]
    pub fn gt0(self) -> [bool; LANES] {
        self.0.map(|x| x > 0.0)
    }

    /// |x| per lane.
    #[inline]
    pub fn abs(self) -> Self {
        self.map(f64::abs)
    }

    /// √x per lane.
    #[inline]
    pub fn sqrt(self) -> Self {
        self.map(f64::sqrt)
    }
}

macro_rules! lane_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F4 {
            type Output = F4;
            #[inline]
            fn $f(self, o: F4) -> F4 {
                F4(std::array::from_fn(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl Neg for F4 {
    type Output = F4;
    #[inline]
    fn neg(self) -> F4 {
        self.map(|x| -x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::quat64 as q4;

    /// A lane computes the bits its scalar expression does.
    #[test]
    fn lanes_compute_the_scalar_bits() {
        let qa = [
            [0.3, -0.2, 0.9, 0.1],
            [1e-3, 0.7, -0.7, 0.2],
            [-0.5, 0.5, 0.5, -0.5],
            [1.0, 0.0, 0.0, 0.0],
        ];
        let qb = [
            [-0.1, 0.4, 0.4, 0.8],
            [0.2, 0.2, -0.9, 0.1],
            [0.6, -0.3, 0.1, 0.7],
            [0.0, 1.0, 0.0, 0.0],
        ];
        let lanes = |q: [[f64; 4]; 4]| -> [F4; 4] { std::array::from_fn(|c| F4(q.map(|x| x[c]))) };
        let (a, b) = (lanes(qa), lanes(qb));
        let (ga, gb) = q4::mul_vjp(a, q4::conj(b), q4::mul(a, b));
        for l in 0..LANES {
            let (sa, sb) = q4::mul_vjp(qa[l], q4::conj(qb[l]), q4::mul(qa[l], qb[l]));
            for c in 0..4 {
                assert_eq!(ga[c].0[l].to_bits(), sa[c].to_bits());
                assert_eq!(gb[c].0[l].to_bits(), sb[c].to_bits());
            }
            let d = q4::dot4(a, b).sqrt() / F4::splat(3.0);
            assert_eq!(d.0[l].to_bits(), (q4::dot4(qa[l], qb[l]).sqrt() / 3.0).to_bits());
        }
        let x = F4([-1.0, 2.0, 0.0, -0.0]);
        assert_eq!(F4::select(x.lt0(), -x, x), x.abs());
        assert_eq!(x.gt0(), [false, true, false, false]);
    }
}
