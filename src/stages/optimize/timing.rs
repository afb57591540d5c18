//! Wall-clock time per phase of the optimisation steps (image loading, render forward and
//! backward, L_rgb, the motion or graph terms, Adam, density control), summed over steps, for
//! `usplat4d bench optimize`'s breakdown. Timing reads the clock around each phase and
//! changes nothing the phases compute.

use std::time::{Duration, Instant};

/// Per-phase wall time, phases in the order first seen.
#[derive(Debug, Clone, Default)]
pub struct PhaseTimes {
    /// `(phase, total time)`.
    pub totals: Vec<(&'static str, Duration)>,
}

impl PhaseTimes {
    /// Run `f`, adding its wall time to `phase`.
    pub fn time<R>(&mut self, phase: &'static str, f: impl FnOnce() -> R) -> R {
        let start = Instant::now();
        let r = f();
        self.add(phase, start.elapsed());
        r
    }

    /// Add `d` to `phase`.
    pub fn add(&mut self, phase: &'static str, d: Duration) {
        match self.totals.iter_mut().find(|(k, _)| *k == phase) {
            Some((_, t)) => *t += d,
            None => self.totals.push((phase, d)),
        }
    }

    /// Add every phase of `other`.
    pub fn merge(&mut self, other: &PhaseTimes) {
        for &(k, d) in &other.totals {
            self.add(k, d);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_accumulate_in_first_seen_order() {
        let mut t = PhaseTimes::default();
        t.add("b", Duration::from_millis(2));
        assert_eq!(t.time("a", || 7), 7);
        t.add("b", Duration::from_millis(3));
        let mut u = PhaseTimes::default();
        u.merge(&t);
        assert_eq!(u.totals.iter().map(|x| x.0).collect::<Vec<_>>(), ["b", "a"]);
        assert_eq!(u.totals[0].1, Duration::from_millis(5));
    }
}
