//! Unlit shading of a surface point: base colour factor × base colour texture × vertex
//! colour, or a deterministic procedural texture for untextured materials.
//!
//! The procedural texture colours a 3D grid of cells in the bind pose (cell edge = 1/16 of
//! the bind-pose bounding-box diagonal) with hashed colours that multiply the material's
//! colour, so it moves with the surface and gives photometric reconstruction something to
//! match. Alpha modes are ignored: every surface is opaque.

use glam::Vec3;

use super::asset::Asset;
use super::shade::TextureMode;

/// Shades surface points of one asset.
pub struct Shader<'a> {
    asset: &'a Asset,
    procedural: Vec<bool>,
    cell: f32,
}

impl<'a> Shader<'a> {
    /// A shader for `asset` with the procedural texture chosen by `mode`.
    pub fn new(asset: &'a Asset, mode: TextureMode) -> Self {
        let procedural = asset
            .parts
            .iter()
            .map(|p| {
                let textured = asset.materials[p.material]
                    .texture
                    .is_some_and(|(i, _)| i < asset.textures.len());
                match mode {
                    TextureMode::Auto => !textured,
                    TextureMode::Procedural => true,
                    TextureMode::None => false,
                }
            })
            .collect();
        let (lo, hi) = asset
            .mesh
            .rest
            .iter()
            .fold((Vec3::MAX, Vec3::MIN), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let diag = (hi - lo).length();
        Shader { asset, procedural, cell: if diag > 0.0 { diag / 16.0 } else { 1.0 } }
    }

    /// Whether any part uses the procedural texture.
    pub fn any_procedural(&self) -> bool {
        self.procedural.iter().any(|&p| p)
    }

    /// Linear RGB of triangle `tri` at barycentric coordinates `b` (perspective-correct).
    pub fn color(&self, tri: u32, b: [f32; 3]) -> Vec3 {
        let m = &self.asset.mesh;
        let [i0, i1, i2] = m.tris[tri as usize].map(|i| i as usize);
        let part = m.tri_part[tri as usize] as usize;
        let mat = &self.asset.materials[self.asset.parts[part].material];
        let vcol = m.color[i0] * b[0] + m.color[i1] * b[1] + m.color[i2] * b[2];
        let mut c = mat.base_color.truncate() * vcol.truncate();
        if self.procedural[part] {
            let p = m.rest[i0] * b[0] + m.rest[i1] * b[1] + m.rest[i2] * b[2];
            c *= cell_color((p / self.cell).floor());
        } else if let Some((img, _)) = mat.texture
            && let Some(tex) = self.asset.textures.get(img)
        {
            let uv = m.uv[i0] * b[0] + m.uv[i1] * b[1] + m.uv[i2] * b[2];
            c *= tex.sample(uv, mat.wrap).truncate();
        }
        c
    }
}

/// Hashed colour of a procedural cell, each channel in [0.2, 1].
fn cell_color(cell: Vec3) -> Vec3 {
    let key = (cell.x as i64 as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (cell.y as i64 as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (cell.z as i64 as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    let h = crate::util::rng::mix(key);
    let ch = |s: u32| 0.2 + 0.8 * ((h >> s) & 0xFF) as f32 / 255.0;
    Vec3::new(ch(0), ch(8), ch(16))
}
