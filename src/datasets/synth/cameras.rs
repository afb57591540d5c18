//! The camera protocol of the benchmark.
//!
//! Orbit protocol: the object is centred at the origin with a bounding-box diagonal of 2
//! (so it lies inside the unit sphere); C cameras at distance [`ORBIT_DISTANCE`] sit on a
//! circle at `elevation_deg` above the horizontal (glTF +Y up), camera k at azimuth
//! `360·k/C` degrees plus `deg_per_frame·t` at frame t (counter-clockwise seen from above;
//! azimuth 0 is on +Z), all looking at the origin with +Y up. Camera 0 (`cam00`) is the
//! training video, the others are evaluation views with `angle_offset_deg = 360·k/C`. The
//! focal length makes the unit sphere fill [`FILL`] of the smaller image half-size:
//! `f = FILL · min(W, H)/2 / tan(asin(1/ORBIT_DISTANCE))` (≈ 32.3° field of view across the
//! smaller side at the defaults).
//!
//! Trajectory protocol (`--trajectory dycheck:DIR`): the cameras of a real sequence; the
//! object is placed at the point closest (least squares) to all training optical axes, its
//! +Y along the cameras' mean up direction and its +Z facing the first training camera, and
//! scaled so its bounding sphere fills [`FILL`] of the smaller half-size at the mean
//! training distance. The path's lens distortion is dropped (the renderer is a pinhole), and
//! every camera of the path is rendered at its own frame's animation time.

use glam::{DMat3, DMat4, DVec3};

use crate::scene::{Camera, Pinhole, Split};

/// Distance of the orbit cameras from the object centre, world units (2× the bbox diagonal).
pub const ORBIT_DISTANCE: f64 = 4.0;
/// Fraction of the smaller image half-size the object's bounding sphere fills.
pub const FILL: f64 = 0.9;

/// World-to-camera (OpenCV axes: x right, y down, z forward) of a camera at `eye` looking at
/// `target` with world `up` pointing up in the image.
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> DMat4 {
    let z = (target - eye).normalize();
    let x = z.cross(up).normalize();
    let y = z.cross(x);
    let r = DMat3::from_cols(x, y, z).transpose();
    DMat4::from_mat3_translation(r, -(r * eye))
}

/// Focal length, pixels, of the orbit protocol.
pub fn orbit_focal(width: u32, height: u32) -> f64 {
    let half = (1.0 / ORBIT_DISTANCE).asin();
    FILL * 0.5 * width.min(height) as f64 / half.tan()
}

/// Image, depth and mask paths of `camera` at `frame`, relative to the scene directory.
pub fn paths(camera: &str, frame: u32) -> (String, String, String) {
    (
        format!("rgb/{camera}/{frame:05}.png"),
        format!("depth/{camera}/{frame:05}.npy"),
        format!("mask/{camera}/{frame:05}.png"),
    )
}

/// The orbit protocol's cameras, frame-major (`[T·C]`, camera k of frame t at `t·C + k`).
pub fn orbit(
    frames: u32,
    cameras: u32,
    deg_per_frame: f64,
    elevation_deg: f64,
    width: u32,
    height: u32,
) -> Vec<Camera> {
    let f = orbit_focal(width, height);
    let el = elevation_deg.to_radians();
    let mut out = Vec::with_capacity((frames * cameras) as usize);
    for t in 0..frames {
        for k in 0..cameras {
            let offset = 360.0 * k as f64 / cameras as f64;
            let az = (offset + deg_per_frame * t as f64).to_radians();
            let eye =
                ORBIT_DISTANCE * DVec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos());
            let name = format!("cam{k:02}");
            let (image_path, depth_path, mask_path) = paths(&name, t);
            out.push(Camera {
                frame: t,
                camera: name,
                split: if k == 0 { Split::Train } else { Split::Eval },
                pinhole: Pinhole {
                    fx: f,
                    fy: f,
                    cx: width as f64 / 2.0,
                    cy: height as f64 / 2.0,
                    width,
                    height,
                    w2c: Camera::w2c_from_mat(look_at(eye, DVec3::ZERO, DVec3::Y)),
                },
                image_path,
                depth_path: Some(depth_path),
                mask_path: Some(mask_path),
                angle_offset_deg: Some(offset as f32),
                distortion: None,
            });
        }
    }
    out
}

/// Similarity placing the normalised object (origin-centred, unit bounding sphere) in the
/// world: `world = origin + scale · rotation · p`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Placement {
    /// Object centre in the world.
    pub origin: DVec3,
    /// Object-to-world rotation.
    pub rotation: DMat3,
    /// World units per normalised unit.
    pub scale: f64,
}

