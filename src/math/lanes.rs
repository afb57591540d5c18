//! `L` f64 lanes ([`Lanes`]) for loops that apply the same arithmetic to many independent
//! items (the smoothness sweep's Gaussians): the generic quaternion functions of
//! [`super::quat64`] run on them unchanged, and the compiler turns the lane-by-lane
//! operations into vector instructions. Two lanes are one register of the x86-64
//! baseline (SSE2), so a quaternion of lanes stays in registers. Each lane's result has the
//! bits of the same scalar expression (IEEE operations, in the same order), so a lane loop
//! is interchangeable with its scalar form, and one lane is the scalar form.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// sign(x) with sign(0) = 0 (and 0 for NaN): the subgradient of |x| that the L1 terms use;
/// [`Lanes::sign`] is its per-lane form.
#[inline]
pub fn sign(x: f64) -> f64 {
    // branch-free: the signs of the L1 terms' residuals are unpredictable
    (x > 0.0) as u8 as f64 - (x < 0.0) as u8 as f64
}

/// `L` f64 values, operated on lane by lane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lanes<const L: usize>(pub [f64; L]);

impl<const L: usize> Default for Lanes<L> {
    fn default() -> Self {
        Lanes([0.0; L])
    }
}

impl<const L: usize> Lanes<L> {
    /// `x` in every lane.
    #[inline]
    pub fn splat(x: f64) -> Self {
        Lanes([x; L])
    }

    /// `f` applied to every lane.
    #[inline]
    pub fn map(self, f: impl Fn(f64) -> f64) -> Self {
        Lanes(self.0.map(f))
    }

    /// Per lane: `a` where `c`, else `b` (by the bits, as a vector blend).
    #[inline]
    pub fn select(c: Mask<L>, a: Self, b: Self) -> Self {
        Lanes(std::array::from_fn(|l| {
            f64::from_bits((a.0[l].to_bits() & c.0[l]) | (b.0[l].to_bits() & !c.0[l]))
        }))
    }

    /// Per lane: `self < 0`.
    #[inline]
    pub fn lt0(self) -> Mask<L> {
        Mask(self.0.map(|x| if x < 0.0 { u64::MAX } else { 0 }))
    }

    /// Per lane: `self > 0`.
    #[inline]
    pub fn gt0(self) -> Mask<L> {
        Mask(self.0.map(|x| if x > 0.0 { u64::MAX } else { 0 }))
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

    /// [`sign`] per lane (±1, and +0 for ±0 and NaN), by masks (a compare and a blend)
    /// rather than a conversion per lane.
    #[inline]
    pub fn sign(self) -> Self {
        let (one, zero) = (Self::splat(1.0), Self::splat(0.0));
        Self::select(self.gt0(), one, zero) - Self::select(self.lt0(), one, zero)
    }
}

/// A per-lane condition of [`Lanes`]: every bit set where it holds (a vector compare's
/// result).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mask<const L: usize>([u64; L]);

impl<const L: usize> Mask<L> {
    /// Whether the condition holds in every lane.
    #[inline]
    pub fn all(self) -> bool {
        self.0.iter().all(|&m| m == u64::MAX)
    }
}

macro_rules! lane_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<const L: usize> $tr for Lanes<L> {
            type Output = Lanes<L>;
            #[inline]
            fn $f(self, o: Lanes<L>) -> Lanes<L> {
                Lanes(std::array::from_fn(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl<const L: usize> Neg for Lanes<L> {
    type Output = Lanes<L>;
    #[inline]
    fn neg(self) -> Lanes<L> {
        self.map(|x| -x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::quat64 as q4;

    type F2 = Lanes<2>;

    /// A lane computes the bits its scalar expression does.
    #[test]
    fn lanes_compute_the_scalar_bits() {
        let qa = [[0.3, -0.2, 0.9, 0.1], [1e-3, 0.7, -0.7, 0.2], [-0.5, 0.5, 0.5, -0.5]];
        let qb = [[-0.1, 0.4, 0.4, 0.8], [0.2, 0.2, -0.9, 0.1], [0.6, -0.3, 0.1, 0.7]];
        for s in 0..qa.len() - 1 {
            let lanes = |q: &[[f64; 4]]| -> [F2; 4] {
                std::array::from_fn(|c| Lanes(std::array::from_fn(|l| q[s + l][c])))
            };
            let (a, b) = (lanes(&qa), lanes(&qb));
            let (ga, gb) = q4::mul_vjp(a, q4::conj(b), q4::mul(a, b));
            for l in 0..2 {
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
        for x in [Lanes([-1.0, 2.0]), Lanes([0.0, -0.0])] {
            assert_eq!(F2::select(x.lt0(), -x, x), x.abs());
        }
        let xs = [-2.5, 3.0, 0.0, -0.0, f64::NAN, f64::INFINITY, -f64::INFINITY, -5e-324, 5e-324];
        for w in xs.windows(2) {
            let s = Lanes([w[0], w[1]]).sign();
            for l in 0..2 {
                let want = sign(w[l]);
                assert_eq!(s.0[l].to_bits(), want.to_bits(), "sign of {}", w[l]);
            }
        }
        let m = Lanes([-1.0, 2.0]).gt0();
        assert!(!m.all() && Lanes([1.0, 2.0]).gt0().all());
        assert_eq!(F2::select(m, F2::splat(1.0), F2::splat(-1.0)), Lanes([-1.0, 1.0]));
    }
}
