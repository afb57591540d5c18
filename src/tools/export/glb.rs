//! The binary glTF (GLB) file of one frame with the Khronos `KHR_gaussian_splatting`
//! extension (ratified; text of the extension's README in KhronosGroup/glTF).
//!
//! One node, one mesh, one `POINTS` primitive whose attributes are `POSITION`,
//! `KHR_gaussian_splatting:ROTATION` (unit quaternion in glTF order `x y z w`),
//! `:SCALE` (linear, not log, as the extension requires), `:OPACITY` (in [0, 1], not a
//! logit) and `:SH_DEGREE_l_COEF_n` (the raw SH coefficients, degree 0 being 3DGS's
//! `f_dc`; within a degree from the lowest order m to the highest, which is the order of
//! the 3DGS basis and of [`Splats::sh_rest`]). The extension object names the `ellipse`
//! kernel and the `srgb_rec709_display` colour space (our images are display sRGB, as
//! 3DGS's). Every attribute is a tightly packed float accessor in its own buffer view.
//! Positions are written in the model's world frame as they are (no axis conversion to
//! glTF's +Y up).

use serde_json::{Value, json};

use super::splats::Splats;

/// The extension's name.
pub const EXTENSION: &str = "KHR_gaussian_splatting";

const COMPONENT_FLOAT: u32 = 5126;
const MODE_POINTS: u32 = 0;
const GLB_MAGIC: u32 = 0x4654_6C67;
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

/// Attribute semantic and accessor type of each attribute written, in order, with its
/// values per Gaussian.
fn attributes(s: &Splats) -> Vec<(String, &'static str, Vec<f32>)> {
    let flat3 = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let mut out = vec![
        ("POSITION".to_string(), "VEC3", flat3(&s.position)),
        (
            format!("{EXTENSION}:ROTATION"),
            "VEC4",
            s.rotation.iter().flat_map(|q| [q[1], q[2], q[3], q[0]]).collect(),
        ),
        (format!("{EXTENSION}:SCALE"), "VEC3", flat3(&s.scale)),
        (format!("{EXTENSION}:OPACITY"), "SCALAR", s.opacity.clone()),
        (format!("{EXTENSION}:SH_DEGREE_0_COEF_0"), "VEC3", flat3(&s.f_dc)),
    ];
    let k = s.num_rest();
    for l in 1..=s.sh_degree as usize {
        for n in 0..2 * l + 1 {
            let j = l * l - 1 + n;
            let values = (0..s.len())
                .flat_map(|i| (0..3).map(move |c| (i, c)))
                .map(|(i, c)| s.sh_rest[(i * k + j) * 3 + c]);
            out.push((format!("{EXTENSION}:SH_DEGREE_{l}_COEF_{n}"), "VEC3", values.collect()));
        }
    }
    out
}

/// The GLB file of `s`; `name` labels the node (e.g. the frame).
pub fn encode(s: &Splats, name: &str) -> Vec<u8> {
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut semantics = serde_json::Map::new();
    for (i, (semantic, kind, values)) in attributes(s).into_iter().enumerate() {
        let offset = bin.len();
        for v in &values {
            bin.extend(v.to_le_bytes());
        }
        views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": values.len() * 4}));
        let mut accessor = json!({
            "bufferView": i,
            "componentType": COMPONENT_FLOAT,
            "count": s.len(),
            "type": kind,
        });
        if semantic == "POSITION" && !s.is_empty() {
            // glTF requires min and max on POSITION accessors
            let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
            for p in &s.position {
                for c in 0..3 {
                    lo[c] = lo[c].min(p[c]);
                    hi[c] = hi[c].max(p[c]);
                }
            }
            accessor["min"] = json!(lo);
            accessor["max"] = json!(hi);
        }
        accessors.push(accessor);
        semantics.insert(semantic, json!(i));
    }
    let doc = json!({
        "asset": {"version": "2.0", "generator": concat!("usplat4d ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"primitives": [{
            "mode": MODE_POINTS,
            "attributes": Value::Object(semantics),
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}},
        }]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    let mut json_bytes = doc.to_string().into_bytes();
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    for word in [GLB_MAGIC, 2, total as u32, json_bytes.len() as u32, CHUNK_JSON] {
        out.extend(word.to_le_bytes());
    }
    out.extend(&json_bytes);
    for word in [bin.len() as u32, CHUNK_BIN] {
        out.extend(word.to_le_bytes());
    }
    out.extend(&bin);
    out
}

#[cfg(test)]
pub(crate) mod read {
    //! A reader of the files [`super::encode`] writes, for tests.

    use std::collections::BTreeMap;

    fn word(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    /// The JSON document and every attribute of the first primitive as floats, by semantic.
    pub fn decode(bytes: &[u8]) -> (serde_json::Value, BTreeMap<String, Vec<f32>>) {
        assert_eq!(word(bytes, 0), super::GLB_MAGIC);
        assert_eq!(word(bytes, 4), 2);
        assert_eq!(word(bytes, 8) as usize, bytes.len());
        let json_len = word(bytes, 12) as usize;
        assert_eq!(word(bytes, 16), super::CHUNK_JSON);
        let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        let at = 20 + json_len;
        assert_eq!(word(bytes, at + 4), super::CHUNK_BIN);
        let bin = &bytes[at + 8..at + 8 + word(bytes, at) as usize];
        let prim = &doc["meshes"][0]["primitives"][0];
        let mut out = BTreeMap::new();
        for (semantic, index) in prim["attributes"].as_object().unwrap() {
            let acc = &doc["accessors"][index.as_u64().unwrap() as usize];
            assert_eq!(acc["componentType"], super::COMPONENT_FLOAT);
            let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
            let (off, len) =
                (view["byteOffset"].as_u64().unwrap(), view["byteLength"].as_u64().unwrap());
            let data = &bin[off as usize..(off + len) as usize];
            let floats = data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            out.insert(semantic.clone(), floats);
        }
        (doc, out)
    }
}