impl Placement {
    /// The identity placement of the orbit protocol.
    pub const IDENTITY: Placement =
        Placement { origin: DVec3::ZERO, rotation: DMat3::IDENTITY, scale: 1.0 };

    /// The 4×4 matrix of this placement.
    pub fn matrix(&self) -> DMat4 {
        DMat4::from_translation(self.origin) * DMat4::from_mat3(self.rotation * self.scale)
    }
}

/// Placement of the object in front of a real camera path (see the module doc).
pub fn place_on_path(cams: &[Camera]) -> Placement {
    let train: Vec<&Camera> = cams.iter().filter(|c| c.split == Split::Train).collect();
    let train = if train.is_empty() { cams.iter().collect() } else { train };
    let (mut a, mut b, mut up) = (DMat3::ZERO, DVec3::ZERO, DVec3::ZERO);
    for c in &train {
        let r = c.rotation();
        let d = r.row(2).normalize();
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * c.center();
        up -= r.row(1);
    }
    let mean_center = train.iter().map(|c| c.center()).sum::<DVec3>() / train.len().max(1) as f64;
    let origin = if a.determinant().abs() > 1e-9 {
        a.inverse() * b
    } else {
        mean_center + train.first().map(|c| c.rotation().row(2)).unwrap_or(DVec3::Z)
    };
    let up = if up.length() > 0.0 { up.normalize() } else { DVec3::Y };
    let first = train.first().map(|c| c.center()).unwrap_or(DVec3::Z);
    let towards = first - origin;
    let mut z = towards - up * towards.dot(up);
    if z.length() < 1e-9 {
        z = up.any_orthonormal_vector();
    }
    let z = z.normalize();
    let x = up.cross(z);
    let dist = train.iter().map(|c| (c.center() - origin).length()).sum::<f64>()
        / train.len().max(1) as f64;
    let half = train
        .first()
        .map(|c| {
            (0.5 * c.pinhole.width as f64 / c.pinhole.fx)
                .min(0.5 * c.pinhole.height as f64 / c.pinhole.fy)
        })
        .unwrap_or(0.5);
    Placement {
        origin,
        rotation: DMat3::from_cols(x, up, z),
        scale: FILL * dist * half.atan().sin(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_protocol() {
        let cams = orbit(3, 12, 3.0, 35.0, 64, 48);
        assert_eq!(cams.len(), 36);
        for c in &cams {
            // The object centre projects to the image centre.
            let (u, v, z) = c.project(DVec3::ZERO).unwrap();
            assert!((u - 32.0).abs() < 1e-9 && (v - 24.0).abs() < 1e-9);
            assert!((z - ORBIT_DISTANCE).abs() < 1e-9);
            // World up points up in the image (negative v), x axis to the right.
            let (_, v_up, _) = c.project(DVec3::Y * 0.1).unwrap();
            assert!(v_up < 24.0);
            let k: u32 = c.camera[3..].parse().unwrap();
            let az = 30.0 * k as f64 + 3.0 * c.frame as f64;
            let center = c.center();
            let got = center.x.atan2(center.z).to_degrees().rem_euclid(360.0);
            assert!((got - az.rem_euclid(360.0)).abs() < 1e-6, "{} {got} {az}", c.camera);
            let el = (center.y / center.length()).asin().to_degrees();
            assert!((el - 35.0).abs() < 1e-9);
            assert_eq!(c.angle_offset_deg, Some(30.0 * k as f32));
            assert_eq!(c.split == Split::Train, k == 0);
        }
        assert_eq!(cams[12 + 3].image_path, "rgb/cam03/00001.png");
        // The unit sphere fits: a point at distance 1 from the centre, perpendicular to the
        // optical axis, lands inside the image.
        let c = &cams[0];
        let right = c.rotation().row(0);
        let (u, _, _) = c.project(right).unwrap();
        assert!(u < 64.0 && u > 32.0 + 0.8 * 24.0, "{u}");
    }

    #[test]
    fn placement_at_the_axes_crossing() {
        let target = DVec3::new(1.0, 2.0, 3.0);
        let mut cams = orbit(1, 4, 0.0, 10.0, 32, 32);
        for c in &mut cams {
            c.split = Split::Train;
            let m = c.w2c_mat() * DMat4::from_translation(-target);
            c.pinhole.w2c = Camera::w2c_from_mat(m);
        }
        let p = place_on_path(&cams);
        assert!(p.origin.abs_diff_eq(target, 1e-9), "{:?}", p.origin);
        assert!(p.rotation.col(1).abs_diff_eq(DVec3::Y, 1e-9));
        assert!(p.scale > 0.5 && p.scale < 1.1, "{}", p.scale);
    }
}
