//! Invariant checks shared by the table readers: finite values, normalised quaternions,
//! unique ids and frames without gaps. Each returns the first violation with its file,
//! column and row.

use std::path::Path;

use super::{Error, Result, TableReader};

/// Tolerance on `|q| - 1` for stored quaternions.
pub const QUAT_NORM_TOL: f32 = 1e-3;

/// Every value of `column` is finite; `row0` is the file row of `values[0]`.
pub fn finite<F: Copy + Into<f64>>(
    path: &Path,
    column: &str,
    row0: u64,
    values: &[F],
) -> Result<()> {
    match values.iter().position(|v| !(*v).into().is_finite()) {
        Some(i) => Err(Error::Value {
            path: path.to_path_buf(),
            column: column.to_string(),
            row: row0 + i as u64,
            msg: format!("non-finite value {}", values[i].into()),
        }),
        None => Ok(()),
    }
}

/// Every item of a list column stored flattened, `width` items per row (`values` is
/// `[rows, width]`), is finite; the message names the row and the item within it.
pub fn finite_items<F: Copy + Into<f64>>(
    path: &Path,
    column: &str,
    row0: u64,
    values: &[F],
    width: usize,
) -> Result<()> {
    match values.iter().position(|v| !(*v).into().is_finite()) {
        Some(i) => Err(Error::Value {
            path: path.to_path_buf(),
            column: column.to_string(),
            row: row0 + (i / width) as u64,
            msg: format!("non-finite value {} (item {} of {width})", values[i].into(), i % width),
        }),
        None => Ok(()),
    }
}

/// Every value lies in `[lo, hi]`.
pub fn in_range(
    path: &Path,
    column: &str,
    row0: u64,
    values: &[f32],
    lo: f32,
    hi: f32,
) -> Result<()> {
    match values.iter().position(|v| !(lo..=hi).contains(v)) {
        Some(i) => Err(Error::Value {
            path: path.to_path_buf(),
            column: column.to_string(),
            row: row0 + i as u64,
            msg: format!("value {} outside [{lo}, {hi}]", values[i]),
        }),
        None => Ok(()),
    }
}

/// Quaternions `(w, x, y, z)` given as four columns are normalised within [`QUAT_NORM_TOL`].
pub fn unit_quaternions(
    path: &Path,
    row0: u64,
    w: &[f32],
    x: &[f32],
    y: &[f32],
    z: &[f32],
) -> Result<()> {
    for i in 0..w.len() {
        let n = (w[i] * w[i] + x[i] * x[i] + y[i] * y[i] + z[i] * z[i]).sqrt();
        if n.is_nan() || (n - 1.0).abs() > QUAT_NORM_TOL {
            return Err(Error::Value {
                path: path.to_path_buf(),
                column: "qw,qx,qy,qz".into(),
                row: row0 + i as u64,
                msg: format!(
                    "quaternion ({}, {}, {}, {}) has norm {n}, expected 1",
                    w[i], x[i], y[i], z[i]
                ),
            });
        }
    }
    Ok(())
}

/// Ids are unique; reports the row of the first repeat.
pub fn unique_ids(path: &Path, column: &str, row0: u64, ids: &[u32]) -> Result<()> {
    let mut seen = std::collections::HashMap::with_capacity(ids.len());
    for (i, id) in ids.iter().enumerate() {
        if let Some(first) = seen.insert(*id, i) {
            return Err(Error::Value {
                path: path.to_path_buf(),
                column: column.to_string(),
                row: row0 + i as u64,
                msg: format!("duplicate id {id} (first at row {})", row0 + first as u64),
            });
        }
    }
    Ok(())
}

/// The frame column of row group `group` holds the single value `group` (per-frame tables
/// store frame t in row group t, so frames run 0..T-1 without gaps).
pub fn frame_column(path: &Path, group: usize, row0: u64, frames: &[u32]) -> Result<()> {
    match frames.iter().position(|f| *f as usize != group) {
        Some(i) => Err(Error::Frame {
            path: path.to_path_buf(),
            frame: group as u64,
            msg: format!(
                "row {} has frame {}, expected {group} (frames must be 0..T-1 without gaps, one row group each)",
                row0 + i as u64,
                frames[i]
            ),
        }),
        None => Ok(()),
    }
}

/// Every row group of a per-frame table holds `rows` rows; `expected` says what they are
/// (e.g. "one per Gaussian (N)") for the message.
pub fn rows_per_frame(r: &TableReader, rows: usize, expected: &str) -> Result<()> {
    match (0..r.num_row_groups()).find(|&g| r.row_group_rows(g) != rows as u64) {
        Some(g) => Err(Error::Frame {
            path: r.path().into(),
            frame: g as u64,
            msg: format!("{} rows, expected {expected}", r.row_group_rows(g)),
        }),
        None => Ok(()),
    }
}

/// The id column of one frame repeats `expected` row by row (`expected(i)` is row i's id);
/// `why` completes the message, e.g. "ids run 0..M-1 in every frame".
pub fn ids_in_order(
    path: &Path,
    column: &str,
    row0: u64,
    ids: &[u32],
    expected: impl Fn(usize) -> u32,
    why: &str,
) -> Result<()> {
    match ids.iter().enumerate().find(|(i, id)| **id != expected(*i)) {
        Some((i, id)) => Err(Error::Value {
            path: path.into(),
            column: column.into(),
            row: row0 + i as u64,
            msg: format!("id {id} where {} was expected ({why})", expected(i)),
        }),
        None => Ok(()),
    }
}
