//! The report's images: grids of the farthest evaluation views (ground truth next to each
//! method's render), per-frame uncertainty heat maps (u rendered as a colour-mapped
//! feature in the training camera), key nodes and motion segments drawn over a render, and
//! the key-graph weight matrix reordered by segment.

use std::collections::BTreeMap;

use crate::formats::png::{Image, read_png};
use crate::model::Model;
use crate::render::{
    ColorSource, CpuRenderer, RenderCamera, RenderSettings, Renderer, SplatInputs,
};
use crate::scene::{Camera, Scene};
use crate::stages::evaluate::angular_distance;
use crate::stages::graph::spectral::SparseSym;
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::segments::Segments;

use super::plots::PALETTE;

/// Viridis, piecewise linear through nine samples of matplotlib's table; `x` in [0, 1].
pub fn viridis(x: f64) -> [f32; 3] {
    const C: [[f32; 3]; 9] = [
        [0.267, 0.005, 0.329],
        [0.279, 0.175, 0.483],
        [0.230, 0.322, 0.546],
        [0.173, 0.449, 0.558],
        [0.128, 0.567, 0.551],
        [0.153, 0.680, 0.504],
        [0.361, 0.786, 0.388],
        [0.668, 0.862, 0.196],
        [0.993, 0.906, 0.144],
    ];
    let x = if x.is_finite() { x.clamp(0.0, 1.0) } else { 0.0 } * 8.0;
    let k = (x.floor() as usize).min(7);
    let f = (x - k as f64) as f32;
    std::array::from_fn(|c| C[k][c] * (1.0 - f) + C[k + 1][c] * f)
}

/// The eval camera farthest from the training view (largest angular offset, an offset above
/// 180° counting as 360° minus it; the last eval camera when the scene has no offsets) and
/// up to `n` of its frames, evenly spaced.
pub fn farthest_views(scene: &Scene, n: usize) -> Vec<&Camera> {
    let eval: Vec<&Camera> = scene.eval().collect();
    let key = |c: &Camera| c.angle_offset_deg.map_or(0.0, angular_distance);
    let Some(far) = eval.iter().map(|c| key(c)).reduce(f32::max) else { return Vec::new() };
    let name =
        eval.iter().rev().find(|c| key(c) == far).map(|c| c.camera.clone()).unwrap_or_default();
    let cams: Vec<&Camera> = eval.into_iter().filter(|c| c.camera == name).collect();
    if cams.len() <= n {
        return cams;
    }
    (0..n).map(|k| cams[k * (cams.len() - 1) / (n - 1).max(1)]).collect()
}

/// Rows of `[ground truth, method 1, ...]` images at the views `cams`, read from the scene
/// and from each render directory at the camera's image path (composited over white).
pub fn view_grid(
    scene: &Scene,
    cams: &[&Camera],
    renders: &[(String, std::path::PathBuf)],
) -> anyhow::Result<Vec<(String, Vec<Image>)>> {
    let mut rows = Vec::new();
    for cam in cams {
        let mut row = vec![read_png(&scene.resolve(&cam.image_path))?.rgb_over([1.0; 3])];
        for (_, dir) in renders {
            row.push(read_png(&dir.join(&cam.image_path))?.rgb_over([1.0; 3]));
        }
        rows.push((format!("camera {} frame {}", cam.camera, cam.frame), row));
    }
    Ok(rows)
}

/// Render `model` at `frame` in `cam` with one RGB colour per Gaussian (canonical order).
pub fn render_colored(
    model: &Model,
    frame: usize,
    cam: &Camera,
    colors: &[[f32; 3]],
) -> anyhow::Result<Image> {
    let state = model.frame(frame)?;
    let inputs = SplatInputs { colors: ColorSource::Rgb(colors), ..model.splat_inputs(&state) };
    let cam = RenderCamera::from(&model.render_camera(cam));
    let out = CpuRenderer.render(&cam, &inputs, &RenderSettings::default())?;
    Ok(Image { width: out.width, height: out.height, channels: 3, data: out.color })
}

/// log10 bounds of a heat map: the 2nd and 98th percentiles of the finite positive values.
pub fn log_range(values: &[f32]) -> (f64, f64) {
    let mut v: Vec<f64> =
        values.iter().filter(|u| u.is_finite() && **u > 0.0).map(|u| (*u as f64).log10()).collect();
    if v.is_empty() {
        return (0.0, 1.0);
    }
    v.sort_by(f64::total_cmp);
    let lo = v[(v.len() - 1) * 2 / 100];
    let hi = v[(v.len() - 1) * 98 / 100];
    if hi > lo { (lo, hi) } else { (lo, lo + 1.0) }
}

/// Colours mapping log10 `u` over `(lo, hi)` to viridis (dark = confident).
pub fn heat_colors(u: &[f32], (lo, hi): (f64, f64)) -> Vec<[f32; 3]> {
    u.iter()
        .map(|&u| viridis(((u.max(f32::MIN_POSITIVE) as f64).log10() - lo) / (hi - lo)))
        .collect()
}

/// Colours by motion segment (keyed by `gaussian_id`; Gaussians without a label grey).
pub fn segment_colors(model: &Model, segments: &Segments) -> Vec<[f32; 3]> {
    let by_id: BTreeMap<u32, u32> =
        segments.id.iter().copied().zip(segments.segment.iter().copied()).collect();
    model
        .gaussians
        .id
        .iter()
        .map(|id| match by_id.get(id) {
            Some(&s) => {
                let c = PALETTE[s as usize % PALETTE.len()];
                [c.0 as f32 / 255.0, c.1 as f32 / 255.0, c.2 as f32 / 255.0]
            }
            None => [0.6, 0.6, 0.6],
        })
        .collect()
}

