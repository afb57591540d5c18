//! Page validation in front of parquet-rs's decoders: every page of a column chunk is checked
//! before it is decoded, so that a corrupt file gives an error instead of a panic inside the
//! parquet crate (parquet-rs 60, found by `fuzzed_tables_never_panic`).
//!
//! Rejected: a dictionary-encoded data page without a dictionary page before it ("Decoder for
//! dict should have been set"); encodings other than PLAIN, RLE and dictionary (corrupt
//! BYTE_STREAM_SPLIT and DELTA pages panic; no writer of our tables uses them); level
//! sections longer than the page (V2 lengths and V1 BIT_PACKED levels are sliced unchecked);
//! a PLAIN byte-array data or dictionary page with no values but value bytes (a division by
//! zero); and RLE / bit-packed hybrid runs whose header is not a canonical varint of at most
//! 5 bytes (a run header of 11 bytes overflows a shift) or whose values run past the end of
//! their section (the packed definition-level decoder slices out of bounds). Writers (ours,
//! pyarrow) never produce any of these.

use bytes::Bytes;
use parquet::basic::{Encoding, Type as PhysicalType};
use parquet::column::page::{Page, PageMetadata, PageReader};
use parquet::errors::ParquetError;
use parquet::schema::types::ColumnDescPtr;

/// The pages of one column chunk, each checked before it reaches the decoder.
pub struct CheckedPages<P> {
    inner: P,
    descr: ColumnDescPtr,
    dictionary: bool,
}

impl<P: PageReader> CheckedPages<P> {
    /// Check the pages of `inner`, a chunk of the column `descr`.
    pub fn new(inner: P, descr: ColumnDescPtr) -> Self {
        CheckedPages { inner, descr, dictionary: false }
    }

    /// `page` if it is safe to decode, else an error saying what is wrong with it.
    pub fn check(&mut self, page: Option<Page>) -> parquet::errors::Result<Option<Page>> {
        let corrupt = |msg: String| Err(ParquetError::General(format!("corrupt page: {msg}")));
        let Some(p) = &page else { return Ok(page) };
        let encoding = match p {
            Page::DictionaryPage { buf, num_values, .. } => {
                if *num_values == 0
                    && !buf.is_empty()
                    && self.descr.physical_type() == PhysicalType::BYTE_ARRAY
                {
                    return corrupt(format!(
                        "a byte-array dictionary of no values but {} bytes",
                        buf.len()
                    ));
                }
                self.dictionary = true;
                return Ok(page);
            }
            Page::DataPage { encoding, .. } | Page::DataPageV2 { encoding, .. } => *encoding,
        };
        let dict = matches!(encoding, Encoding::PLAIN_DICTIONARY | Encoding::RLE_DICTIONARY);
        if dict && !self.dictionary {
            return corrupt("a dictionary-encoded data page without a dictionary page".into());
        }
        if !dict && !matches!(encoding, Encoding::PLAIN | Encoding::RLE) {
            return Err(ParquetError::General(format!(
                "unsupported page encoding {encoding} (tables use PLAIN, RLE and dictionary pages)"
            )));
        }
        let (values, non_null) = match self.levels(p) {
            Ok(v) => v,
            Err(msg) => return corrupt(msg),
        };
        if encoding == Encoding::PLAIN
            && self.descr.physical_type() == PhysicalType::BYTE_ARRAY
            && non_null == 0
            && !values.is_empty()
        {
            return corrupt(format!("no values but {} bytes of byte-array values", values.len()));
        }
        let runs = match encoding {
            _ if dict => match values.first() {
                Some(&width) if width <= 32 => rle_runs(&values[1..], width),
                Some(&width) => Err(format!("dictionary index bit width {width} (at most 32)")),
                None => Ok(()),
            },
            Encoding::RLE => match prefixed(&values) {
                Some(section) => rle_runs(section, 1),
                None => Err("RLE values shorter than their length prefix".into()),
            },
            _ => Ok(()),
        };
        match runs {
            Ok(()) => Ok(page),
            Err(msg) => corrupt(msg),
        }
    }

