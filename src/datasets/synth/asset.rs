//! glTF loading: turns a `.gltf`/`.glb` file into the flat, render-ready [`Asset`] the
//! benchmark poses every frame.
//!
//! Every mesh primitive instanced by a node of the scene becomes one [`Part`] (bind-pose
//! positions, skin influences, morph-target position deltas) whose vertices occupy a range
//! of the flat vertex arrays of [`FlatMesh`]; triangles (lists, strips and fans) index those
//! arrays globally. Materials keep the base colour factor and texture; textures are decoded
//! once into linear-light RGBA texels. Buffers and images may be embedded (GLB binary chunk,
//! data URIs) or external files next to the glTF; a missing file is an error naming it.

use std::path::{Path, PathBuf};

use glam::{Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::mesh::Mode;

use super::Error;
use super::anim::{Animation, Channel, Interp, Node, Property};
use super::shade::{Material, Texture, Wrap, srgb_to_linear};
use crate::util::fs::IoError;

/// A skin: joint nodes and their inverse bind matrices, `[J]` each.
#[derive(Debug, Clone)]
pub struct Skin {
    /// Joint node indices.
    pub joints: Vec<usize>,
    /// Inverse bind matrices.
    pub inverse_bind: Vec<Mat4>,
}

/// Up to eight joint influences of one vertex (JOINTS_0/WEIGHTS_0 and _1); unused slots
/// have weight 0.
pub type Influences = ([u16; 8], [f32; 8]);

/// One primitive as instanced by one node.
#[derive(Debug, Clone)]
pub struct Part {
    /// The instancing node (its world matrix places an unskinned part).
    pub node: usize,
    /// The skin, if the node has one.
    pub skin: Option<usize>,
    /// Bind-pose positions, mesh space, `[V_part]`.
    pub positions: Vec<Vec3>,
    /// Skin influences, `[V_part]` (empty without a skin).
    pub influences: Vec<Influences>,
    /// Morph-target position deltas, `[targets][V_part]`.
    pub targets: Vec<Vec<Vec3>>,
    /// Material index into [`Asset::materials`].
    pub material: usize,
}

/// Per-vertex attributes and triangles of all parts, flat.
#[derive(Debug, Clone, Default)]
pub struct FlatMesh {
    /// Texture coordinates of the material's base colour texture set, `[V]` (0 without).
    pub uv: Vec<Vec2>,
    /// Linear vertex colour COLOR_0, `[V]` (1 without).
    pub color: Vec<Vec4>,
    /// Bind-pose positions in mesh space, `[V]` (procedural texture coordinates).
    pub rest: Vec<Vec3>,
    /// Triangles as global vertex indices, `[F, 3]`.
    pub tris: Vec<[u32; 3]>,
    /// Part of each triangle, `[F]`.
    pub tri_part: Vec<u32>,
}

/// A loaded glTF scene ready to be posed.
#[derive(Debug, Clone)]
pub struct Asset {
    /// The file it was read from.
    pub path: PathBuf,
    /// All nodes, glTF order.
    pub nodes: Vec<Node>,
    /// Parent of each node, `[nodes]`.
    pub parent: Vec<Option<usize>>,
    /// Skins, glTF order.
    pub skins: Vec<Skin>,
    /// Animations, glTF order.
    pub animations: Vec<Animation>,
    /// Decoded textures, indexed by glTF image index.
    pub textures: Vec<Texture>,
    /// Materials, glTF order, plus the default material last.
    pub materials: Vec<Material>,
    /// Instanced primitives.
    pub parts: Vec<Part>,
    /// Flat attributes and triangles.
    pub mesh: FlatMesh,
}

impl Asset {
    /// Number of vertices V of the flat mesh.
    pub fn num_vertices(&self) -> usize {
        self.mesh.rest.len()
    }

    /// The animation named `name`, or the first one when `name` is `None`; `Ok(None)` when
    /// the file has no animation.
    pub fn animation(&self, name: Option<&str>) -> Result<Option<&Animation>, Error> {
        match name {
            None => Ok(self.animations.first()),
            Some(n) => self.animations.iter().find(|a| a.name == n).map(Some).ok_or_else(|| {
                let list: Vec<String> =
                    self.animations.iter().map(|a| format!("'{}'", a.name)).collect();
                Error::UnknownAnimation {
                    path: self.path.clone(),
                    name: n.to_string(),
                    available: if list.is_empty() { "none".into() } else { list.join(", ") },
                }
            }),
        }
    }
}

/// Load `path` (`.gltf` with embedded or external buffers, or `.glb`).
pub fn load(path: &Path) -> Result<Asset, Error> {
    let malformed = |msg: String| Error::Malformed { path: path.to_path_buf(), msg };
    let bytes = std::fs::read(path).map_err(IoError::at(path))?;
    if bytes.len() >= 12 && &bytes[..4] == b"glTF" {
        let declared = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
        if declared > bytes.len() {
            return Err(malformed(format!(
                "truncated: the GLB header declares {declared} bytes, the file has {}",
                bytes.len()
            )));
        }
    }
    let gltf::Gltf { document, blob } =
        gltf::Gltf::from_slice(&bytes).map_err(|e| malformed(e.to_string()))?;
    let base = path.parent().unwrap_or(Path::new("."));
    for b in document.buffers() {
        if let gltf::buffer::Source::Uri(uri) = b.source()
            && let Some(file) = external_file(base, uri)
            && !file.is_file()
        {
            return Err(Error::MissingFile {
                path: path.to_path_buf(),
                what: format!("buffer {}", b.index()),
                file,
            });
        }
    }
    for im in document.images() {
        if let gltf::image::Source::Uri { uri, .. } = im.source()
            && let Some(file) = external_file(base, uri)
            && !file.is_file()
        {
            return Err(Error::MissingFile {
                path: path.to_path_buf(),
                what: format!("texture image {}", im.index()),
                file,
            });
        }
    }
    let buffers =
        gltf::import_buffers(&document, Some(base), blob).map_err(|e| malformed(e.to_string()))?;
    let images = gltf::import_images(&document, Some(base), &buffers)
        .map_err(|e| malformed(format!("cannot decode a texture image: {e}")))?;
    let get = |b: gltf::Buffer| buffers.get(b.index()).map(|d| &d.0[..]);

    let textures = images.iter().map(decode_texture).collect::<Vec<_>>();
    let mut materials: Vec<Material> = document.materials().map(|m| material(&m)).collect();
    materials.push(Material::default());
    let default_material = materials.len() - 1;

    let nodes: Vec<Node> = document
        .nodes()
        .map(|n| {
            let (t, r, s) = n.transform().decomposed();
            let weights = n
                .weights()
                .map(<[f32]>::to_vec)
                .or_else(|| n.mesh().and_then(|m| m.weights().map(<[f32]>::to_vec)))
                .unwrap_or_default();
            Node {
                translation: Vec3::from(t),
                rotation: Quat::from_array(r).normalize(),
                scale: Vec3::from(s),
                children: n.children().map(|c| c.index()).collect(),
                weights,
            }
        })
        .collect();
    let mut parent = vec![None; nodes.len()];
    for (i, n) in nodes.iter().enumerate() {
        for &c in &n.children {
            parent[c] = Some(i);
        }
    }

    let skins = document
        .skins()
        .map(|s| {
            let joints: Vec<usize> = s.joints().map(|j| j.index()).collect();
            let inverse_bind: Vec<Mat4> = match s.reader(get).read_inverse_bind_matrices() {
                Some(it) => it.map(|m| Mat4::from_cols_array_2d(&m)).collect(),
                None => vec![Mat4::IDENTITY; joints.len()],
            };
            if inverse_bind.len() < joints.len() {
                return Err(malformed(format!(
                    "skin {}: fewer inverse bind matrices than joints",
                    s.index()
                )));
            }
            Ok(Skin { joints, inverse_bind })
        })
        .collect::<Result<Vec<_>, _>>()?;

    let animations = document
        .animations()
        .map(|a| {
            animation(&a, get, nodes.len())
                .map_err(|m| malformed(format!("animation {}: {m}", a.index())))
        })
        .collect::<Result<Vec<_>, _>>()?;

    // Instanced primitives: every node of the default scene (or all root nodes) with a mesh.
    let roots: Vec<usize> = match document.default_scene().or_else(|| document.scenes().next()) {
        Some(s) => s.nodes().map(|n| n.index()).collect(),
        None => (0..nodes.len()).filter(|&i| parent[i].is_none()).collect(),
    };
    let mut order = Vec::new();
    let mut stack: Vec<usize> = roots.into_iter().rev().collect();
    let mut seen = vec![false; nodes.len()];
    while let Some(n) = stack.pop() {
        if std::mem::replace(&mut seen[n], true) {
            continue;
        }
        order.push(n);
        stack.extend(nodes[n].children.iter().rev());
    }
    let doc_nodes: Vec<gltf::Node> = document.nodes().collect();
    let mut parts = Vec::new();
    let mut mesh = FlatMesh::default();
    for n in order {
        let node = &doc_nodes[n];
        let Some(m) = node.mesh() else { continue };
        let skin = node.skin().map(|s| s.index());
        for prim in m.primitives() {
            let ctx = |msg: &str| {
                malformed(format!("mesh {} primitive {}: {msg}", m.index(), prim.index()))
            };
            let reader = prim.reader(get);
            let Some(pos) = reader.read_positions() else {
                return Err(ctx("POSITION is missing or lies outside its buffer"));
            };
            let positions: Vec<Vec3> = pos.map(Vec3::from).collect();
            let nv = positions.len();
            let mat = prim.material().index().unwrap_or(default_material);
            let set = materials[mat].texture.map(|t| t.1).unwrap_or(0);
            let uv: Vec<Vec2> = match reader.read_tex_coords(set) {
                Some(t) => t.into_f32().map(Vec2::from).collect(),
                None => vec![Vec2::ZERO; nv],
            };
            let color: Vec<Vec4> = match reader.read_colors(0) {
                Some(c) => c.into_rgba_f32().map(Vec4::from).collect(),
                None => vec![Vec4::ONE; nv],
            };
            let influences = if skin.is_some() { influences(&reader, nv) } else { Vec::new() };
            let targets: Vec<Vec<Vec3>> = reader
                .read_morph_targets()
                .map(|(p, _, _)| match p {
                    Some(p) => p.map(Vec3::from).collect(),
                    None => vec![Vec3::ZERO; nv],
                })
                .collect();
            if uv.len() != nv || color.len() != nv || targets.iter().any(|t| t.len() != nv) {
                return Err(ctx("attribute counts differ from the POSITION count"));
            }
            if skin.is_some() && influences.len() != nv {
                return Err(ctx("skinned mesh without JOINTS_0/WEIGHTS_0 for every vertex"));
            }
            let indices: Vec<u32> = match reader.read_indices() {
                Some(i) => i.into_u32().collect(),
                None => (0..nv as u32).collect(),
            };
            if let Some(&bad) = indices.iter().find(|&&i| i as usize >= nv) {
                return Err(ctx(&format!("index {bad} out of range ({nv} vertices)")));
            }
            if let Some(sk) = skin {
                let nj = skins[sk].joints.len();
                if influences
                    .iter()
                    .any(|(j, w)| j.iter().zip(w).any(|(j, w)| *w != 0.0 && *j as usize >= nj))
                {
                    return Err(ctx(&format!("joint index out of range (skin has {nj} joints)")));
                }
            }
            let first = mesh.rest.len();
            let part = parts.len() as u32;
            for t in triangles(prim.mode(), &indices) {
                mesh.tris.push(t.map(|i| i + first as u32));
                mesh.tri_part.push(part);
            }
            mesh.uv.extend(uv);
            mesh.color.extend(color);
            mesh.rest.extend(&positions);
            parts.push(Part { node: n, skin, positions, influences, targets, material: mat });
        }
    }
    if mesh.tris.is_empty() {
        return Err(malformed("the scene has no triangle mesh".into()));
    }
    Ok(Asset {
        path: path.to_path_buf(),
        nodes,
        parent,
        skins,
        animations,
        textures,
        materials,
        parts,
        mesh,
    })
}

/// The file an external (non-data) URI names, relative to `base`.
fn external_file(base: &Path, uri: &str) -> Option<PathBuf> {
    if uri.starts_with("data:") {
        return None;
    }
    let decoded = uri.replace("%20", " ");
    Some(base.join(decoded))
}

/// Triangles of a primitive's index list in its drawing mode (points and lines give none).
fn triangles(mode: Mode, idx: &[u32]) -> Vec<[u32; 3]> {
    match mode {
        Mode::Triangles => idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        Mode::TriangleStrip => (2..idx.len())
            .map(|i| {
                if i % 2 == 0 {
                    [idx[i - 2], idx[i - 1], idx[i]]
                } else {
                    [idx[i - 1], idx[i - 2], idx[i]]
                }
            })
            .collect(),
        Mode::TriangleFan => (2..idx.len()).map(|i| [idx[0], idx[i - 1], idx[i]]).collect(),
        _ => Vec::new(),
    }
}

fn influences<'a, 's, F>(reader: &gltf::mesh::Reader<'a, 's, F>, nv: usize) -> Vec<Influences>
where
    F: Clone + Fn(gltf::Buffer<'a>) -> Option<&'s [u8]>,
{
    let mut out = vec![([0u16; 8], [0f32; 8]); nv];
    for set in 0..2u32 {
        let (Some(j), Some(w)) = (reader.read_joints(set), reader.read_weights(set)) else {
            if set == 0 {
                return Vec::new();
            }
            break;
        };
        let o = 4 * set as usize;
        for (k, (j, w)) in j.into_u16().zip(w.into_f32()).enumerate().take(nv) {
            out[k].0[o..o + 4].copy_from_slice(&j);
            out[k].1[o..o + 4].copy_from_slice(&w);
        }
    }
    out
}

fn material(m: &gltf::Material) -> Material {
    let pbr = m.pbr_metallic_roughness();
    let texture = pbr.base_color_texture().map(|info| {
        let s = info.texture().sampler();
        (info.texture().source().index(), info.tex_coord(), [wrap(s.wrap_s()), wrap(s.wrap_t())])
    });
    Material {
        base_color: Vec4::from(pbr.base_color_factor()),
        texture: texture.map(|(i, set, _)| (i, set)),
        wrap: texture.map(|t| t.2).unwrap_or([Wrap::Repeat; 2]),
    }
}

fn wrap(w: gltf::texture::WrappingMode) -> Wrap {
    match w {
        gltf::texture::WrappingMode::ClampToEdge => Wrap::Clamp,
        gltf::texture::WrappingMode::MirroredRepeat => Wrap::Mirror,
        gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
    }
}

/// Decode image data (sRGB-encoded) into linear RGBA texels.
fn decode_texture(d: &gltf::image::Data) -> Texture {
    use gltf::image::Format as F;
    let n = (d.width * d.height) as usize;
    let (ch, bytes) = match d.format {
        F::R8 => (1, 1),
        F::R8G8 => (2, 1),
        F::R8G8B8 => (3, 1),
        F::R8G8B8A8 => (4, 1),
        F::R16 => (1, 2),
        F::R16G16 => (2, 2),
        F::R16G16B16 => (3, 2),
        F::R16G16B16A16 => (4, 2),
        F::R32G32B32FLOAT => (3, 4),
        F::R32G32B32A32FLOAT => (4, 4),
    };
    let value = |i: usize| -> f32 {
        let b = &d.pixels[i * bytes..(i + 1) * bytes];
        match bytes {
            1 => b[0] as f32 / 255.0,
            2 => u16::from_le_bytes([b[0], b[1]]) as f32 / 65535.0,
            _ => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        }
    };
    let texels = if d.pixels.len() < n * ch * bytes {
        vec![Vec4::ONE; n]
    } else {
        (0..n)
            .map(|p| {
                let c = |k: usize| value(p * ch + k.min(ch - 1));
                let (r, g, b) = if ch < 3 { (c(0), c(0), c(0)) } else { (c(0), c(1), c(2)) };
                let a = if ch == 4 || ch == 2 { c(ch - 1) } else { 1.0 };
                Vec4::new(srgb_to_linear(r), srgb_to_linear(g), srgb_to_linear(b), a)
            })
            .collect()
    };
    Texture { width: d.width as usize, height: d.height as usize, texels }
}

fn animation<'a, 's, F>(
    a: &gltf::Animation<'a>,
    get: F,
    num_nodes: usize,
) -> Result<Animation, String>
where
    F: Clone + Fn(gltf::Buffer<'a>) -> Option<&'s [u8]>,
{
    use gltf::animation::util::ReadOutputs;
    let mut channels = Vec::new();
    for ch in a.channels() {
        let node = ch.target().node().index();
        if node >= num_nodes {
            return Err(format!("channel targets node {node} of {num_nodes}"));
        }
        let reader = ch.reader(get.clone());
        let times: Vec<f32> = reader.read_inputs().ok_or("sampler without input")?.collect();
        let (property, values, width): (Property, Vec<f32>, usize) = match reader
            .read_outputs()
            .ok_or("sampler without output")?
        {
            ReadOutputs::Translations(it) => (Property::Translation, it.flatten().collect(), 3),
            ReadOutputs::Scales(it) => (Property::Scale, it.flatten().collect(), 3),
            ReadOutputs::Rotations(r) => (Property::Rotation, r.into_f32().flatten().collect(), 4),
            ReadOutputs::MorphTargetWeights(w) => {
                let v: Vec<f32> = w.into_f32().collect();
                (Property::Weights, v, 0)
            }
        };
        let interp = match ch.sampler().interpolation() {
            gltf::animation::Interpolation::Linear => Interp::Linear,
            gltf::animation::Interpolation::Step => Interp::Step,
            gltf::animation::Interpolation::CubicSpline => Interp::CubicSpline,
        };
        let per_key = if interp == Interp::CubicSpline { 3 } else { 1 };
        let width = if width == 0 { values.len() / (times.len() * per_key).max(1) } else { width };
        if times.is_empty() || width == 0 || values.len() != times.len() * per_key * width {
            return Err(format!(
                "channel on node {node}: {} outputs for {} inputs",
                values.len(),
                times.len()
            ));
        }
        if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] <= w[0]) {
            return Err(format!("channel on node {node}: input times are not strictly increasing"));
        }
        channels.push(Channel { node, property, interp, times, values, width });
    }
    let start = channels.iter().map(|c| c.times[0]).fold(f32::INFINITY, f32::min);
    let end =
        channels.iter().map(|c| *c.times.last().unwrap_or(&0.0)).fold(f32::NEG_INFINITY, f32::max);
    let name = a.name().map(str::to_string).unwrap_or_else(|| format!("animation{}", a.index()));
    Ok(Animation {
        name,
        channels,
        start: if start.is_finite() { start } else { 0.0 },
        end: if end.is_finite() { end } else { 0.0 },
    })
}
