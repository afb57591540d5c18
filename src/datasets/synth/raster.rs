//! CPU triangle rasterizer of the benchmark: z-buffer with supersampling, perspective-correct
//! barycentrics, then a resolve pass that shades covered samples and averages them per pixel.
//!
//! Stages: [`rasterize`] projects the world-space triangles `[F, 3]` (pinhole, OpenCV axes)
//! onto an `ss×` finer sample grid `[H·ss, W·ss]` and keeps, per sample, the nearest
//! triangle's z-depth, id and perspective-correct barycentrics; rayon maps one task to a band
//! of [`BAND`] sample rows, each band testing every triangle whose bounding box meets it, so
//! a sample is written by one task only. [`resolve`] maps one task to one pixel row: colour =
//! mean linear colour of the covered samples (then sRGB), alpha = covered fraction, z-depth
//! = nearest covered sample where alpha > 0.5 (else 0), mask = foreground coverage > 0.5. Sample centres
//! sit at `(i + 0.5) / ss` pixels; pixel centres at +0.5. Triangles with a vertex closer than
//! [`NEAR`] to the camera plane are dropped (no clipping).

use glam::{Mat4, Vec2, Vec3};
use rayon::prelude::*;

use crate::formats::png::Image;
use crate::scene::Camera;

/// Sample rows per rayon task.
pub const BAND: usize = 16;
/// Nearest z-depth a triangle vertex may have, world units.
pub const NEAR: f32 = 1e-3;

/// A pinhole view in f32.
#[derive(Debug, Clone, Copy)]
pub struct View {
    /// Focal lengths and principal point, pixels.
    pub fx: f32,
    /// Focal length y.
    pub fy: f32,
    /// Principal point x.
    pub cx: f32,
    /// Principal point y.
    pub cy: f32,
    /// Image width W, pixels.
    pub width: usize,
    /// Image height H, pixels.
    pub height: usize,
    /// World-to-camera, OpenCV axes.
    pub w2c: Mat4,
}

impl View {
    /// The view of a scene camera (distortion is ignored).
    pub fn of(c: &Camera) -> View {
        View {
            fx: c.pinhole.fx as f32,
            fy: c.pinhole.fy as f32,
            cx: c.pinhole.cx as f32,
            cy: c.pinhole.cy as f32,
            width: c.pinhole.width as usize,
            height: c.pinhole.height as usize,
            w2c: c.w2c_mat().as_mat4(),
        }
    }

    /// Pixel coordinates and z-depth of world point `p`; `None` behind [`NEAR`].
    pub fn project(&self, p: Vec3) -> Option<(Vec2, f32)> {
        let c = self.w2c.transform_point3(p);
        (c.z >= NEAR)
            .then(|| (Vec2::new(self.fx * c.x / c.z + self.cx, self.fy * c.y / c.z + self.cy), c.z))
    }
}

/// One z-buffer sample: nearest triangle, its z-depth and barycentrics `(1 - b1 - b2, b1, b2)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// z-depth, world units (`INFINITY` when empty).
    pub z: f32,
    /// Triangle id (`u32::MAX` when empty).
    pub tri: u32,
    /// Perspective-correct barycentric of vertex 1.
    pub b1: f32,
    /// Perspective-correct barycentric of vertex 2.
    pub b2: f32,
}

impl Sample {
    /// The empty sample.
    pub const EMPTY: Sample = Sample { z: f32::INFINITY, tri: u32::MAX, b1: 0.0, b2: 0.0 };

    /// Whether a triangle covers this sample.
    pub fn covered(&self) -> bool {
        self.tri != u32::MAX
    }
}

/// The supersampled z-buffer `[H·ss, W·ss]` of one view.
#[derive(Debug, Clone)]
pub struct Samples {
    /// Samples per pixel side.
    pub ss: usize,
    /// Width in samples (W·ss).
    pub width: usize,
    /// Height in samples (H·ss).
    pub height: usize,
    /// Row-major samples.
    pub data: Vec<Sample>,
}

struct Prepared {
    tri: u32,
    v: [Vec2; 3],
    inv_z: [f32; 3],
    inv_area: f32,
    lo: Vec2,
    hi: Vec2,
}

