//! Two f64 lanes ([`F2`]) for loops that apply the same arithmetic to many independent
//! items (the smoothness sweep's Gaussians): the generic quaternion functions of
//! [`super::quat64`] run on them unchanged, and the compiler turns the lane-by-lane
//! operations into vector instructions. Two lanes are one register of the x86-64 baseline
//! (SSE2), so a quaternion of lanes stays in registers; four were slower for the spills. Each lane's result has the bits of the same scalar
//! expression (IEEE operations, in the same order), so a lane loop is interchangeable with
//! its scalar form.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Lanes per [`F2`].
pub const LANES: usize = 2;

/// Two f64 values, operated on lane by lane.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct F2(pub [f64; LANES]);

impl F2 {
    /// `x` in every lane.
    #[inline]
    pub fn splat(x: f64) -> Self {
        F2([x; LANES])
    }

    /// `f` applied to every lane.
    #[inline]
    pub fn map(self, f: impl Fn(f64) -> f64) -> Self {
        F2(self.0.map(f))
    }

    /// Per lane: `a` where `c`, else `b`.
    #[inline]
    pub fn select(c: [bool; LANES], a: Self, b: Self) -> Self {
        F2(std::array::from_fn(|l| if c[l] { a.0[l] } else { b.0[l] }))
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
        impl $tr for F2 {
            type Output = F2;
            #[inline]
            fn $f(self, o: F2) -> F2 {
                F2(std::array::from_fn(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl Neg for F2 {
    type Output = F2;
    #[inline]
    fn neg(self) -> F2 {
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
        let qa = [[0.3, -0.2, 0.9, 0.1], [1e-3, 0.7, -0.7, 0.2], [-0.5, 0.5, 0.5, -0.5]];
        let qb = [[-0.1, 0.4, 0.4, 0.8], [0.2, 0.2, -0.9, 0.1], [0.6, -0.3, 0.1, 0.7]];
        for s in 0..qa.len() + 1 - LANES {
            let lanes = |q: &[[f64; 4]]| -> [F2; 4] {
                std::array::from_fn(|c| F2(std::array::from_fn(|l| q[s + l][c])))
            };
            let (a, b) = (lanes(&qa), lanes(&qb));
            let (ga, gb) = q4::mul_vjp(a, q4::conj(b), q4::mul(a, b));
            for l in 0..LANES {
                let (qa, qb) = (qa[s + l], qb[s + l]);
                let (sa, sb) = q4::mul_vjp(qa, q4::conj(qb), q4::mul(qa, qb));
                for c in 0..4 {
                    assert_eq!(ga[c].0[l].to_bits(), sa[c].to_bits());
                    assert_eq!(gb[c].0[l].to_bits(), sb[c].to_bits());
                }
                let d = q4::dot4(a, b).sqrt() / F2::splat(3.0);
                assert_eq!(d.0[l].to_bits(), (q4::dot4(qa, qb).sqrt() / 3.0).to_bits());
            }
        }
        for x in [F2([-1.0, 2.0]), F2([0.0, -0.0])] {
            assert_eq!(F2::select(x.lt0(), -x, x), x.abs());
        }
        assert_eq!(F2([-1.0, 2.0]).gt0(), [false, true]);
    }
}
