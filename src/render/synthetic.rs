//! Seeded synthetic Gaussian clouds for tests and `usplat4d bench render`: random Gaussians
//! in front of a pinhole camera, sized so that their footprints cover the image a chosen
//! number of times ("depth complexity").

use glam::Mat4;

use super::RenderCamera;

/// SplitMix64: a tiny seeded generator (deterministic across platforms).
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.uniform().max(1e-7);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

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
    let mut rng = SplitMix64::new(seed);
    let (w, h) = (cam.width as f32, cam.height as f32);
    let sigma_px =
        (depth_complexity * w * h / (n.max(1) as f32 * std::f32::consts::PI * 9.0)).sqrt();
    let mut c = Cloud::default();
    for _ in 0..n {
        let z = rng.range(2.0, 6.0);
        let (u, v) = (rng.range(-0.05, 1.05) * w, rng.range(-0.05, 1.05) * h);
        c.means.push([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z]);
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let norm = q.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
        c.quats.push(q.map(|x| x / norm));
        let base = sigma_px * z / cam.fx;
        c.scales.push(std::array::from_fn(|_| base * (0.4 * rng.normal()).exp()));
        c.opacities.push(rng.range(0.3, 1.0));
        c.colors.push([rng.uniform(), rng.uniform(), rng.uniform()]);
    }
    c
}
