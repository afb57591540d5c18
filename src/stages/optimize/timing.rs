//! Time per phase of the optimisation steps (image loading, render forward and backward,
//! L_rgb, the motion or graph terms, Adam, density control), summed over steps, for
//! `usplat4d bench optimize`'s breakdown: wall time, and CPU time of all the process's
//! threads (Linux `/proc/self/task/*/schedstat`, nanoseconds; absent elsewhere), which a
//! busy machine inflates far less than wall time, read only when asked for
//! ([`PhaseTimes::with_cpu_time`]) since it costs file reads per phase. Timing reads clocks
//! around each phase and changes nothing the phases compute.

use std::time::{Duration, Instant};

/// Per-phase totals, phases in the order first seen.
#[derive(Debug, Clone, Default)]
pub struct PhaseTimes {
    /// `(phase, wall time, CPU time)`; CPU time is `None` where it is not read or cannot be.
    pub totals: Vec<(&'static str, Duration, Option<Duration>)>,
    /// `(part, phase)`: the phases that ran inside another one, beside other parts (their
    /// wall times overlap; their CPU time is not read).
    pub within: Vec<(&'static str, &'static str)>,
    /// Whether phases also read the process's CPU time.
    cpu: bool,
}

/// The clocks at the start of a phase.
#[derive(Debug, Clone, Copy)]
pub struct Mark {
    wall: Instant,
    cpu: Option<u64>,
}

/// CPU time of every thread of this process so far, in nanoseconds.
fn cpu_ns() -> Option<u64> {
    let mut total = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let text = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        total += text.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total)
}

impl PhaseTimes {
    /// Totals that also hold the CPU time of each phase (wall time only by default).
    pub fn with_cpu_time() -> Self {
        PhaseTimes { cpu: true, ..PhaseTimes::default() }
    }

    /// The clocks now.
    pub fn start(&self) -> Mark {
        Mark { wall: Instant::now(), cpu: if self.cpu { cpu_ns() } else { None } }
    }

    /// Add the time since `mark` to `phase`.
    pub fn stop(&mut self, phase: &'static str, mark: Mark) {
        let cpu = mark.cpu.and_then(|a| Some(Duration::from_nanos(cpu_ns()?.saturating_sub(a))));
        self.add(phase, mark.wall.elapsed(), cpu);
    }

    /// Run `f`, adding its time to `phase`.
    pub fn time<R>(&mut self, phase: &'static str, f: impl FnOnce() -> R) -> R {
        let mark = self.start();
        let r = f();
        self.stop(phase, mark);
        r
    }

    fn add(&mut self, phase: &'static str, wall: Duration, cpu: Option<Duration>) {
        match self.totals.iter_mut().find(|(k, ..)| *k == phase) {
            Some((_, w, c)) => {
                *w += wall;
                *c = c.zip(cpu).map(|(a, b)| a + b);
            }
            None => self.totals.push((phase, wall, cpu)),
        }
    }

    /// Add every phase of `other`.
    pub fn merge(&mut self, other: &PhaseTimes) {
        for &(k, w, c) in &other.totals {
            self.add(k, w, c);
        }
        for &(k, p) in &other.within {
            self.mark_within(k, p);
        }
    }

    /// Add the phases of `other` as parts of `phase` (wall time only).
    pub fn merge_within(&mut self, phase: &'static str, other: &PhaseTimes) {
        for &(k, w, _) in &other.totals {
            self.add(k, w, None);
            self.mark_within(k, phase);
        }
    }

    /// The phase that `part` ran inside, if any.
    pub fn parent(&self, part: &str) -> Option<&'static str> {
        self.within.iter().find(|(k, _)| *k == part).map(|(_, p)| *p)
    }

    fn mark_within(&mut self, part: &'static str, phase: &'static str) {
        if self.parent(part).is_none() {
            self.within.push((part, phase));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_accumulate_in_first_seen_order() {
        let mut t = PhaseTimes::with_cpu_time();
        t.add("b", Duration::from_millis(2), Some(Duration::from_millis(1)));
        assert_eq!(t.time("a", || (0..200_000u64).map(|x| x ^ 3).sum::<u64>()), 19_999_900_000);
        t.add("b", Duration::from_millis(3), Some(Duration::from_millis(4)));
        let mut u = PhaseTimes::default();
        u.merge(&t);
        assert_eq!(u.totals.iter().map(|x| x.0).collect::<Vec<_>>(), ["b", "a"]);
        assert_eq!(u.totals[0].1, Duration::from_millis(5));
        assert_eq!(u.totals[0].2, Some(Duration::from_millis(5)));
        if cfg!(target_os = "linux") {
            assert!(u.totals[1].2.is_some(), "CPU time is read on Linux");
        }
    }

    #[test]
    fn parts_keep_their_phase_and_only_wall_time() {
        let mut part = PhaseTimes::with_cpu_time();
        part.add("render", Duration::from_millis(4), Some(Duration::from_millis(4)));
        let mut t = PhaseTimes::with_cpu_time();
        t.add("both", Duration::from_millis(5), Some(Duration::from_millis(9)));
        t.merge_within("both", &part);
        t.merge_within("both", &part);
        let mut total = PhaseTimes::default();
        total.merge(&t);
        assert_eq!(total.parent("render"), Some("both"));
        assert_eq!(total.parent("both"), None);
        assert_eq!(total.totals[1], ("render", Duration::from_millis(8), None));
    }
}