fn edge(a: Vec2, b: Vec2, p: Vec2) -> f32 {
    (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
}

/// Rasterize triangles `tris` `[F, 3]` over world positions `pos` `[V]` in `view` at `ss`×`ss`
/// samples per pixel.
pub fn rasterize(view: &View, ss: usize, pos: &[Vec3], tris: &[[u32; 3]]) -> Samples {
    let (sw, sh) = (view.width * ss, view.height * ss);
    let s = ss as f32;
    let proj: Vec<Option<(Vec2, f32)>> =
        pos.par_iter().map(|p| view.project(*p).map(|(q, z)| (q * s, z))).collect();
    let prepared: Vec<Prepared> = tris
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            let [a, b, c] = [proj[t[0] as usize]?, proj[t[1] as usize]?, proj[t[2] as usize]?];
            let v = [a.0, b.0, c.0];
            let area = edge(v[0], v[1], v[2]);
            if area.abs() <= 1e-12 || !area.is_finite() {
                return None;
            }
            let lo = v[0].min(v[1]).min(v[2]);
            let hi = v[0].max(v[1]).max(v[2]);
            if hi.x < 0.0 || hi.y < 0.0 || lo.x > sw as f32 || lo.y > sh as f32 {
                return None;
            }
            Some(Prepared {
                tri: i as u32,
                v,
                inv_z: [1.0 / a.1, 1.0 / b.1, 1.0 / c.1],
                inv_area: 1.0 / area,
                lo,
                hi,
            })
        })
        .collect();
    let mut data = vec![Sample::EMPTY; sw * sh];
    data.par_chunks_mut(BAND * sw).enumerate().for_each(|(band, rows)| {
        let y0 = band * BAND;
        let y1 = y0 + rows.len() / sw;
        for t in &prepared {
            // Sample centres (i + 0.5) inside [lo, hi].
            let ya = ((t.lo.y - 0.5).ceil().max(y0 as f32)) as usize;
            let yb = ((t.hi.y - 0.5).floor() + 1.0).clamp(0.0, y1 as f32) as usize;
            let xa = (t.lo.x - 0.5).ceil().max(0.0) as usize;
            let xb = ((t.hi.x - 0.5).floor() + 1.0).clamp(0.0, sw as f32) as usize;
            if xa >= xb {
                continue;
            }
            // Normalised edge functions step by these per sample along x.
            let step = |a: Vec2, b: Vec2| -(b.y - a.y) * t.inv_area;
            let (d0, d1, d2) = (step(t.v[1], t.v[2]), step(t.v[2], t.v[0]), step(t.v[0], t.v[1]));
            for y in ya..yb {
                let row = &mut rows[(y - y0) * sw..(y - y0 + 1) * sw];
                let p = Vec2::new(xa as f32 + 0.5, y as f32 + 0.5);
                let e0 = edge(t.v[1], t.v[2], p) * t.inv_area;
                let e1 = edge(t.v[2], t.v[0], p) * t.inv_area;
                let e2 = edge(t.v[0], t.v[1], p) * t.inv_area;
                for x in xa..xb {
                    let k = (x - xa) as f32;
                    let (l0, l1, l2) = (e0 + k * d0, e1 + k * d1, e2 + k * d2);
                    if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                        continue;
                    }
                    let (q0, q1, q2) = (l0 * t.inv_z[0], l1 * t.inv_z[1], l2 * t.inv_z[2]);
                    let z = 1.0 / (q0 + q1 + q2);
                    let s = &mut row[x];
                    if z < s.z {
                        *s = Sample { z, tri: t.tri, b1: q1 * z, b2: q2 * z };
                    }
                }
            }
        }
    });
    Samples { ss, width: sw, height: sh, data }
}

/// The images of one view.
#[derive(Debug, Clone)]
pub struct Resolved {
    /// RGBA `[H, W, 4]`: sRGB/255 colour of the covered part, alpha = coverage.
    pub rgba: Image,
    /// Mask `[H, W, 1]`: 1 where the coverage by foreground triangles (ids below the
    /// `foreground` of [`resolve`]) is > 0.5.
    pub mask: Image,
    /// z-depth `[H, W]`, world units, 0 where coverage ≤ 0.5.
    pub depth: Vec<f32>,
}

