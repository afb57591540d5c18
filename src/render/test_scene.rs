//! Owned test scenes shared by the CPU renderer's tests and the GPU parity tests: random
//! clouds (optionally with SH colours and feature channels), the fuzzed inputs (NaN, Inf,
//! zero quaternions, huge scales, behind the camera), the settings and the tilted camera.

use glam::Mat4;

use super::synthetic::{Cloud, camera, cloud};
use super::*;
use crate::util::rng::Rng;

/// Owned inputs of a test scene.
#[derive(Debug, Clone)]
pub(crate) struct Scene {
    pub(crate) means: Vec<[f32; 3]>,
    pub(crate) quats: Vec<[f32; 4]>,
    pub(crate) scales: Vec<[f32; 3]>,
    pub(crate) opacities: Vec<f32>,
    pub(crate) dc: Vec<[f32; 3]>,
    pub(crate) rest: Vec<f32>,
    pub(crate) degree: u8,
    pub(crate) frame: Option<ShFrame>,
    pub(crate) features: Vec<f32>,
    pub(crate) nf: usize,
}

impl Scene {
    /// RGB colours, no features.
    pub(crate) fn from_cloud(c: Cloud) -> Scene {
        Scene {
            means: c.means,
            quats: c.quats,
            scales: c.scales,
            opacities: c.opacities,
            dc: c.colors,
            rest: Vec::new(),
            degree: 0,
            frame: None,
            features: Vec::new(),
            nf: 0,
        }
    }

    /// A seeded random cloud; with `frame`, degree-3 SH in that frame and two features.
    pub(crate) fn new(
        cam: &RenderCamera,
        n: usize,
        complexity: f32,
        seed: u64,
        frame: Option<ShFrame>,
    ) -> Scene {
        let mut s = Scene::from_cloud(cloud(cam, n, complexity, seed));
        let Some(frame) = frame else { return s };
        let mut rng = Rng::from_state(seed ^ 0x5eed);
        (s.degree, s.nf, s.frame) = (3, 2, Some(frame));
        let k3 = 3 * (sh::num_basis(3) - 1);
        s.rest = (0..n * k3).map(|_| rng.range_f32(-0.3, 0.3)).collect();
        s.features = (0..n * 2).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        s
    }

    /// The poisoned scene of the fuzz tests on a 32x24 camera: Gaussians 0-9 must be culled
    /// (NaN / Inf mean, zero / NaN quaternion, huge / Inf scale, behind the camera, NaN
    /// opacity, huge position, negative opacity); 10-12 are rendered without poisoning the
    /// image (zero scale, NaN colour, a huge but finite scale covering every tile).
    pub(crate) fn fuzzed() -> (RenderCamera, Scene) {
        let cam = camera(32, 24);
        let mut s = Scene::from_cloud(cloud(&cam, 20, 5.0, 5));
        let (nan, inf) = (f32::NAN, f32::INFINITY);
        s.means[0][1] = nan;
        s.means[1][2] = inf;
        s.quats[2] = [0.0; 4];
        s.quats[3][2] = nan;
        s.scales[4] = [1e25; 3];
        s.scales[5][0] = inf;
        s.means[6][2] = -3.0;
        s.opacities[7] = nan;
        s.means[8] = [1e30, -1e30, 1e30];
        s.opacities[9] = -0.5;
        s.scales[10] = [0.0; 3];
        s.dc[11] = [nan, inf, -inf];
        s.scales[12] = [1e5; 3];
        (cam, s)
    }

    pub(crate) fn inputs(&self) -> SplatInputs<'_> {
        let colors = match self.frame {
            None => ColorSource::Rgb(&self.dc),
            Some(frame) => {
                ColorSource::Sh { degree: self.degree, dc: &self.dc, rest: &self.rest, frame }
            }
        };
        SplatInputs {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
            colors,
            features: &self.features,
            num_features: self.nf,
        }
    }
}

/// Render settings of the tests: a coloured background, the 3DGS alpha clamp.
pub(crate) fn settings() -> RenderSettings {
    RenderSettings { background: [0.2, 0.5, 0.9], alpha_max: 0.99 }
}

/// The `w`x`h` camera turned 0.1 rad about y and shifted off the origin.
pub(crate) fn tilted(w: u32, h: u32) -> RenderCamera {
    let w2c =
        Mat4::from_rotation_y(0.1) * Mat4::from_translation(glam::Vec3::new(0.05, -0.02, 0.1));
    RenderCamera { w2c, ..camera(w, h) }
}
