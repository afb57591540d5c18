//! Surface points of the posed mesh: area-uniform sampling
//! of (triangle, barycentric) points, and their position and local frame at any pose.
//!
//! A surface point is fixed on the mesh (triangle id + barycentrics), so following it
//! through the poses gives exact ground-truth tracks; the frame (tangent along the
//! triangle's first edge, bitangent, face normal) gives the oracle Gaussians' rotations.

use glam::{Mat3, Quat, Vec3};

use crate::util::rng::Rng;

/// A point fixed on the mesh surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// Triangle id.
    pub tri: u32,
    /// Barycentric coordinates.
    pub b: [f32; 3],
}

fn tri_area(pos: &[Vec3], t: &[u32; 3]) -> f64 {
    let [a, b, c] = t.map(|i| pos[i as usize].as_dvec3());
    0.5 * (b - a).cross(c - a).length()
}

/// Total area of triangles `tris` `[F, 3]` over positions `pos` `[V]`.
pub fn total_area(pos: &[Vec3], tris: &[[u32; 3]]) -> f64 {
    tris.iter().map(|t| tri_area(pos, t)).sum()
}

/// `n` points uniform by area over the surface, drawn from `rng` (empty for zero area).
pub fn sample_surface(
    pos: &[Vec3],
    tris: &[[u32; 3]],
    n: usize,
    rng: &mut Rng,
) -> Vec<SurfacePoint> {
    let mut cdf = Vec::with_capacity(tris.len());
    let mut acc = 0.0;
    for t in tris {
        acc += tri_area(pos, t);
        cdf.push(acc);
    }
    if acc.is_nan() || acc <= 0.0 {
        return Vec::new();
    }
    (0..n)
        .map(|_| {
            let u = rng.uniform() * acc;
            let tri = cdf.partition_point(|&c| c <= u).min(tris.len() - 1);
            let r1 = rng.uniform().sqrt();
            let r2 = rng.uniform();
            let b = [1.0 - r1, r1 * (1.0 - r2), r1 * r2].map(|x| x as f32);
            SurfacePoint { tri: tri as u32, b }
        })
        .collect()
}

/// World position of `s`.
pub fn position(pos: &[Vec3], tris: &[[u32; 3]], s: &SurfacePoint) -> Vec3 {
    let [a, b, c] = tris[s.tri as usize].map(|i| pos[i as usize]);
    a * s.b[0] + b * s.b[1] + c * s.b[2]
}

/// Rotation (local-to-world) of the surface frame at `s`: columns tangent (first edge
/// direction), bitangent, face normal. Identity for a degenerate triangle.
pub fn frame(pos: &[Vec3], tris: &[[u32; 3]], s: &SurfacePoint) -> Quat {
    let [a, b, c] = tris[s.tri as usize].map(|i| pos[i as usize]);
    let n = (b - a).cross(c - a);
    let e = b - a;
    if !n.is_finite() || n.length_squared() <= 0.0 || e.length_squared() <= 0.0 {
        return Quat::IDENTITY;
    }
    let n = n.normalize();
    let t = e.normalize();
    let bt = n.cross(t);
    Quat::from_mat3(&Mat3::from_cols(t, bt, n)).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_uniform_and_frames() {
        // Two triangles, the second with three times the area.
        let pos = [
            Vec3::ZERO,
            Vec3::X,
            Vec3::Y,
            Vec3::new(3.0, 0.0, 0.0),
            Vec3::new(3.0, 0.0, 0.0) + Vec3::X * 3.0,
            Vec3::new(3.0, 1.0, 0.0),
        ];
        let tris = [[0, 1, 2], [3, 4, 5]];
        let s = sample_surface(&pos, &tris, 4000, &mut Rng::from_state(7).after(1));
        let second = s.iter().filter(|p| p.tri == 1).count();
        assert!((second as f64 / 4000.0 - 0.75).abs() < 0.03, "{second}");
        assert!(
            s.iter()
                .all(|p| p.b.iter().all(|&x| x >= 0.0)
                    && (p.b.iter().sum::<f32>() - 1.0).abs() < 1e-5)
        );
        assert_eq!(s, sample_surface(&pos, &tris, 4000, &mut Rng::from_state(7).after(1)));
        let q = frame(&pos, &tris, &s[0]);
        assert!((q * Vec3::Z).abs_diff_eq(Vec3::Z, 1e-6));
        assert!((q * Vec3::X).abs_diff_eq(Vec3::X, 1e-6));
    }
}
