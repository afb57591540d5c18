//! One DyCheck/Nerfies camera file (`camera/<cam>_<t:05d>.json`): parsing with errors that
//! name the key, conversion to our [`Camera`] at a downscale factor, conversion back, and
//! the JSON text.
//!
//! Keys (formats-and-protocols.md §3.2): `orientation` 3x3 world-to-camera rotation (rows =
//! camera axes in world), `position` camera centre, `focal_length`, `principal_point`
//! (pixels at 1x, pixel centres at +0.5), `skew`, `pixel_aspect_ratio`,
//! `radial_distortion` [k1, k2, k3], `tangential_distortion` [p1, p2] (older files:
//! `tangential`), `image_size` [W, H] at 1x. The last five are optional here (defaults 0,
//! 1, zeros, zeros); the first five are required.

use std::path::Path;

use glam::{DMat3, DMat4, DVec3, DVec4};
use serde_json::json;

use super::json::Obj;
use super::{Error, Result};
use crate::scene::{Camera, Pinhole, Split};

/// Largest tolerated `max |O·Oᵀ − I|` of an orientation (the iPhone files reach 1e-7).
const ROTATION_TOLERANCE: f64 = 1e-4;

/// A DyCheck camera as stored in its JSON file (1x image domain, source world frame).
#[derive(Debug, Clone, PartialEq)]
pub struct DycheckCamera {
    /// World-to-camera rotation; row i is camera axis i in world coordinates (OpenCV axes).
    pub orientation: [[f64; 3]; 3],
    /// Camera centre in world coordinates.
    pub position: [f64; 3],
    /// Focal length, pixels at 1x.
    pub focal_length: f64,
    /// Principal point `[cx, cy]`, pixels at 1x (pixel centres at +0.5).
    pub principal_point: [f64; 2],
    /// `fy / fx`.
    pub pixel_aspect_ratio: f64,
    /// `[k1, k2, k3]`.
    pub radial_distortion: [f64; 3],
    /// `[p1, p2]`.
    pub tangential_distortion: [f64; 2],
    /// `[W, H]` at 1x.
    pub image_size: [u32; 2],
}

/// Python's `int(round(x))` (round half to even), as `rescale_image_domain` sizes images.
pub(super) fn round_half_even(x: f64) -> u32 {
    x.round_ties_even().max(0.0) as u32
}

impl DycheckCamera {
    /// Parse camera file `path` (`needed_by` names what lists it, for a missing file).
    pub fn read(path: &Path, needed_by: Option<&str>) -> Result<Self> {
        let value = super::read_json(path, needed_by)?;
        let o = Obj::new(path, &value)?;
        let orientation = o.mat3("orientation")?;
        let m = DMat3::from_cols_array_2d(&orientation).transpose();
        let dev = (m * m.transpose() - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, x| a.max(x.abs()));
        let det = m.determinant();
        if dev > ROTATION_TOLERANCE || det <= 0.0 {
            return Err(o.err(
                "orientation",
                format!("not a rotation matrix (max |O*O^T - I| = {dev:.3e}, det = {det:.4})"),
            ));
        }
        let position = o.vec("position", 3)?;
        let focal_length = o.f64("focal_length")?;
        if focal_length <= 0.0 {
            return Err(o.err("focal_length", format!("must be positive, got {focal_length}")));
        }
        let pp = o.vec("principal_point", 2)?;
        let size = o.vec("image_size", 2)?;
        if size.iter().any(|s| *s < 1.0 || s.fract() != 0.0 || *s > u32::MAX as f64) {
            return Err(
                o.err("image_size", format!("expected 2 positive integers [W, H], got {size:?}"))
            );
        }
        let skew = match o.opt("skew") {
            Some(v) => o.as_f64("skew", v)?,
            None => 0.0,
        };
        if skew != 0.0 {
            return Err(o.err("skew", format!("non-zero skew ({skew}) is not supported")));
        }
        let pixel_aspect_ratio = match o.opt("pixel_aspect_ratio") {
            Some(v) => o.as_f64("pixel_aspect_ratio", v)?,
            None => 1.0,
        };
        if pixel_aspect_ratio <= 0.0 {
            return Err(
                o.err("pixel_aspect_ratio", format!("must be positive, got {pixel_aspect_ratio}"))
            );
        }
        let radial = match o.opt("radial_distortion") {
            Some(v) => o.as_vec("radial_distortion", v, 3)?,
            None => vec![0.0; 3],
        };
        let tan_key = if o.opt("tangential_distortion").is_none() && o.opt("tangential").is_some() {
            "tangential"
        } else {
            "tangential_distortion"
        };
        let tangential = match o.opt(tan_key) {
            Some(v) => o.as_vec(tan_key, v, 2)?,
            None => vec![0.0; 2],
        };
        Ok(DycheckCamera {
            orientation,
            position: [position[0], position[1], position[2]],
            focal_length,
            principal_point: [pp[0], pp[1]],
            pixel_aspect_ratio,
            radial_distortion: [radial[0], radial[1], radial[2]],
            tangential_distortion: [tangential[0], tangential[1]],
            image_size: [size[0] as u32, size[1] as u32],
        })
    }