/// Draw each key node of `model` at `frame` as a 5x5 black-ringed white dot on `img`.
pub fn draw_keys(
    img: &mut Image,
    model: &Model,
    frame: usize,
    cam: &Camera,
    segments: &Segments,
) -> anyhow::Result<usize> {
    let state = model.frame(frame)?;
    let keys: std::collections::BTreeSet<u32> =
        segments.id.iter().zip(&segments.is_key).filter(|(_, k)| **k).map(|(id, _)| *id).collect();
    let mut drawn = 0;
    for (i, id) in model.gaussians.id.iter().enumerate() {
        if !keys.contains(id) {
            continue;
        }
        let p = state.position[i];
        let Some((x, y, _)) = cam.project(glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        else {
            continue;
        };
        let (cx, cy) = (x.floor() as i64, y.floor() as i64);
        for dy in -2i64..=2 {
            for dx in -2i64..=2 {
                let (px, py) = (cx + dx, cy + dy);
                if px < 0 || py < 0 || px >= img.width as i64 || py >= img.height as i64 {
                    continue;
                }
                let v = if dx.abs() == 2 || dy.abs() == 2 { 0.0 } else { 1.0 };
                let o = (py as usize * img.width + px as usize) * img.channels;
                img.data[o..o + 3].fill(v);
            }
        }
        drawn += 1;
    }
    Ok(drawn)
}

/// The key-key weight matrix (symmetrised) with keys ordered by segment, then id, as a
/// viridis image of at most `max_side` pixels a side (each pixel the largest weight of its
/// block), and the largest weight.
pub fn weight_matrix(edges: &Edges, segments: &Segments, max_side: usize) -> (Image, f64) {
    let label: BTreeMap<u32, u32> =
        segments.id.iter().copied().zip(segments.segment.iter().copied()).collect();
    let mut keys: Vec<u32> = (0..edges.len())
        .filter(|&e| edges.kind[e] == EdgeKind::KeyKey)
        .flat_map(|e| [edges.src[e], edges.dst[e]])
        .collect();
    keys.sort_unstable_by_key(|id| (label.get(id).copied().unwrap_or(u32::MAX), *id));
    keys.dedup();
    let pos: BTreeMap<u32, u32> = keys.iter().enumerate().map(|(p, id)| (*id, p as u32)).collect();
    let w = SparseSym::symmetrised(
        keys.len(),
        (0..edges.len())
            .filter(|&e| edges.kind[e] == EdgeKind::KeyKey)
            .map(|e| (pos[&edges.src[e]], pos[&edges.dst[e]], edges.weight[e] as f64)),
    );
    let nk = keys.len().max(1);
    let side = nk.clamp(1, max_side.max(1));
    let mut cells = vec![0.0f64; side * side];
    for (i, row) in w.rows.iter().enumerate() {
        for &(j, v) in row {
            let c = (i * side / nk) * side + j as usize * side / nk;
            cells[c] = cells[c].max(v);
        }
    }
    let max = cells.iter().copied().fold(0.0, f64::max);
    let data = cells
        .iter()
        .flat_map(|&v| if v > 0.0 { viridis(v / max) } else { [1.0, 1.0, 1.0] })
        .collect();
    (Image { width: side, height: side, channels: 3, data }, max)
}

/// Images side by side (same height), separated by `gap` white columns.
pub fn hstack(images: &[Image], gap: usize) -> Image {
    let h = images.iter().map(|i| i.height).max().unwrap_or(0);
    let w = images.iter().map(|i| i.width).sum::<usize>() + gap * images.len().saturating_sub(1);
    let mut out = Image::filled(w, h, 3, 1.0);
    let mut x0 = 0;
    for im in images {
        let rgb = im.rgb_over([1.0; 3]);
        for y in 0..rgb.height {
            let src = &rgb.data[y * rgb.width * 3..(y + 1) * rgb.width * 3];
            out.data[(y * w + x0) * 3..(y * w + x0 + rgb.width) * 3].copy_from_slice(src);
        }
        x0 += im.width + gap;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viridis_ends_and_clamps() {
        assert_eq!(viridis(0.0), [0.267, 0.005, 0.329]);
        assert_eq!(viridis(1.0), [0.993, 0.906, 0.144]);
        assert_eq!(viridis(-3.0), viridis(0.0));
        assert_eq!(viridis(f64::NAN), viridis(0.0));
    }

    #[test]
    fn weight_matrix_is_block_diagonal_by_segment() {
        // Keys 10, 11 in segment 1 and 20, 21 in segment 0, linked within segments only.
        let edges = Edges {
            src: vec![10, 11, 20, 21],
            dst: vec![11, 10, 21, 20],
            kind: vec![EdgeKind::KeyKey; 4],
            weight: vec![1.0; 4],
            rest_length: vec![None; 4],
        };
        let segments =
            Segments { id: vec![10, 11, 20, 21], segment: vec![1, 1, 0, 0], is_key: vec![true; 4] };
        let (img, max) = weight_matrix(&edges, &segments, 64);
        assert_eq!((img.width, max), (4, 1.0));
        let white =
            |x: usize, y: usize| img.data[(y * 4 + x) * 3..(y * 4 + x) * 3 + 3] == [1.0, 1.0, 1.0];
        // Off-diagonal blocks are empty, in-block off-diagonal cells are set.
        assert!(white(2, 0) && white(0, 3) && !white(1, 0) && !white(3, 2));
    }

    #[test]
    fn log_range_ignores_unseen() {
        let (lo, hi) = log_range(&[0.0, f32::INFINITY, 1.0, 10.0, 100.0]);
        assert!(lo >= 0.0 && hi <= 2.0 && hi > lo);
    }
}
