//! Dense n-dimensional arrays decoded from checkpoint and numpy files: a dtype, a C-order
//! shape and the values widened to one of five element types (f32, f64, i64, i32, bool).
//! Shared by the PyTorch reader ([`super::torch`]) and the `.npy`/`.npz` reader
//! ([`super::npz`]).

/// Element type as stored in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    /// IEEE half (decoded to f32).
    F16,
    /// bfloat16 (decoded to f32).
    BF16,
    /// f32.
    F32,
    /// f64.
    F64,
    /// u8 (decoded to i32).
    U8,
    /// i8 (decoded to i32).
    I8,
    /// i16 (decoded to i32).
    I16,
    /// i32.
    I32,
    /// i64.
    I64,
    /// bool (one byte, 0 or not).
    Bool,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::U8 | DType::I8 | DType::Bool => 1,
            DType::F16 | DType::BF16 | DType::I16 => 2,
            DType::F32 | DType::I32 => 4,
            DType::F64 | DType::I64 => 8,
        }
    }

    /// The torch name (`float32`, `int64`, `bool`, ...) used in messages.
    pub fn name(self) -> &'static str {
        match self {
            DType::F16 => "float16",
            DType::BF16 => "bfloat16",
            DType::F32 => "float32",
            DType::F64 => "float64",
            DType::U8 => "uint8",
            DType::I8 => "int8",
            DType::I16 => "int16",
            DType::I32 => "int32",
            DType::I64 => "int64",
            DType::Bool => "bool",
        }
    }

    /// The dtype of a numpy type code without its byte order (`f4`, `i8`, `b1`, ...); `None`
    /// for the codes the importers do not read.
    pub fn from_numpy(code: &str) -> Option<DType> {
        Some(match code {
            "f2" => DType::F16,
            "f4" => DType::F32,
            "f8" => DType::F64,
            "i1" => DType::I8,
            "u1" => DType::U8,
            "i2" => DType::I16,
            "i4" => DType::I32,
            "i8" => DType::I64,
            "b1" => DType::Bool,
            _ => return None,
        })
    }

    /// Decode `count` little-endian elements gathered by `index` (element positions in
    /// `bytes`; the caller has checked that every position is in range).
    pub fn decode(self, bytes: &[u8], index: impl Iterator<Item = usize>) -> Data {
        let at = |i: usize, n: usize| &bytes[i * n..i * n + n];
        match self {
            DType::F32 => Data::F32(
                index
                    .map(|i| f32::from_le_bytes(at(i, 4).try_into().unwrap_or_default()))
                    .collect(),
            ),
            DType::F64 => Data::F64(
                index
                    .map(|i| f64::from_le_bytes(at(i, 8).try_into().unwrap_or_default()))
                    .collect(),
            ),
            DType::F16 => Data::F32(
                index
                    .map(|i| f16_to_f32(u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]])))
                    .collect(),
            ),
            DType::BF16 => Data::F32(
                index
                    .map(|i| {
                        f32::from_bits(
                            (u16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]) as u32) << 16,
                        )
                    })
                    .collect(),
            ),
            DType::I64 => Data::I64(
                index
                    .map(|i| i64::from_le_bytes(at(i, 8).try_into().unwrap_or_default()))
                    .collect(),
            ),
            DType::I32 => Data::I32(
                index
                    .map(|i| i32::from_le_bytes(at(i, 4).try_into().unwrap_or_default()))
                    .collect(),
            ),
            DType::I16 => Data::I32(
                index
                    .map(|i| i16::from_le_bytes([bytes[2 * i], bytes[2 * i + 1]]) as i32)
                    .collect(),
            ),
            DType::U8 => Data::I32(index.map(|i| bytes[i] as i32).collect()),
            DType::I8 => Data::I32(index.map(|i| bytes[i] as i8 as i32).collect()),
            DType::Bool => Data::Bool(index.map(|i| bytes[i] != 0).collect()),
        }
    }
}

/// IEEE binary16 to f32 (exact).
fn f16_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f32;
    match exp {
        0 => sign * frac * 2f32.powi(-24),
        31 if frac == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + frac / 1024.0) * 2f32.powi(e - 15),
    }
}

/// Values of an array, C order.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    /// f32 (also f16 and bf16, widened).
    F32(Vec<f32>),
    /// f64.
    F64(Vec<f64>),
    /// i64.
    I64(Vec<i64>),
    /// i32 (also u8, i8, i16, widened).
    I32(Vec<i32>),
    /// bool.
    Bool(Vec<bool>),
}

/// A dense array: dtype as stored, C-order shape, values.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Element type in the file.
    pub dtype: DType,
    /// Shape, C order (empty for a scalar).
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values.
    pub data: Data,
}

impl Array {
    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    /// The values as f64 if the dtype is a float type.
    pub fn floats(&self) -> Option<Vec<f64>> {
        match &self.data {
            Data::F32(v) => Some(v.iter().map(|x| *x as f64).collect()),
            Data::F64(v) => Some(v.clone()),
            _ => None,
        }
    }

    /// The values as i64 if the dtype is an integer type.
    pub fn ints(&self) -> Option<Vec<i64>> {
        match &self.data {
            Data::I64(v) => Some(v.clone()),
            Data::I32(v) => Some(v.iter().map(|x| *x as i64).collect()),
            _ => None,
        }
    }

    /// The values if the dtype is bool.
    pub fn bools(&self) -> Option<Vec<bool>> {
        match &self.data {
            Data::Bool(v) => Some(v.clone()),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_precision_values_decode_exactly() {
        for (bits, want) in
            [(0x3c00, 1.0), (0xc000, -2.0), (0x0001, 2f32.powi(-24)), (0x7bff, 65504.0)]
        {
            assert_eq!(f16_to_f32(bits), want);
        }
        assert_eq!(f16_to_f32(0x7c00), f32::INFINITY);
        let d = DType::BF16.decode(&[0x80, 0x3f], 0..1);
        assert_eq!(d, Data::F32(vec![1.0]));
    }
}
