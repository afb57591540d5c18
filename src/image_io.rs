//! Image and array files shared by the stages: 8-bit PNG (RGB, RGBA, grey) and float32
//! `.npy` (z-depth, 0 = invalid). All writes are atomic (temporary file, then rename).
//!
//! In memory an image is [`Image`]: `[H, W, C]` row-major f32 values in [0, 1] (sRGB-encoded
//! values divided by 255, as the evaluation protocols use them).

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// Errors of reading or writing image and array files; each names the file.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// File system error.
    #[error("{}: {cause}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        cause: std::io::Error,
    },
    /// The image could not be decoded or encoded.
    #[error("{}: {cause}", path.display())]
    Image {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        cause: image::ImageError,
    },
    /// A malformed `.npy` file or an unsupported dtype or shape.
    #[error("{}: {msg}", path.display())]
    Npy {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// A float image `[H, W, C]`, values in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width W.
    pub width: usize,
    /// Height H.
    pub height: usize,
    /// Channels C (1, 3 or 4).
    pub channels: usize,
    /// Row-major `[H, W, C]` values.
    pub data: Vec<f32>,
}

impl Image {
    /// A constant image.
    pub fn filled(width: usize, height: usize, channels: usize, value: f32) -> Self {
        Image { width, height, channels, data: vec![value; width * height * channels] }
    }

    /// The value at pixel `(x, y)`, channel `c`.
    pub fn at(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[(y * self.width + x) * self.channels + c]
    }

    /// Values quantised to 8 bits (round half up, clamped), as 8-bit PNG storage does.
    pub fn to_u8(&self) -> Vec<u8> {
        self.data.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect()
    }

    /// The image quantised to 8 bits and back (DyCheck's `to_quantized_float32`).
    pub fn quantized(&self) -> Image {
        let data = self.to_u8().into_iter().map(|b| b as f32 / 255.0).collect();
        Image { data, ..*self }
    }

    /// The first three channels; RGBA is composited over `background` by its alpha.
    pub fn rgb_over(&self, background: [f32; 3]) -> Image {
        let n = self.width * self.height;
        let mut data = Vec::with_capacity(n * 3);
        for i in 0..n {
            let p = &self.data[i * self.channels..(i + 1) * self.channels];
            match self.channels {
                1 => data.extend_from_slice(&[p[0]; 3]),
                3 => data.extend_from_slice(p),
                _ => {
                    let a = p[3];
                    for c in 0..3 {
                        data.push(p[c] * a + background[c] * (1.0 - a));
                    }
                }
            }
        }
        Image { width: self.width, height: self.height, channels: 3, data }
    }

    /// Channel `c` as a single-channel image.
    pub fn channel(&self, c: usize) -> Image {
        let data = self.data.iter().skip(c).step_by(self.channels).copied().collect();
        Image { width: self.width, height: self.height, channels: 1, data }
    }
}

/// Read a PNG (grey, grey+alpha, RGB or RGBA; 8 or 16 bit) into [0, 1] floats, keeping its
/// channel count (grey+alpha becomes RGBA).
pub fn read_png(path: &Path) -> Result<Image> {
    let img = image::ImageReader::open(path)
        .map_err(|source| Error::Io { path: path.into(), cause: source })?
        .with_guessed_format()
        .map_err(|source| Error::Io { path: path.into(), cause: source })?
        .decode()
        .map_err(|source| Error::Image { path: path.into(), cause: source })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (channels, data) = match img.color().channel_count() {
        1 => (1, img.to_luma8().into_raw()),
        3 => (3, img.to_rgb8().into_raw()),
        _ => (4, img.to_rgba8().into_raw()),
    };
    Ok(Image {
        width: w,
        height: h,
        channels,
        data: data.into_iter().map(|b| b as f32 / 255.0).collect(),
    })
}

/// Write `img` as an 8-bit PNG (grey, RGB or RGBA by its channel count), atomically.
pub fn write_png(path: &Path, img: &Image) -> Result<()> {
    let color = match img.channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        _ => image::ExtendedColorType::Rgba8,
    };
    let mut buf = Vec::new();
    image::codecs::png::PngEncoder::new_with_quality(
        &mut buf,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Adaptive,
    )
    .write_image(&img.to_u8(), img.width as u32, img.height as u32, color)
    .map_err(|source| Error::Image { path: path.into(), cause: source })?;
    write_atomic(path, &buf)
}