    /// The JSON object of this camera (keys sorted, as DyCheck writes them).
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "orientation": self.orientation,
            "position": self.position,
            "focal_length": self.focal_length,
            "principal_point": self.principal_point,
            "skew": 0.0,
            "pixel_aspect_ratio": self.pixel_aspect_ratio,
            "radial_distortion": self.radial_distortion,
            "tangential_distortion": self.tangential_distortion,
            "image_size": self.image_size,
        })
    }

    /// Our camera for this file at downscale `factor` (≥ 1), with the world transform
    /// `world = (center, scale)` applied to the position when given. Paths are left empty.
    pub fn to_camera(
        &self,
        factor: u32,
        world: Option<([f64; 3], f64)>,
        frame: u32,
        camera: &str,
        split: Split,
    ) -> Camera {
        let s = 1.0 / factor as f64;
        let mut p = DVec3::from_array(self.position);
        if let Some((center, scale)) = world {
            p = (p - DVec3::from_array(center)) * scale;
        }
        let r = DMat3::from_cols_array_2d(&self.orientation).transpose();
        let t = -(r * p);
        let w2c = DMat4::from_cols(
            r.x_axis.extend(0.0),
            r.y_axis.extend(0.0),
            r.z_axis.extend(0.0),
            DVec4::new(t.x, t.y, t.z, 1.0),
        );
        let [k1, k2, k3] = self.radial_distortion;
        let [p1, p2] = self.tangential_distortion;
        let d = [k1, k2, k3, p1, p2];
        Camera {
            frame,
            camera: camera.to_string(),
            split,
            pinhole: Pinhole {
                fx: self.focal_length * s,
                fy: self.focal_length * s * self.pixel_aspect_ratio,
                cx: self.principal_point[0] * s,
                cy: self.principal_point[1] * s,
                width: round_half_even(self.image_size[0] as f64 * s),
                height: round_half_even(self.image_size[1] as f64 * s),
                w2c: Camera::w2c_from_mat(w2c),
            },
            image_path: String::new(),
            depth_path: None,
            mask_path: None,
            angle_offset_deg: None,
            distortion: d.iter().any(|x| *x != 0.0).then_some(d),
        }
    }

    /// The DyCheck camera of our `cam` when `cam`'s image domain is DyCheck's downscale
    /// `factor` (the 1x intrinsics and size are `factor` times ours).
    pub fn from_camera(cam: &Camera, factor: u32) -> Result<Self> {
        let f = factor as f64;
        let m = cam.w2c_mat();
        let r = DMat3::from_mat4(m);
        let t = m.w_axis.truncate();
        // The true inverse (not Oᵀ): stored rotations are orthonormal only to ~1e-7, and
        // −O·(−O⁻¹·t) must give back t.
        let position = -(r.inverse() * t);
        if !(cam.pinhole.fx > 0.0 && cam.pinhole.fy > 0.0) {
            return Err(Error::Scene(format!(
                "camera {} frame {}: focal lengths must be positive, got {} {}",
                cam.camera, cam.frame, cam.pinhole.fx, cam.pinhole.fy
            )));
        }
        let rt = r.transpose();
        let d = cam.distortion.unwrap_or([0.0; 5]);
        Ok(DycheckCamera {
            orientation: [rt.x_axis.to_array(), rt.y_axis.to_array(), rt.z_axis.to_array()],
            position: position.to_array(),
            focal_length: cam.pinhole.fx * f,
            principal_point: [cam.pinhole.cx * f, cam.pinhole.cy * f],
            pixel_aspect_ratio: cam.pinhole.fy / cam.pinhole.fx,
            radial_distortion: [d[0], d[1], d[2]],
            tangential_distortion: [d[3], d[4]],
            image_size: [cam.pinhole.width * factor, cam.pinhole.height * factor],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// DyCheck's `project` (formats-and-protocols.md §3.2), written from the formula with K
    /// as a matrix: `x_c = O(X − p)`, distort, `pix = K·[u', v', 1]`.
    fn dycheck_project(c: &DycheckCamera, x: [f64; 3]) -> [f64; 2] {
        let d = [x[0] - c.position[0], x[1] - c.position[1], x[2] - c.position[2]];
        let o = &c.orientation;
        let xc: Vec<f64> =
            (0..3).map(|i| o[i][0] * d[0] + o[i][1] * d[1] + o[i][2] * d[2]).collect();
        let (u, v) = (xc[0] / xc[2], xc[1] / xc[2]);
        let [k1, k2, k3] = c.radial_distortion;
        let [p1, p2] = c.tangential_distortion;
        let r2 = u * u + v * v;
        let rad = 1.0 + r2 * (k1 + r2 * (k2 + k3 * r2));
        let un = u * rad + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
        let vn = v * rad + 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v);
        let f = c.focal_length;
        let k =
            [[f, 0.0, c.principal_point[0]], [0.0, f * c.pixel_aspect_ratio, c.principal_point[1]]];
        [k[0][0] * un + k[0][1] * vn + k[0][2], k[1][1] * vn + k[1][2]]
    }

    fn hand_made() -> DycheckCamera {
        let (a, b) = (0.3f64, -0.2f64);
        let rz = DMat3::from_rotation_z(a) * DMat3::from_rotation_x(b);
        let rt = rz.transpose();
        DycheckCamera {
            orientation: [rt.x_axis.to_array(), rt.y_axis.to_array(), rt.z_axis.to_array()],
            position: [0.4, -0.1, -2.0],
            focal_length: 700.0,
            principal_point: [361.3, 478.9],
            pixel_aspect_ratio: 1.02,
            radial_distortion: [0.05, -0.02, 0.004],
            tangential_distortion: [0.001, -0.002],
            image_size: [720, 960],
        }
    }

    #[test]
    fn projection_matches_dycheck_formula_with_distortion() {
        let dc = hand_made();
        for factor in [1u32, 2, 4] {
            let cam = dc.to_camera(factor, None, 0, "0", Split::Train);
            assert_eq!(cam.distortion, Some([0.05, -0.02, 0.004, 0.001, -0.002]));
            for x in [[0.0, 0.0, 0.0], [0.5, 0.3, 0.2], [-0.4, 0.2, -0.3]] {
                let want = dycheck_project(&dc, x);
                let (u, v, z) = cam.project(DVec3::from_array(x)).unwrap();
                let s = factor as f64;
                assert!(
                    (u - want[0] / s).abs() < 1e-9 && (v - want[1] / s).abs() < 1e-9,
                    "{u} {v} vs {want:?}/{s}"
                );
                assert!(z > 0.0);
            }
        }
    }

    #[test]
    fn rescale_rounds_half_to_even_and_centre_is_position() {
        let mut dc = hand_made();
        dc.image_size = [45, 61];
        let cam = dc.to_camera(2, None, 3, "1", Split::Eval);
        // 22.5 -> 22 and 30.5 -> 30 (Python's round), not 23 / 31.
        assert_eq!((cam.pinhole.width, cam.pinhole.height), (22, 30));
        assert!((cam.center() - DVec3::from_array(dc.position)).length() < 1e-12);
        let back =
            DycheckCamera::from_camera(&dc.to_camera(1, None, 0, "0", Split::Train), 1).unwrap();
        for i in 0..3 {
            assert!((back.position[i] - dc.position[i]).abs() < 1e-12);
        }
        assert!((back.pixel_aspect_ratio - 1.02).abs() < 1e-12);
    }

    #[test]
    fn world_normalisation_follows_dycheck_parser() {
        let dc = hand_made();
        let cam = dc.to_camera(1, Some(([0.1, 0.2, 0.3], 0.5)), 0, "0", Split::Train);
        let want = (DVec3::from_array(dc.position) - DVec3::new(0.1, 0.2, 0.3)) * 0.5;
        assert!((cam.center() - want).length() < 1e-12);
    }
}
