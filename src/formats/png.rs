//! 8-bit PNG files (RGB, RGBA, grey). In memory an image is [`Image`]: `[H, W, C]` row-major
//! f32 values in [0, 1] (sRGB-encoded values divided by 255, as the evaluation protocols use
//! them).

use std::path::Path;

use image::ImageEncoder;

use super::Result;
use crate::util::fs::{IoError, PathError, write_atomic};

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
        .map_err(IoError::at(path))?
        .with_guessed_format()
        .map_err(IoError::at(path))?
        .decode()
        .map_err(PathError::at(path))?;
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
    .map_err(PathError::at(path))?;
    Ok(write_atomic(path, &buf)?)
}

#[cfg(test)]
mod tests {
    use super::*;

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