use image::ImageEncoder;

/// Write `bytes` to `path` through a temporary file in the same directory and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let io = |source| Error::Io { path: path.into(), cause: source };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(io)?;
    let mut tmp = tempfile::Builder::new().prefix(".tmp-").tempfile_in(&dir).map_err(io)?;
    tmp.write_all(bytes).map_err(io)?;
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}

/// Write a float32 array of `shape` (C order) as `.npy` version 1.0, atomically.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(Error::Npy {
            path: path.into(),
            msg: format!("shape {shape:?} does not hold {} values", data.len()),
        });
    }
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_str =
        if shape.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_str}, }}");
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut buf = Vec::with_capacity(10 + header.len() + data.len() * 4);
    buf.extend_from_slice(b"\x93NUMPY\x01\x00");
    buf.extend_from_slice(&(header.len() as u16).to_le_bytes());
    buf.extend_from_slice(header.as_bytes());
    for v in data {
        buf.extend_from_slice(&v.to_le_bytes());
    }
    write_atomic(path, &buf)
}

/// Read a little-endian float32 or float64 C-order `.npy` file: `(shape, values as f32)`.
pub fn read_npy_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
    let npy = |msg: String| Error::Npy { path: path.into(), msg };
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|mut f| f.read_to_end(&mut bytes))
        .map_err(|source| Error::Io { path: path.into(), cause: source })?;
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(npy("not a .npy file (bad magic)".into()));
    }
    let (hlen, hstart) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => {
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(npy(format!("unsupported .npy version {v}"))),
    };
    let header = bytes
        .get(hstart..hstart + hlen)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| npy("truncated or non-text header".into()))?;
    let field = |key: &str| -> Option<&str> {
        let i = header.find(&format!("'{key}'"))? + key.len() + 2;
        Some(header[i..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr").ok_or_else(|| npy("header has no 'descr'".into()))?;
    let width = if descr.starts_with("'<f4'") {
        4
    } else if descr.starts_with("'<f8'") {
        8
    } else {
        return Err(npy(format!("unsupported dtype {}", descr.split(',').next().unwrap_or(""))));
    };
    if field("fortran_order").is_some_and(|v| v.starts_with("True")) {
        return Err(npy("Fortran-order arrays are not supported".into()));
    }
    let shape_txt = field("shape").ok_or_else(|| npy("header has no 'shape'".into()))?;
    let inner = shape_txt.trim_start_matches('(');
    let inner = &inner[..inner.find(')').ok_or_else(|| npy("malformed shape".into()))?];
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| npy(format!("malformed shape '{shape_txt}'"))))
        .collect::<Result<Vec<usize>>>()?;
    let n: usize = shape.iter().product();
    let body = &bytes[hstart + hlen..];
    if body.len() < n * width {
        return Err(npy(format!(
            "truncated: shape {shape:?} needs {} bytes, file has {}",
            n * width,
            body.len()
        )));
    }
    let data = if width == 4 {
        body[..n * 4]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    } else {
        body[..n * 8]
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])) as f32)
            .collect()
    };
    Ok((shape, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_round_trip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        write_npy_f32(&p, &[2, 3, 4], &data).unwrap();
        let (shape, back) = read_npy_f32(&p).unwrap();
        assert_eq!(shape, vec![2, 3, 4]);
        assert_eq!(back, data);
        std::fs::write(&p, b"\x93NUMPY\x01\x00").unwrap();
        assert!(read_npy_f32(&p).unwrap_err().to_string().contains("a.npy"));
    }

    #[test]
    fn png_round_trip_is_8_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        let img = Image {
            width: 3,
            height: 2,
            channels: 4,
            data: (0..24).map(|i| i as f32 / 23.0).collect(),
        };
        write_png(&p, &img).unwrap();
        let back = read_png(&p).unwrap();
        assert_eq!(back, img.quantized());
    }
}
