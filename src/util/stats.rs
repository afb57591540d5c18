//! Order statistics.

/// Linear-interpolation quantile `q` in [0, 1] of `v` (reorders `v`).
pub fn quantile(v: &mut [f32], q: f64) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let pos = q * (v.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    let a = *v.select_nth_unstable_by(lo, f32::total_cmp).1;
    let b =
        if hi == lo { a } else { *v[lo + 1..].iter().min_by(|x, y| x.total_cmp(y)).unwrap_or(&a) };
    (a as f64 + (b as f64 - a as f64) * (pos - lo as f64)) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantile_interpolates_between_order_statistics() {
        let mut v = vec![4.0, 1.0, 3.0, 2.0, 5.0];
        assert_eq!(quantile(&mut v, 0.0), 1.0);
        assert_eq!(quantile(&mut v, 1.0), 5.0);
        assert_eq!(quantile(&mut v, 0.5), 3.0);
        assert_eq!(quantile(&mut v, 0.625), 3.5);
        assert_eq!(quantile(&mut [], 0.5), 0.0);
    }
}
