//! A hand-made scene and model for tests and demos (`usplat4d render` on something small).

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3};

use crate::model::{FrameState, Gaussians, Model};
use crate::scene::{Camera, Pinhole, Scene, Split};
use crate::tables::{self, Provenance};

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
            let pinhole = Pinhole::centred(60.0, 80, 60, Camera::w2c_from_mat(w2c));
            cameras.push(Camera {
                angle_offset_deg: Some(angle as f32),
                ..Camera::new(frame, name, split, pinhole)
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
