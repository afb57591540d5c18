//! Lifting 2D observations to 3D with the depth prior: the per-frame inputs of a training
//! camera (depth prior, foreground mask, RGB) and the unprojection of the 2D tracks.
//!
//! A track is *observed* at frame t when the tracks prior says it is visible there and the
//! depth prior has a valid foreground value at its pixel; its 3D position is the pixel
//! unprojected at the median of the valid foreground depths of its 3x3 neighbourhood (the
//! median resists the flying pixels that depth networks leave at depth edges).

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3, Vec3};

use crate::formats::npy::read_npy_f32;
use crate::formats::png::{Image, read_png};
use crate::scene::Camera;
use crate::tables::tracks_2d::Tracks2dFrame;

/// Errors of reading one frame's inputs; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An image or array could not be read.
    #[error(transparent)]
    Io(#[from] crate::formats::Error),
    /// A file does not match its camera.
    #[error("{}: {msg}", path.display())]
    Shape {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// The training camera lacks a file that init needs.
    #[error("training camera '{camera}' frame {frame}: no {what} path in cameras.parquet")]
    Missing {
        /// Camera name.
        camera: String,
        /// Frame.
        frame: u32,
        /// `depth_path` or `mask_path`.
        what: &'static str,
    },
}

/// What a monocular pipeline has of one training frame.
pub struct FrameInputs {
    /// Width W.
    pub width: usize,
    /// Height H.
    pub height: usize,
    /// Depth prior `[H, W]` (z-depth, 0 = invalid), zeroed outside the foreground mask.
    pub depth: Vec<f32>,
    /// RGB `[H, W, 3]` (straight colour of the RGBA image), when requested.
    pub rgb: Option<Image>,
    /// Camera-to-world of the frame.
    c2w: DMat4,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// Read the depth prior (at `depth`), the mask and optionally the RGB image of `cam`.
pub fn read_frame(
    cam: &Camera,
    depth: Option<PathBuf>,
    mask: Option<PathBuf>,
    with_rgb: Option<PathBuf>,
) -> Result<FrameInputs, Error> {
    let missing = |what| Error::Missing { camera: cam.camera.clone(), frame: cam.frame, what };
    let (w, h) = cam.pinhole.size();
    let depth_path = depth.ok_or_else(|| missing("depth_path"))?;
    let mask_path = mask.ok_or_else(|| missing("mask_path"))?;
    let (shape, mut depth) = read_npy_f32(&depth_path)?;
    if shape.iter().product::<usize>() != w * h || shape.first() != Some(&h) {
        return Err(Error::Shape {
            path: depth_path,
            msg: format!("depth of shape {shape:?}, the camera is {h}x{w} (HxW)"),
        });
    }
    let mask = read_png(&mask_path)?;
    check_size(&mask_path, &mask, w, h)?;
    for (i, d) in depth.iter_mut().enumerate() {
        if !(mask.data[i * mask.channels] > 0.5 && d.is_finite() && *d > 0.0) {
            *d = 0.0;
        }
    }
    let rgb = match with_rgb {
        Some(p) => {
            let img = read_png(&p)?;
            check_size(&p, &img, w, h)?;
            Some(straight_rgb(img))
        }
        None => None,
    };
    Ok(FrameInputs {
        width: w,
        height: h,
        depth,
        rgb,
        c2w: cam.w2c_mat().inverse(),
        fx: cam.pinhole.fx,
        fy: cam.pinhole.fy,
        cx: cam.pinhole.cx,
        cy: cam.pinhole.cy,
    })
}

fn check_size(path: &Path, img: &Image, w: usize, h: usize) -> Result<(), Error> {
    if (img.width, img.height) != (w, h) {
        return Err(Error::Shape {
            path: path.into(),
            msg: format!("image is {}x{}, the camera is {w}x{h}", img.width, img.height),
        });
    }
    Ok(())
}

/// The straight (un-premultiplied) RGB of an image: the colour channels as stored.
fn straight_rgb(img: Image) -> Image {
    match img.channels {
        3 => img,
        4 => {
            let data = img.data.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
            Image { channels: 3, data, ..img }
        }
        _ => img.rgb_over([0.0; 3]),
    }
}

impl FrameInputs {
    /// World point of pixel position `(x, y)` (pixel centres at +0.5) at z-depth `z`.
    pub fn unproject(&self, x: f64, y: f64, z: f64) -> Vec3 {
        let c = DVec3::new((x - self.cx) / self.fx * z, (y - self.cy) / self.fy * z, z);
        self.c2w.transform_point3(c).as_vec3()
    }

    /// Depth prior at pixel `(ix, iy)` (0 = invalid or background).
    pub fn depth_at(&self, ix: usize, iy: usize) -> f32 {
        self.depth[iy * self.width + ix]
    }

    /// Median of the valid depths in the 3x3 neighbourhood of the pixel holding `(x, y)`.
    pub fn robust_depth(&self, x: f32, y: f32) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (ix, iy) = (x as usize, y as usize);
        if ix >= self.width || iy >= self.height || self.depth_at(ix, iy) <= 0.0 {
            return None;
        }
        let mut v: Vec<f32> = Vec::with_capacity(9);
        for jy in iy.saturating_sub(1)..(iy + 2).min(self.height) {
            for jx in ix.saturating_sub(1)..(ix + 2).min(self.width) {
                let d = self.depth_at(jx, jy);
                if d > 0.0 {
                    v.push(d);
                }
            }
        }
        v.sort_by(f32::total_cmp);
        Some(v[v.len() / 2])
    }

    /// 3D positions `[M]` of the tracks observed in this frame (`None` where not observed).
    pub fn lift_tracks(&self, tracks: &Tracks2dFrame) -> Vec<Option<Vec3>> {
        tracks
            .xy
            .iter()
            .zip(&tracks.visible)
            .map(|(&[x, y], &vis)| {
                if !vis {
                    return None;
                }
                let z = self.robust_depth(x, y)?;
                Some(self.unproject(x as f64, y as f64, z as f64))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(depth: Vec<f32>, w: usize, h: usize) -> FrameInputs {
        FrameInputs {
            width: w,
            height: h,
            depth,
            rgb: None,
            c2w: DMat4::IDENTITY,
            fx: 10.0,
            fy: 10.0,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
        }
    }

    #[test]
    fn unproject_inverts_the_pinhole() {
        let f = frame(vec![2.0; 16], 4, 4);
        let p = f.unproject(3.0, 1.0, 2.0);
        assert_eq!(p, Vec3::new(0.2, -0.2, 2.0));
    }

    #[test]
    fn robust_depth_ignores_one_flying_pixel_and_background() {
        let mut d = vec![2.0; 25];
        d[6] = 9.0; // a flying pixel next to (2, 2)
        d[0] = 0.0;
        let f = frame(d, 5, 5);
        assert_eq!(f.robust_depth(2.5, 2.5), Some(2.0));
        assert_eq!(f.robust_depth(0.5, 0.5), None, "background pixel");
        assert_eq!(f.robust_depth(-1.0, -1.0), None, "behind the camera");
        let t = Tracks2dFrame { xy: vec![[2.5, 2.5], [2.5, 2.5]], visible: vec![true, false] };
        let lifted = f.lift_tracks(&t);
        assert!(lifted[0].is_some() && lifted[1].is_none());
    }
}