/// Shade and average the samples per pixel; `shade(tri, barycentrics)` gives linear RGB.
/// Triangles with ids from `foreground` on (a static ground plane) are background: in the
/// colour, alpha and depth, not in the mask.
pub fn resolve(
    s: &Samples,
    shade: &(dyn Fn(u32, [f32; 3]) -> Vec3 + Sync),
    foreground: u32,
) -> Resolved {
    let (w, h, ss) = (s.width / s.ss, s.height / s.ss, s.ss);
    let mut rgba = Image::filled(w, h, 4, 0.0);
    let mut mask = Image::filled(w, h, 1, 0.0);
    let mut depth = vec![0f32; w * h];
    rgba.data
        .par_chunks_mut(w * 4)
        .zip(mask.data.par_chunks_mut(w))
        .zip(depth.par_chunks_mut(w))
        .enumerate()
        .for_each(|(py, ((rgba_row, mask_row), depth_row))| {
            for px in 0..w {
                let (mut sum, mut n, mut zmin) = (Vec3::ZERO, 0usize, f32::INFINITY);
                let mut n_fg = 0usize;
                for sy in 0..ss {
                    let row = (py * ss + sy) * s.width + px * ss;
                    for smp in &s.data[row..row + ss] {
                        if smp.covered() {
                            sum += shade(smp.tri, [1.0 - smp.b1 - smp.b2, smp.b1, smp.b2]);
                            n += 1;
                            n_fg += usize::from(smp.tri < foreground);
                            zmin = zmin.min(smp.z);
                        }
                    }
                }
                if n == 0 {
                    continue;
                }
                let c = sum / n as f32;
                let alpha = n as f32 / (ss * ss) as f32;
                let o = &mut rgba_row[px * 4..px * 4 + 4];
                o[0] = super::shade::linear_to_srgb(c.x);
                o[1] = super::shade::linear_to_srgb(c.y);
                o[2] = super::shade::linear_to_srgb(c.z);
                o[3] = alpha;
                if alpha > 0.5 {
                    depth_row[px] = zmin;
                }
                if n_fg * 2 > ss * ss {
                    mask_row[px] = 1.0;
                }
            }
        });
    Resolved { rgba, mask, depth }
}

/// Relative z tolerance of the visibility test (0.5 % of the point's depth).
pub const VIS_TOL: f32 = 5e-3;

