//! Materials and textures of an asset: base colour factor and texture (bilinear, sampler
//! wrap modes, linear light), the procedural texture choice, and the sRGB transfer
//! functions. [`super::shader`] shades surface points with them.

use std::sync::LazyLock;

use glam::{Vec2, Vec4};

/// Texture coordinate wrap mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wrap {
    /// Clamp to the edge texel.
    Clamp,
    /// Repeat.
    Repeat,
    /// Mirrored repeat.
    Mirror,
}

/// A decoded texture in linear light, `[H, W]` row-major texels.
#[derive(Debug, Clone)]
pub struct Texture {
    /// Width, texels.
    pub width: usize,
    /// Height, texels.
    pub height: usize,
    /// Linear RGBA texels.
    pub texels: Vec<Vec4>,
}

/// The unlit part of a glTF material.
#[derive(Debug, Clone)]
pub struct Material {
    /// Base colour factor, linear RGBA.
    pub base_color: Vec4,
    /// Base colour texture: (image index, TEXCOORD set).
    pub texture: Option<(usize, u32)>,
    /// Wrap modes along u and v.
    pub wrap: [Wrap; 2],
}

impl Default for Material {
    fn default() -> Self {
        Material { base_color: Vec4::ONE, texture: None, wrap: [Wrap::Repeat; 2] }
    }
}

/// Which surfaces get the procedural texture.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum TextureMode {
    /// Procedural texture on materials without a base colour texture.
    Auto,
    /// Procedural texture everywhere (the model's textures are ignored).
    Procedural,
    /// No procedural texture: untextured materials render in their flat colour.
    None,
}

/// sRGB-encoded value in [0, 1] to linear light.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 { v / 12.92 } else { ((v + 0.055) / 1.055).powf(2.4) }
}

const LUT_SIZE: usize = 1 << 14;

static TO_SRGB: LazyLock<Vec<f32>> = LazyLock::new(|| {
    (0..=LUT_SIZE)
        .map(|i| {
            let v = i as f32 / LUT_SIZE as f32;
            if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 }
        })
        .collect()
});

/// Linear light in [0, 1] to the sRGB-encoded value in [0, 1] (table with 2^14 steps: error
/// below 0.2 of an 8-bit level).
pub fn linear_to_srgb(v: f32) -> f32 {
    TO_SRGB[(v.clamp(0.0, 1.0) * LUT_SIZE as f32 + 0.5) as usize]
}

fn wrap_coord(i: isize, n: usize, w: Wrap) -> usize {
    let n = n as isize;
    match w {
        Wrap::Clamp => i.clamp(0, n - 1) as usize,
        Wrap::Repeat => i.rem_euclid(n) as usize,
        Wrap::Mirror => {
            let m = i.rem_euclid(2 * n);
            (if m < n { m } else { 2 * n - 1 - m }) as usize
        }
    }
}

impl Texture {
    /// Bilinear sample at texture coordinates `uv` (texel centres at +0.5).
    pub fn sample(&self, uv: Vec2, wrap: [Wrap; 2]) -> Vec4 {
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as isize, y0 as isize);
        let (w, h) = (self.width as isize, self.height as isize);
        if x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
            // Interior: no wrapping needed.
            let i = y0 as usize * self.width + x0 as usize;
            let t = &self.texels;
            let top = t[i].lerp(t[i + 1], fx);
            let bottom = t[i + self.width].lerp(t[i + self.width + 1], fx);
            return top.lerp(bottom, fy);
        }
        let t = |dx: isize, dy: isize| {
            let xi = wrap_coord(x0 + dx, self.width, wrap[0]);
            let yi = wrap_coord(y0 + dy, self.height, wrap[1]);
            self.texels[yi * self.width + xi]
        };
        let top = t(0, 0).lerp(t(1, 0), fx);
        let bottom = t(0, 1).lerp(t(1, 1), fx);
        top.lerp(bottom, fy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip_and_bilinear_wrap() {
        for k in 0..=255 {
            let v = k as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 0.2 / 255.0, "{k}");
        }
        let tex = Texture { width: 2, height: 1, texels: vec![Vec4::ZERO, Vec4::ONE] };
        // Halfway between the two texel centres.
        assert!(
            tex.sample(Vec2::new(0.5, 0.5), [Wrap::Clamp; 2]).abs_diff_eq(Vec4::splat(0.5), 1e-6)
        );
        // At u = 0 clamping holds texel 0; repeating blends with texel 1 across the seam.
        assert_eq!(tex.sample(Vec2::new(0.0, 0.5), [Wrap::Clamp; 2]), Vec4::ZERO);
        assert!(
            tex.sample(Vec2::new(0.0, 0.5), [Wrap::Repeat; 2]).abs_diff_eq(Vec4::splat(0.5), 1e-6)
        );
        assert_eq!(wrap_coord(-1, 4, Wrap::Mirror), 0);
        assert_eq!(wrap_coord(5, 4, Wrap::Mirror), 2);
        assert_eq!(wrap_coord(5, 4, Wrap::Repeat), 1);
    }
}
