//! Test helpers of the image losses: deterministic images and a finite-difference checker
//! that collects every failure and asserts once (tolerance `abs + rel·|fd|`).

pub(crate) use crate::util::rng::grid_noise as noise;

/// Collects finite-difference comparisons of one test.
pub struct Check {
    name: String,
    abs: f64,
    rel: f64,
    failures: Vec<String>,
    max_err: f64,
    count: usize,
}

impl Check {
    /// A checker with tolerance `abs + rel·|fd|`.
    pub fn new(name: &str, abs: f64, rel: f64) -> Check {
        Check { name: name.into(), abs, rel, failures: Vec::new(), max_err: 0.0, count: 0 }
    }

    /// Compare one analytic derivative with its finite difference.
    pub fn compare(&mut self, case: &str, analytic: f64, fd: f64) {
        let err = (analytic - fd).abs();
        self.max_err = self.max_err.max(err);
        self.count += 1;
        if err.is_nan() || err > self.abs + self.rel * fd.abs() {
            self.failures.push(format!("{case}: analytic {analytic:.9e}, fd {fd:.9e}"));
        }
    }

    /// Central differences of `loss` at every `stride`-th entry of `x` (step `eps`, exact in
    /// f32 for inputs on the 1/4096 grid) against the analytic gradient `g`.
    pub fn image(
        &mut self,
        case: &str,
        x: &[f32],
        g: &[f32],
        eps: f32,
        loss: impl Fn(&[f32]) -> f64,
        stride: usize,
    ) {
        let mut v = x.to_vec();
        for i in (0..x.len()).step_by(stride) {
            v[i] = x[i] + eps;
            let lp = loss(&v);
            v[i] = x[i] - eps;
            let lm = loss(&v);
            v[i] = x[i];
            let fd = (lp - lm) / (2.0 * eps as f64);
            self.compare(&format!("{case} [{i}]"), g[i] as f64, fd);
        }
    }

    /// Print the largest error and assert that nothing failed.
    pub fn finish(self) {
        eprintln!(
            "FD {}: {} comparisons, max abs error {:.3e}",
            self.name, self.count, self.max_err
        );
        assert!(self.count > 0, "FD {}: nothing compared", self.name);
        assert!(
            self.failures.is_empty(),
            "FD {}: {} of {} failed:\n{}",
            self.name,
            self.failures.len(),
            self.count,
            self.failures.join("\n")
        );
    }
}
