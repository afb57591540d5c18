//! Packing of the kernels' uniform block (`Params` in shaders/common.wgsl): six vec4s, then
//! 32 scalars in declaration order; the convergence test's `min_weight` (word
//! [`MIN_WEIGHT_WORD`]) is written by `convergence_saved` and 0 otherwise.

use super::super::cpu::project::CameraConsts;
use super::super::{RenderCamera, RenderSettings};
use super::frame::{FrameKey, PARAM_WORDS};

/// How colours are given: RGB, or SH evaluated in the world or local frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ColorMode {
    Rgb = 0,
    ShWorld = 1,
    ShLocal = 2,
}

/// Word of `Params::min_weight` in the uniform block.
pub(crate) const MIN_WEIGHT_WORD: usize = 50;

/// The uniform block of one render.
pub(crate) fn pack(
    cam: &RenderCamera,
    settings: &RenderSettings,
    key: &FrameKey,
    mode: ColorMode,
    sh_degree: u8,
    smooth_cutoff: bool,
) -> [u32; PARAM_WORDS] {
    let c = CameraConsts::new(cam);
    let f = |v: f32| v.to_bits();
    let mut w = [0u32; PARAM_WORDS];
    for j in 0..3 {
        let col = c.rot.col(j);
        w[4 * j..4 * j + 3].copy_from_slice(&[f(col.x), f(col.y), f(col.z)]);
    }
    w[12..15].copy_from_slice(&[f(c.trans.x), f(c.trans.y), f(c.trans.z)]);
    w[16..19].copy_from_slice(&[f(c.center.x), f(c.center.y), f(c.center.z)]);
    w[20..23].copy_from_slice(&settings.background.map(f));
    let tiles_x = key.w.div_ceil(16) as u32;
    let tiles_y = key.h.div_ceil(16) as u32;
    let scalars = [
        f(c.fx),
        f(c.fy),
        f(c.cx),
        f(c.cy),
        f(c.lim_x[0]),
        f(c.lim_x[1]),
        f(c.lim_y[0]),
        f(c.lim_y[1]),
        f(c.width),
        f(c.height),
        f(c.near),
        f(c.far),
        f(settings.alpha_max),
        key.w as u32,
        key.h as u32,
        tiles_x,
        tiles_y,
        key.n as u32,
        key.nc as u32,
        key.nf as u32,
        sh_degree as u32,
        mode as u32,
        smooth_cutoff as u32,
        key.color_stride as u32,
        key.pair_cap as u32,
        tiles_x * tiles_y,
    ];
    w[24..24 + scalars.len()].copy_from_slice(&scalars);
    w
}
