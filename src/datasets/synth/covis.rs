//! Covisibility masks of evaluation views from ground truth (DyCheck's protocol): an eval
//! pixel is covisible when its surface point is visible in at least `max(5, 0.1·T)` of the
//! T training frames.
//!
//! Approximation: only every `stride`-th training frame is tested (at most
//! [`MAX_TESTED_FRAMES`]), with the threshold scaled by the tested fraction (rounded up,
//! clamped to the tested count). The pixel's surface point is the first covered sample of
//! the pixel; visibility is [`raster::visibility`] against a pixel-resolution z-buffer of
//! each tested training frame (the first covered sample of each pixel).

use glam::Vec3;
use rayon::prelude::*;

use super::raster::{self, Sample, Samples, View};
use super::surface::{self, SurfacePoint};
use crate::formats::png::Image;

/// Most training frames kept for the covisibility test.
pub const MAX_TESTED_FRAMES: usize = 24;

struct Tested {
    view: View,
    pos: Vec<Vec3>,
    pixels: Samples,
}

/// Training-frame z-buffers collected for covisibility.
pub struct Covis {
    stride: usize,
    num_train: usize,
    tested: Vec<Tested>,
}

/// First covered sample of each pixel, as a one-sample-per-pixel buffer `[H, W]`.
fn per_pixel(s: &Samples) -> Samples {
    let (w, h) = (s.width / s.ss, s.height / s.ss);
    let data = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (px, py) = (i % w, i / w);
            let mut covered = (0..s.ss * s.ss)
                .map(|k| s.data[(py * s.ss + k / s.ss) * s.width + px * s.ss + k % s.ss]);
            let n = covered.clone().filter(Sample::covered).count();
            if 2 * n > s.ss * s.ss {
                covered.find(Sample::covered).unwrap_or(Sample::EMPTY)
            } else {
                Sample::EMPTY
            }
        })
        .collect();
    Samples { ss: 1, width: w, height: h, data }
}

impl Covis {
    /// Collector for a training video of `num_train` frames.
    pub fn new(num_train: usize) -> Self {
        Covis {
            stride: num_train.div_ceil(MAX_TESTED_FRAMES).max(1),
            num_train,
            tested: Vec::new(),
        }
    }

    /// Whether training frame `frame` is tested.
    pub fn wants(&self, frame: u32) -> bool {
        (frame as usize).is_multiple_of(self.stride)
    }

    /// Keep training frame's view, world vertex positions `[V]` and z-buffer.
    pub fn keep(&mut self, view: View, pos: Vec<Vec3>, samples: &Samples) {
        self.tested.push(Tested { view, pos, pixels: per_pixel(samples) });
    }

    /// Visible-frame count an eval pixel needs.
    pub fn threshold(&self) -> usize {
        let required = 5.max((0.1 * self.num_train as f64).ceil() as usize) as f64;
        let n = self.tested.len();
        ((required * n as f64 / self.num_train.max(1) as f64).ceil() as usize).clamp(1, n.max(1))
    }

    /// Covisibility mask `[H, W, 1]` of an eval view with z-buffer `s`.
    pub fn mask(&self, s: &Samples, tris: &[[u32; 3]]) -> Image {
        let px = per_pixel(s);
        let need = self.threshold();
        let data = px
            .data
            .par_iter()
            .map(|smp| {
                if !smp.covered() {
                    return 0.0;
                }
                let sp = SurfacePoint { tri: smp.tri, b: [1.0 - smp.b1 - smp.b2, smp.b1, smp.b2] };
                let seen = self
                    .tested
                    .iter()
                    .filter(|t| {
                        let p = surface::position(&t.pos, tris, &sp);
                        raster::visibility(&t.view, &t.pixels, p, sp.tri).is_some_and(|v| v.1)
                    })
                    .count();
                if seen >= need { 1.0 } else { 0.0 }
            })
            .collect();
        Image { width: px.width, height: px.height, channels: 1, data }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_marks_points_hidden_in_training() {
        // Training camera at the origin looking down +z: a small front triangle at z = 1
        // hides the centre of a large back triangle at z = 3. The eval camera looks back
        // from z = 4 and sees only the back triangle.
        let pos = vec![
            Vec3::new(-0.25, -0.25, 1.0),
            Vec3::new(0.25, -0.25, 1.0),
            Vec3::new(0.0, 0.25, 1.0),
            Vec3::new(-6.0, -6.0, 3.0),
            Vec3::new(6.0, -6.0, 3.0),
            Vec3::new(0.0, 6.0, 3.0),
        ];
        let tris = [[0, 1, 2], [3, 4, 5]];
        let view =
            |w2c| View { fx: 32.0, fy: 32.0, cx: 16.0, cy: 16.0, width: 32, height: 32, w2c };
        let train = view(glam::Mat4::IDENTITY);
        let back = glam::Mat4::from_scale(Vec3::new(-1.0, 1.0, -1.0))
            * glam::Mat4::from_translation(Vec3::new(0.0, 0.0, -4.0));
        let eval = view(back);
        let mut c = Covis::new(1);
        c.keep(train, pos.clone(), &raster::rasterize(&train, 2, &pos, &tris));
        let m = c.mask(&raster::rasterize(&eval, 2, &pos, &tris), &tris);
        // Centre: hidden behind the front triangle in training. Corner (0.4, 0.4) in the
        // eval view is world (-0.4, 0.4, 3), beside the front triangle: seen in training.
        assert_eq!(m.at(16, 16, 0), 0.0);
        assert_eq!(m.at(28, 28, 0), 1.0);
    }

    #[test]
    fn threshold_scales_with_tested_frames() {
        let mut c = Covis::new(240);
        assert_eq!(c.stride, 10);
        assert!(c.wants(20) && !c.wants(21));
        let v = View {
            fx: 1.0,
            fy: 1.0,
            cx: 0.0,
            cy: 0.0,
            width: 1,
            height: 1,
            w2c: glam::Mat4::IDENTITY,
        };
        let s = Samples { ss: 1, width: 1, height: 1, data: vec![Sample::EMPTY] };
        for _ in 0..24 {
            c.keep(v, Vec::new(), &s);
        }
        // max(5, 24) = 24 of 240 frames → 24 · 24 / 240 = 2.4 → 3 of the 24 tested.
        assert_eq!(c.threshold(), 3);
    }
}
