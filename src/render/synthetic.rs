//! Seeded synthetic Gaussian clouds for tests and `usplat4d bench render`: random Gaussians
//! in front of a pinhole camera, sized so that their footprints cover the image a chosen
//! number of times ("depth complexity").

use glam::Mat4;

use super::{ColorSource, RenderCamera, SplatInputs};
use crate::util::rng::Rng;

/// A random cloud of N Gaussians with RGB colours, `[N]` each.
#[derive(Debug, Clone, Default)]
pub struct Cloud {
    /// Positions.
    pub means: Vec<[f32; 3]>,
    /// Unit quaternions w, x, y, z.
    pub quats: Vec<[f32; 4]>,
    /// Scales.
    pub scales: Vec<[f32; 3]>,
    /// Opacities.
    pub opacities: Vec<f32>,
    /// RGB colours.
    pub colors: Vec<[f32; 3]>,
}

impl Cloud {
    /// The renderer inputs of the cloud (RGB colours, no features).
    pub fn inputs(&self) -> SplatInputs<'_> {
        SplatInputs {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
            colors: ColorSource::Rgb(&self.colors),
            features: &[],
            num_features: 0,
        }
    }
}

/// A camera at the origin looking down +z, focal length `0.8·width`.
pub fn camera(width: u32, height: u32) -> RenderCamera {
    let f = 0.8 * width as f32;
    RenderCamera {
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        w2c: Mat4::IDENTITY,
        width,
        height,
        near: 0.01,
        far: 1e4,
    }
}

/// `n` Gaussians uniformly spread over the view of `cam` at depths 2..6, with random
/// rotations, anisotropic scales, opacities in [0.3, 1] and colours, sized so that their 3σ
/// discs cover the image about `depth_complexity` times.
pub fn cloud(cam: &RenderCamera, n: usize, depth_complexity: f32, seed: u64) -> Cloud {
    let mut rng = Rng::from_state(seed);
    let (w, h) = (cam.width as f32, cam.height as f32);
    let sigma_px =
        (depth_complexity * w * h / (n.max(1) as f32 * std::f32::consts::PI * 9.0)).sqrt();
    let mut c = Cloud::default();
    for _ in 0..n {
        let z = rng.range_f32(2.0, 6.0);
        let (u, v) = (rng.range_f32(-0.05, 1.05) * w, rng.range_f32(-0.05, 1.05) * h);
        c.means.push([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z]);
        let q = [rng.normal_f32(), rng.normal_f32(), rng.normal_f32(), rng.normal_f32()];
        let norm = q.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        c.quats.push(q.map(|x| x / norm));
        let base = sigma_px * z / cam.fx;
        c.scales.push(std::array::from_fn(|_| base * (0.4 * rng.normal_f32()).exp()));
        c.opacities.push(rng.range_f32(0.3, 1.0));
        c.colors.push([rng.uniform_f32(), rng.uniform_f32(), rng.uniform_f32()]);
    }
    c
}
