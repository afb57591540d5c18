//! Adam (Kingma & Ba) with one group per parameter tensor and a constant learning rate per
//! group, as the release's fine-tuning stage configures it (official-release.md Sec. 5.3:
//! one Adam per tensor, `LambdaLR = 1`). The step count is shared by all groups; moments
//! are f32 like the parameters. Element-wise and rayon over chunks, so the result does not
//! depend on the thread count.

use rayon::prelude::*;

/// β₁ of every group.
pub const BETA1: f32 = 0.9;
/// β₂ of every group.
pub const BETA2: f32 = 0.999;
/// ε of every group (3DGS and MoSca's Gaussian optimisers).
pub const EPS: f32 = 1e-15;

/// Moments of one parameter tensor, flattened.
#[derive(Debug, Clone, PartialEq)]
pub struct Group {
    /// Name (the training log's `lr_<name>` column).
    pub name: String,
    /// Learning rate.
    pub lr: f32,
    /// First moment, same length as the tensor.
    pub m: Vec<f32>,
    /// Second moment.
    pub v: Vec<f32>,
}

/// The optimiser: groups and the step count t.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    /// Steps taken so far.
    pub t: u64,
    /// One group per tensor.
    pub groups: Vec<Group>,
}

impl Adam {
    /// An optimiser over `(name, lr, len)` tensors with zero moments.
    pub fn new(groups: &[(&str, f32, usize)]) -> Self {
        Adam {
            t: 0,
            groups: groups
                .iter()
                .map(|&(name, lr, n)| Group {
                    name: name.to_string(),
                    lr,
                    m: vec![0.0; n],
                    v: vec![0.0; n],
                })
                .collect(),
        }
    }

    /// The group named `name`.
    pub fn group_mut(&mut self, name: &str) -> &mut Group {
        self.groups.iter_mut().find(|g| g.name == name).unwrap_or_else(|| panic!("no group {name}"))
    }

    /// Start a step: t ← t + 1 (bias corrections use the new t).
    pub fn begin_step(&mut self) {
        self.t += 1;
    }

    /// Update `params` of group `g` with `grads` (same length as the group).
    pub fn update(&mut self, g: usize, params: &mut [f32], grads: &[f32]) {
        let t = self.t.max(1) as i32;
        let group = &mut self.groups[g];
        assert_eq!(params.len(), group.m.len(), "group {}: parameter length", group.name);
        assert_eq!(grads.len(), group.m.len(), "group {}: gradient length", group.name);
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        let lr = group.lr;
        const CHUNK: usize = 1 << 14;
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks(CHUNK))
            .zip(group.m.par_chunks_mut(CHUNK).zip(group.v.par_chunks_mut(CHUNK)))
            .for_each(|((p, g), (m, v))| {
                for i in 0..p.len() {
                    m[i] = BETA1 * m[i] + (1.0 - BETA1) * g[i];
                    v[i] = BETA2 * v[i] + (1.0 - BETA2) * g[i] * g[i];
                    p[i] -= lr * (m[i] / c1) / ((v[i] / c2).sqrt() + EPS);
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_steps_equal_the_closed_form() {
        let mut a = Adam::new(&[("x", 0.1, 2)]);
        let mut p = vec![1.0f32, -2.0];
        a.begin_step();
        a.update(0, &mut p, &[0.5, -3.0]);
        // t = 1: m̂ = g, v̂ = g², step = lr·g/|g| = ±lr
        assert!((p[0] - 0.9).abs() < 1e-6 && (p[1] + 1.9).abs() < 1e-6, "{p:?}");
        a.begin_step();
        a.update(0, &mut p, &[1.0, 0.0]);
        // t = 2 by hand in f64
        let (b1, b2) = (0.9f64, 0.999f64);
        for (k, (g1, g2, p1)) in [(0.5f64, 1.0f64, 0.9f64), (-3.0, 0.0, -1.9)].iter().enumerate() {
            let m = b1 * (1.0 - b1) * g1 + (1.0 - b1) * g2;
            let v = b2 * (1.0 - b2) * g1 * g1 + (1.0 - b2) * g2 * g2;
            let (mh, vh) = (m / (1.0 - b1 * b1), v / (1.0 - b2 * b2));
            let want = p1 - 0.1 * mh / (vh.sqrt() + 1e-15);
            assert!((p[k] as f64 - want).abs() < 1e-6, "{k}: {} vs {want}", p[k]);
        }
        assert_eq!(a.t, 2);
    }
}
