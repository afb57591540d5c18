//! The one seeded random generator of the crate: splitmix64 (Steele, Lea and Flood 2014),
//! deterministic across platforms and thread counts.
//!
//! [`mix`] is the splitmix64 hash (one step of the stream from a state); [`Rng`] is the
//! reference splitmix64 stream. Outputs depend on how each caller seeded its stream, so the
//! seedings of the code this generator replaced are kept bit for bit: [`Rng::from_state`]
//! (the reference seeding: the renderer's test clouds, the metric tests), [`Rng::new`] (the
//! graph stages: the seed is hashed and the first output skipped) and
//! `Rng::from_state(seed).after(1)` (the synthetic benchmark's surface sampling).

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// The splitmix64 output function of an advanced state.
fn finalize(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// splitmix64 hash of `x`: the first output of the stream from state `x`.
pub fn mix(x: u64) -> u64 {
    finalize(x.wrapping_add(GOLDEN))
}

/// A reproducible random key of `(seed, stream, item)`: picking the item with the smallest
/// key is a uniform random pick that does not depend on iteration order or thread count.
pub fn rank_key(seed: u64, stream: u64, item: u64) -> u64 {
    mix(mix(mix(seed) ^ stream) ^ item)
}

/// A splitmix64 stream.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// The graph stages' stream of `seed`: from state `mix(seed)` (nearby seeds give
    /// unrelated streams), first output skipped.
    pub fn new(seed: u64) -> Self {
        Rng(mix(seed)).after(1)
    }

    /// The reference splitmix64 stream from state `state`.
    pub fn from_state(state: u64) -> Self {
        Rng(state)
    }

    /// The same stream with its next `n` outputs skipped.
    pub fn after(mut self, n: usize) -> Self {
        self.0 = self.0.wrapping_add(GOLDEN.wrapping_mul(n as u64));
        self
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(GOLDEN);
        finalize(self.0)
    }

    /// Uniform in [0, 1) with 53 random bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [0, 1) with 24 random bits.
    pub fn uniform_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [lo, hi) (24 random bits).
    pub fn range_f32(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform_f32()
    }

    /// Standard normal (Box-Muller on [`Rng::uniform`]).
    pub fn normal(&mut self) -> f64 {
        let a = self.uniform().max(1e-300);
        let b = self.uniform();
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }

    /// Standard normal in f32 (Box-Muller on [`Rng::uniform_f32`]).
    pub fn normal_f32(&mut self) -> f32 {
        let u1 = self.uniform_f32().max(1e-7);
        let u2 = self.uniform_f32();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

/// `n` values of the stream from state `seed` in [0, 1) on the 1/4096 grid, so that
/// finite-difference steps of 1/1024 are exact in f32 (the gradient tests' images).
#[cfg(test)]
pub(crate) fn grid_noise(n: usize, seed: u64) -> Vec<f32> {
    let mut r = Rng::from_state(seed);
    (0..n).map(|_| (r.next_u64() >> 52) as f32 / 4096.0).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first outputs of the stream from state 0 (the reference values of splitmix64).
    #[test]
    fn stream_matches_reference_splitmix64() {
        let mut r = Rng::from_state(0);
        assert_eq!(r.next_u64(), 0xE220_A839_7B1D_CDAF);
        assert_eq!(r.next_u64(), 0x6E78_9E6A_A1B9_65F4);
        assert_eq!(r.next_u64(), 0x06C4_5D18_8009_454F);
        // The graph stages' seeding, as they wrote it: state mix(seed), then mix(state + φ).
        let (mut g, mut state) = (Rng::new(5), mix(5));
        for _ in 0..3 {
            state = state.wrapping_add(GOLDEN);
            assert_eq!(g.next_u64(), mix(state));
        }
    }
}
