//! The mask term of L_rgb: Shape of Motion's `mse(acc, masks)` (its foreground-only model,
//! `w_mask` = 1), the mean over pixels of (α − m)² between the rendered accumulated opacity
//! and the scene's foreground mask, with its gradient w.r.t. α. The release trains with a
//! mask weight of 0.

/// Mean of (α − m)² over `[H, W]` pixels; with `grad = Some((g, scale))` adds
/// `scale · dL/dα = scale · 2(α − m)/(H·W)` to `g` (`[H, W]`). Zero for an empty image.
pub fn alpha_mask_with_grad(alpha: &[f32], mask: &[f32], grad: Option<(&mut [f32], f64)>) -> f64 {
    assert_eq!(alpha.len(), mask.len(), "alpha and mask differ in size");
    if alpha.is_empty() {
        return 0.0;
    }
    let inv_n = 1.0 / alpha.len() as f64;
    let sum: f64 = alpha.iter().zip(mask).map(|(a, m)| (*a as f64 - *m as f64).powi(2)).sum();
    if let Some((g, scale)) = grad {
        for ((g, a), m) in g.iter_mut().zip(alpha).zip(mask) {
            *g += (scale * 2.0 * (*a as f64 - *m as f64) * inv_n) as f32;
        }
    }
    sum * inv_n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::optimize::image_loss::fd::{Check, noise};

    #[test]
    fn mask_gradient_matches_finite_differences() {
        let alpha = noise(9 * 7, 31);
        let mask: Vec<f32> = (0..9 * 7).map(|i| if i % 3 == 0 { 0.0 } else { 1.0 }).collect();
        let mut g = vec![0.0f32; alpha.len()];
        alpha_mask_with_grad(&alpha, &mask, Some((&mut g, 1.5)));
        let mut check = Check::new("mask", 1e-7, 1e-4);
        let loss = |a: &[f32]| 1.5 * alpha_mask_with_grad(a, &mask, None);
        check.image("alpha", &alpha, &g, 1.0 / 1024.0, loss, 1);
        check.finish();
    }

    #[test]
    fn perfect_alpha_costs_nothing() {
        let mask: Vec<f32> = (0..20).map(|i| (i % 2) as f32).collect();
        let mut g = vec![0.0f32; 20];
        assert_eq!(alpha_mask_with_grad(&mask, &mask, Some((&mut g, 1.0))), 0.0);
        assert!(g.iter().all(|v| *v == 0.0));
    }
}
