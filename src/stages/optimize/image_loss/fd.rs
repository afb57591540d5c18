//! Test helpers of the image losses: deterministic images and a finite-difference checker
//! that collects every failure and asserts once (tolerance `abs + rel·|fd|`).

/// `n` deterministic values in [0, 1) on the 1/4096 grid (splitmix64), so that steps of
/// 1/1024 are exact in f32.
pub fn noise(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 52) as f32 / 4096.0
        })
        .collect()
}

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
