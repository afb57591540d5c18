//! Seeded synthetic Gaussian clouds for tests and `usplat4d bench render`: random Gaussians
//! in front of a pinhole camera, sized so that their footprints cover the image a chosen
//! number of times ("depth complexity"), and a tiny hand-made scene + model directory.

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3, Mat4};

use super::RenderCamera;
use crate::model::{FrameState, Gaussians, Model};
use crate::scene::{Camera, Scene, Split};
use crate::tables::{self, Provenance};

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

/// Write a hand-made scene and model for tests and demos into `dir/scene` and `dir/model`:
/// a textured plane of 24x24 Gaussians rotating 0.2 rad per frame about the view axis, seen
/// by a train camera `cam00` and an eval camera `cam01` 20° to the side (80x60 pixels), over
/// `frames` frames. Returns `(scene_dir, model_dir)`.
pub fn write_demo_scene(dir: &Path, frames: u32) -> tables::Result<(PathBuf, PathBuf)> {
    let (scene_dir, model_dir) = (dir.join("scene"), dir.join("model"));
    let mut cameras = Vec::new();
    for frame in 0..frames {
        for (name, split, angle) in [("cam00", Split::Train, 0.0f64), ("cam01", Split::Eval, 20.0)]
        {
            let eye =
                DVec3::new(4.0 * angle.to_radians().sin(), 0.0, -4.0 * angle.to_radians().cos());
            // OpenCV axes: look at the origin, y down.
            let c2w_gl = DMat4::look_at_rh(eye, DVec3::ZERO, DVec3::NEG_Y).inverse();
            let w2c = (c2w_gl * DMat4::from_scale(DVec3::new(1.0, 1.0, -1.0))).inverse();
            cameras.push(Camera {
                frame,
                camera: name.into(),
                split,
                fx: 60.0,
                fy: 60.0,
                cx: 40.0,
                cy: 30.0,
                width: 80,
                height: 60,
                w2c: Camera::w2c_from_mat(w2c),
                image_path: format!("rgb/{name}/{frame:05}.png"),
                depth_path: None,
                mask_path: None,
                angle_offset_deg: Some(angle as f32),
                distortion: None,
            });
        }
    }
    let scene = Scene { dir: scene_dir.clone(), cameras };
    scene.save(&Provenance::new("demo", &()))?;
    let side = 24usize;
    let n = side * side;
    let mut g = Gaussians { sh_degree: 0, ..Gaussians::default() };
    let mut pos = Vec::new();
    for i in 0..n {
        let (u, v) = ((i % side) as f32 / side as f32, (i / side) as f32 / side as f32);
        g.id.push(i as u32);
        g.dynamic.push(true);
        g.scale.push([0.05, 0.05, 0.005]);
        g.opacity.push(0.9);
        let check = if ((i % side) / 4 + (i / side) / 4).is_multiple_of(2) { 1.0 } else { 0.3 };
        g.color.push([u * check, v * check, (1.0 - u) * check]);
        pos.push([2.0 * u - 1.0, 2.0 * v - 1.0, 0.0]);
    }
    let states = (0..frames).map(|t| {
        let a = 0.2 * t as f32;
        let q = [(a / 2.0).cos(), 0.0, 0.0, (a / 2.0).sin()];
        let rot = glam::Quat::from_rotation_z(a);
        let position = pos.iter().map(|p| (rot * glam::Vec3::from(*p)).into()).collect();
        Ok(FrameState { frame: t, position, rotation: vec![q; n] })
    });
    Model::save(&model_dir, &g, states, &Provenance::new("demo", &()))?;
    Ok((scene_dir, model_dir))
}