/// Whether world point `p` on triangle `tri` is visible in the view whose z-buffer is `s`:
/// inside the image, and either the sample nearest its projection lies no nearer than `p`
/// (within [`VIS_TOL`]; empty samples are infinitely far) or some sample of the 3×3
/// neighbourhood holds `tri` itself. Returns the pixel position too
/// (`None` when behind the camera).
pub fn visibility(view: &View, s: &Samples, p: Vec3, tri: u32) -> Option<(Vec2, bool)> {
    let (q, z) = view.project(p)?;
    if q.x < 0.0 || q.y < 0.0 || q.x >= view.width as f32 || q.y >= view.height as f32 {
        return Some((q, false));
    }
    let (sx, sy) = ((q.x * s.ss as f32) as isize, (q.y * s.ss as f32) as isize);
    let at = |x: isize, y: isize| {
        s.data[y.clamp(0, s.height as isize - 1) as usize * s.width
            + x.clamp(0, s.width as isize - 1) as usize]
    };
    let mut vis = z <= at(sx, sy).z * (1.0 + VIS_TOL);
    for dy in -1..=1 {
        for dx in -1..=1 {
            let (x, y) = (sx + dx, sy + dy);
            if x < 0 || y < 0 || x >= s.width as isize || y >= s.height as isize {
                continue;
            }
            let smp = s.data[y as usize * s.width + x as usize];
            vis |= smp.tri == tri;
        }
    }
    Some((q, vis))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(n: usize) -> View {
        View {
            fx: n as f32,
            fy: n as f32,
            cx: n as f32 / 2.0,
            cy: n as f32 / 2.0,
            width: n,
            height: n,
            w2c: Mat4::IDENTITY,
        }
    }

    #[test]
    fn triangle_coverage_and_depth() {
        // A right triangle at z = 2 covering the lower-left half of the square x, y ∈ [0, 1]
        // in normalised coordinates → pixels 8..16 of a 16-pixel image with f = 16, c = 8.
        let v = view(16);
        let pos = [Vec3::new(0.0, 0.0, 2.0), Vec3::new(1.0, 0.0, 2.0), Vec3::new(0.0, 1.0, 2.0)];
        let s = rasterize(&v, 2, &pos, &[[0, 1, 2]]);
        let r = resolve(&s, &|_, _| Vec3::ONE, u32::MAX);
        let covered: usize = s.data.iter().filter(|x| x.covered()).count();
        // Half of an 8×8 pixel square = 16×16 samples / 2 (+ the diagonal's samples).
        assert!((covered as i64 - 128).abs() <= 16, "{covered}");
        assert_eq!(r.mask.at(9, 9, 0), 1.0);
        assert_eq!(r.depth[9 * 16 + 9], 2.0);
        assert_eq!(r.mask.at(4, 4, 0), 0.0);
        assert_eq!(r.depth[4 * 16 + 4], 0.0);
        assert_eq!(r.rgba.at(9, 9, 3), 1.0);
        // A pixel on the hypotenuse is partly covered.
        let a = r.rgba.at(11, 12, 3);
        assert!(a > 0.0 && a < 1.0, "{a}");
        // A nearer triangle wins the z-test.
        let near: Vec<Vec3> = pos.iter().map(|p| Vec3::new(p.x * 0.5, p.y * 0.5, 1.0)).collect();
        let all: Vec<Vec3> = pos.iter().chain(&near).copied().collect();
        let s = rasterize(&v, 2, &all, &[[0, 1, 2], [3, 4, 5]]);
        let c = s.data[(9 * 2) * s.width + 9 * 2];
        assert_eq!((c.tri, c.z), (1, 1.0));
    }

    #[test]
    fn perspective_correct_barycentrics() {
        // A slanted triangle: vertices at depths 1, 3 and 3. Barycentrics of the sample
        // nearest a known 3D point must match the point's 3D barycentrics, not screen ones.
        let v = view(64);
        let pos =
            [Vec3::new(-0.5, -0.5, 1.0), Vec3::new(1.5, -1.5, 3.0), Vec3::new(-1.5, 1.5, 3.0)];
        let s = rasterize(&v, 1, &pos, &[[0, 1, 2]]);
        let b = [0.5f32, 0.25, 0.25];
        let p = pos[0] * b[0] + pos[1] * b[1] + pos[2] * b[2];
        let (q, z) = v.project(p).unwrap();
        let smp = s.data[q.y as usize * s.width + q.x as usize];
        assert_eq!(smp.tri, 0);
        assert!((smp.b1 - b[1]).abs() < 0.03 && (smp.b2 - b[2]).abs() < 0.03, "{smp:?}");
        assert!((smp.z - z).abs() < 0.05);
        // Screen-space (affine) barycentrics would be far off: the point projects at 1/z
        // weights 0.5/1, 0.25/3, 0.25/3.
        let screen_b1 = (0.25 / 3.0) / (0.5 + 0.5 / 3.0);
        assert!((screen_b1 - b[1]).abs() > 0.1);
    }

    #[test]
    fn visibility_by_depth_test() {
        let v = view(32);
        let front =
            [Vec3::new(-0.25, -0.25, 1.0), Vec3::new(0.25, -0.25, 1.0), Vec3::new(0.0, 0.25, 1.0)];
        let back =
            [Vec3::new(-6.0, -6.0, 3.0), Vec3::new(6.0, -6.0, 3.0), Vec3::new(0.0, 6.0, 3.0)];
        let pos: Vec<Vec3> = front.iter().chain(&back).copied().collect();
        let s = rasterize(&v, 2, &pos, &[[0, 1, 2], [3, 4, 5]]);
        // Behind the front triangle the back one is hidden; beside it, it is visible.
        assert_eq!(visibility(&v, &s, Vec3::new(0.0, -0.3, 3.0), 1).map(|x| x.1), Some(false));
        assert_eq!(visibility(&v, &s, Vec3::new(1.2, 1.2, 3.0), 1).map(|x| x.1), Some(true));
        assert_eq!(
            visibility(&v, &s, (front[0] + front[1] + front[2]) / 3.0, 0).map(|x| x.1),
            Some(true)
        );
        assert_eq!(visibility(&v, &s, Vec3::new(0.0, 0.0, -1.0), 0), None);
    }
}
