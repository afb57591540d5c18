//! The 3DGS PLY file of one frame (binary little-endian, the layout of the reference
//! `GaussianModel.save_ply` that splat viewers read).
//!
//! One `vertex` element of N rows, all `float`: `x y z`, `nx ny nz` (zeros), `f_dc_0..2`,
//! `f_rest_0..3K-1` channel-major (`f_rest[c·K + k]` is coefficient k+1 of channel c, while
//! [`Splats::sh_rest`] is `[K, 3]`), `opacity` as a logit, `scale_0..2` as natural logs,
//! `rot_0..3` the unit quaternion `w x y z`. Opacities are clamped to [1e-6, 1 − 1e-6] and
//! scales to at least 1e-12 first, so that the file holds no infinities.

use super::splats::Splats;

/// Smallest distance of an opacity from 0 or 1 before its logit is taken.
pub const OPACITY_EPS: f64 = 1e-6;
/// Smallest scale before its log is taken.
pub const MIN_SCALE: f64 = 1e-12;

/// Names of the vertex properties, in file order, for `num_rest` higher SH coefficients.
pub fn property_names(num_rest: usize) -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"].map(String::from).into();
    names.extend((0..3).map(|c| format!("f_dc_{c}")));
    names.extend((0..3 * num_rest).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// The PLY file of `s`.
pub fn encode(s: &Splats) -> Vec<u8> {
    let k = s.num_rest();
    let names = property_names(k);
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {}\n", s.len());
    for name in &names {
        out.push_str(&format!("property float {name}\n"));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    bytes.reserve(s.len() * names.len() * 4);
    let mut row = Vec::with_capacity(names.len());
    for i in 0..s.len() {
        row.clear();
        row.extend(s.position[i]);
        row.extend([0.0; 3]);
        row.extend(s.f_dc[i]);
        let rest = &s.sh_rest[i * 3 * k..(i + 1) * 3 * k];
        for c in 0..3 {
            row.extend((0..k).map(|j| rest[j * 3 + c]));
        }
        let o = (s.opacity[i] as f64).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
        row.push((o / (1.0 - o)).ln() as f32);
        row.extend(s.scale[i].map(|v| (v as f64).max(MIN_SCALE).ln() as f32));
        row.extend(s.rotation[i]);
        for v in &row {
            bytes.extend(v.to_le_bytes());
        }
    }
    bytes
}

#[cfg(test)]
pub(crate) mod read {
    //! A reader of the files [`super::encode`] writes (float properties only), for tests.

    /// Property names and rows of a binary little-endian PLY with one float `vertex` element.
    pub fn decode(bytes: &[u8]) -> (Vec<String>, Vec<Vec<f32>>) {
        let end = b"end_header\n";
        let at = bytes.windows(end.len()).position(|w| w == end).expect("end_header") + end.len();
        let header = std::str::from_utf8(&bytes[..at]).unwrap();
        let mut lines = header.lines();
        assert_eq!(lines.next(), Some("ply"));
        assert_eq!(lines.next(), Some("format binary_little_endian 1.0"));
        let n: usize =
            lines.next().unwrap().strip_prefix("element vertex ").unwrap().parse().unwrap();
        let names: Vec<String> =
            lines.filter_map(|l| l.strip_prefix("property float ").map(String::from)).collect();
        let body = &bytes[at..];
        assert_eq!(body.len(), n * names.len() * 4, "body size");
        let floats: Vec<f32> =
            body.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        let rows = floats.chunks_exact(names.len().max(1)).map(<[f32]>::to_vec).collect();
        (names, rows)
    }
}