    /// Check the level sections of data page `page` (their lengths and RLE runs); returns
    /// the values section and how many non-null values the decoder will expect.
    fn levels(&self, page: &Page) -> Result<(Bytes, u64), String> {
        let bits = |max: i16| (16 - (max.max(0) as u16).leading_zeros()) as u8;
        let (max_rep, max_def) = (self.descr.max_rep_level(), self.descr.max_def_level());
        match page {
            Page::DataPage { buf, num_values, def_level_encoding, rep_level_encoding, .. } => {
                let mut at = 0usize;
                for (max, enc, what) in [
                    (max_rep, rep_level_encoding, "repetition"),
                    (max_def, def_level_encoding, "definition"),
                ] {
                    if max == 0 {
                        continue;
                    }
                    let rest = &buf[at..];
                    at += match enc {
                        Encoding::RLE => {
                            let section = prefixed(rest)
                                .ok_or(format!("{what} levels longer than the page"))?;
                            rle_runs(section, bits(max))?;
                            4 + section.len()
                        }
                        _ => {
                            let n = (*num_values as u64 * bits(max) as u64).div_ceil(8);
                            if n > rest.len() as u64 {
                                return Err(format!("{what} levels longer than the page"));
                            }
                            n as usize
                        }
                    };
                }
                Ok((buf.slice(at..), *num_values as u64))
            }
            Page::DataPageV2 {
                buf,
                num_values,
                num_nulls,
                def_levels_byte_len,
                rep_levels_byte_len,
                ..
            } => {
                let (rep, def) = (*rep_levels_byte_len as u64, *def_levels_byte_len as u64);
                if rep + def > buf.len() as u64 {
                    return Err(format!(
                        "level sections of {rep} + {def} bytes in a page of {} bytes",
                        buf.len()
                    ));
                }
                let (rep, def) = (rep as usize, def as usize);
                if max_rep > 0 {
                    rle_runs(&buf[..rep], bits(max_rep))?;
                }
                if max_def > 0 {
                    rle_runs(&buf[rep..rep + def], bits(max_def))?;
                }
                let non_null = (*num_values as u64).saturating_sub(*num_nulls as u64);
                Ok((buf.slice(rep + def..), non_null))
            }
            Page::DictionaryPage { .. } => Ok((Bytes::new(), 0)),
        }
    }
}

/// The section after a 4-byte little-endian length prefix, if it fits in `data`.
fn prefixed(data: &[u8]) -> Option<&[u8]> {
    let len = u32::from_le_bytes(data.get(..4)?.try_into().ok()?) as usize;
    data.get(4..4usize.checked_add(len)?)
}

/// Walk the runs of an RLE / bit-packed hybrid section of `width`-bit values: every run
/// header must be a varint of at most 5 bytes (a u32, as writers produce) and every run
/// must fit in the section (writers pad bit-packed runs to whole groups of 8 values; the
/// packed definition-level decoder slices past the end of a shorter one).
fn rle_runs(data: &[u8], width: u8) -> Result<(), String> {
    let mut at = 0usize;
    while at < data.len() {
        let mut header: u64 = 0;
        let mut len = 0;
        loop {
            let Some(&byte) = data.get(at + len) else {
                return Ok(()); // a truncated header: the decoder stops there
            };
            header |= ((byte & 0x7F) as u64) << (7 * len);
            len += 1;
            if byte & 0x80 == 0 {
                break;
            }
            if len == 5 {
                return Err(format!("an RLE run header longer than 5 bytes at byte {at}"));
            }
        }
        at += len;
        if header == 0 {
            return Ok(()); // padding ends the runs, as the decoder reads it
        }
        let count = header >> 1;
        let bytes = if header & 1 == 1 {
            count.saturating_mul(width as u64) // groups of 8 values of `width` bits
        } else {
            (width as u64).div_ceil(8)
        };
        if bytes > (data.len() - at) as u64 {
            return Err(format!(
                "an RLE run at byte {} needs {bytes} bytes, {} are left",
                at - len,
                data.len() - at
            ));
        }
        at += bytes as usize;
    }
    Ok(())
}

impl<P: PageReader> Iterator for CheckedPages<P> {
    type Item = parquet::errors::Result<Page>;
    fn next(&mut self) -> Option<Self::Item> {
        self.get_next_page().transpose()
    }
}

impl<P: PageReader> PageReader for CheckedPages<P> {
    fn get_next_page(&mut self) -> parquet::errors::Result<Option<Page>> {
        let page = self.inner.get_next_page()?;
        self.check(page)
    }

    fn peek_next_page(&mut self) -> parquet::errors::Result<Option<PageMetadata>> {
        self.inner.peek_next_page()
    }

    fn skip_next_page(&mut self) -> parquet::errors::Result<()> {
        self.inner.skip_next_page()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rle_run_headers_longer_than_5_bytes_are_rejected() {
        // a 1-bit RLE run of 3 values (header 6), then padding
        assert!(rle_runs(&[6, 1, 0], 1).is_ok());
        // the same header spread over 11 bytes (non-canonical): parquet-rs overflows
        let mut long = vec![0x86];
        long.extend([0x80; 9]);
        long.push(0);
        assert!(rle_runs(&long, 1).unwrap_err().contains("longer than 5 bytes"));
        // a bit-packed run of one group of 8 two-bit values skips 2 bytes
        assert!(rle_runs(&[3, 0xFF, 0xFF, 0x86, 0x80, 0x80, 0x80, 0x80, 0x80], 2).is_err());
        assert!(rle_runs(&[3, 0xFF, 0xFF], 2).is_ok());
        // ... and must have them
        assert!(rle_runs(&[3, 0xFF], 2).unwrap_err().contains("needs 2 bytes, 1 are left"));
        assert!(rle_runs(&[2], 9).unwrap_err().contains("needs 2 bytes"));
    }

    #[test]
    fn length_prefixes_must_fit() {
        assert_eq!(prefixed(&[2, 0, 0, 0, 7, 8, 9]), Some(&[7u8, 8][..]));
        assert_eq!(prefixed(&[9, 0, 0, 0, 7]), None);
        assert_eq!(prefixed(&[0xFF, 0xFF, 0xFF, 0xFF]), None);
        assert_eq!(prefixed(&[1, 0]), None);
    }
}
