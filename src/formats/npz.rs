//! numpy `.npy` arrays and `.npz` archives (a zip of `.npy` entries, as `numpy.savez`
//! writes them), little-endian, C order, of the dtypes f2/f4/f8, i1/i2/i4/i8, u1 and b1.
//! Object arrays (pickled) are refused. Used to read reference fixtures and user arrays.

use std::io::{Cursor, Read};
use std::path::{Path, PathBuf};

use super::array::{Array, DType};

/// A malformed `.npy`/`.npz` file, naming the file and the array.
#[derive(Debug, thiserror::Error)]
#[error("{}: {msg}", path.display())]
pub struct Error {
    /// The file.
    pub path: PathBuf,
    /// What is wrong (prefixed with the array name inside an `.npz`).
    pub msg: String,
}

/// Parse one `.npy` byte string (`what` prefixes error messages).
pub fn parse_npy(bytes: &[u8]) -> Result<Array, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy array (bad magic)".into());
    }
    let (hlen, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => {
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let header = bytes
        .get(start..start.saturating_add(hlen))
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or("truncated or non-text .npy header")?;
    let field = |key: &str| -> Option<&str> {
        let i = header.find(&format!("'{key}'"))? + key.len() + 2;
        Some(header[i..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr").ok_or("header has no 'descr'")?;
    let descr = descr.split('\'').nth(1).ok_or("malformed 'descr'")?;
    let (order, code) = descr.split_at(1.min(descr.len()));
    if order == ">" && !code.ends_with('1') {
        return Err(format!("big-endian dtype '{descr}' is not supported"));
    }
    let dtype = DType::from_numpy(code).ok_or_else(|| format!("unsupported dtype '{descr}'"))?;
    if field("fortran_order").is_some_and(|v| v.starts_with("True")) {
        return Err("Fortran-order arrays are not supported".into());
    }
    let shape_txt = field("shape").ok_or("header has no 'shape'")?;
    let inner = shape_txt.trim_start_matches('(');
    let inner = &inner[..inner.find(')').ok_or("malformed shape")?];
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("malformed shape '({inner})'")))
        .collect::<Result<Vec<usize>, String>>()?;
    let n = shape.iter().try_fold(1usize, |a, b| a.checked_mul(*b)).ok_or("shape overflows")?;
    let body = &bytes[start + hlen..];
    if n.checked_mul(dtype.size()).is_none_or(|need| body.len() < need) {
        return Err(format!("truncated data: shape {shape:?} needs {n} values"));
    }
    Ok(Array { dtype, shape, data: dtype.decode(body, 0..n) })
}

/// Read a `.npy` file.
pub fn read_npy(path: &Path) -> Result<Array, Error> {
    let err = |msg: String| Error { path: path.to_path_buf(), msg };
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    parse_npy(&bytes).map_err(err)
}

/// Read every array of a `.npz` file, in archive order, named without the `.npy` suffix.
pub fn read_npz(path: &Path) -> Result<Vec<(String, Array)>, Error> {
    let err = |msg: String| Error { path: path.to_path_buf(), msg };
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes.as_slice()))
        .map_err(|e| err(format!("not a readable .npz archive: {e}")))?;
    let mut out = Vec::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).map_err(|e| err(e.to_string()))?;
        let name = f.name().map_err(|e| err(e.to_string()))?.trim_end_matches(".npy").to_string();
        let mut buf = Vec::new();
        f.read_to_end(&mut buf).map_err(|e| err(format!("{name}: {e}")))?;
        out.push((name.clone(), parse_npy(&buf).map_err(|m| err(format!("{name}: {m}")))?));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::array::Data;

    fn npy(descr: &str, shape: &str, body: &[u8]) -> Vec<u8> {
        let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        h.push_str(&" ".repeat((64 - (11 + h.len()) % 64) % 64));
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(h.len() as u16).to_le_bytes());
        b.extend_from_slice(h.as_bytes());
        b.extend_from_slice(body);
        b
    }

    #[test]
    fn arrays_of_each_kind_parse() {
        let a = parse_npy(&npy(
            "<i8",
            "(2,)",
            &[1, 0, 0, 0, 0, 0, 0, 0, 254, 255, 255, 255, 255, 255, 255, 255],
        ))
        .unwrap();
        assert_eq!((a.shape.clone(), a.data), (vec![2], Data::I64(vec![1, -2])));
        let a = parse_npy(&npy("|b1", "(1, 2)", &[1, 0])).unwrap();
        assert_eq!((a.shape.clone(), a.data), (vec![1, 2], Data::Bool(vec![true, false])));
        let a = parse_npy(&npy("<f8", "()", &1.5f64.to_le_bytes())).unwrap();
        assert_eq!((a.shape.clone(), a.data), (vec![], Data::F64(vec![1.5])));
        let e = parse_npy(&npy("<f4", "(3,)", &[0; 8])).unwrap_err();
        assert_eq!(e, "truncated data: shape [3] needs 3 values");
        let e = parse_npy(&npy("|O", "(3,)", &[0; 8])).unwrap_err();
        assert_eq!(e, "unsupported dtype '|O'");
    }
}
