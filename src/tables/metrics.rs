//! The `metrics` table: one row per evaluated image (an eval camera at one frame) with its
//! PSNR, SSIM and LPIPS, written by `usplat4d evaluate` as one row group in the scene's
//! camera-table order, read by `evaluate --compare` and by reports.
//!
//! PSNR may be `+inf` (identical images, or an empty mask); it is never NaN. `lpips` is
//! null when the LPIPS weights were not installed. With `masked` the three values are
//! DyCheck's mPSNR / mSSIM / mLPIPS over the eval camera's mask.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, Float32Array, Float64Array, StringArray, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Float64Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, nullable, write_table};
use super::{Error, Provenance, Result};

/// Marker type of the `metrics` table.
pub struct MetricsTable;

impl Table for MetricsTable {
    const NAME: &'static str = "metrics";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("scene", DataType::Utf8),
            field("method", DataType::Utf8),
            field("camera", DataType::Utf8),
            field("frame", DataType::UInt32),
            nullable("angle_offset_deg", DataType::Float32),
            field("psnr", DataType::Float64),
            field("ssim", DataType::Float64),
            nullable("lpips", DataType::Float64),
            field("masked", DataType::Boolean),
        ]))
    }
}

/// One evaluated image.
#[derive(Debug, Clone, PartialEq)]
pub struct MetricRow {
    /// Scene label (the scene directory's name).
    pub scene: String,
    /// Method label.
    pub method: String,
    /// Eval camera name.
    pub camera: String,
    /// Frame index of the image.
    pub frame: u32,
    /// Horizontal angular offset of the camera from the training camera, degrees.
    pub angle_offset_deg: Option<f32>,
    /// PSNR (dB), or mPSNR when `masked`.
    pub psnr: f64,
    /// SSIM, or mSSIM when `masked`.
    pub ssim: f64,
    /// LPIPS (AlexNet v0.1), or mLPIPS; `None` without weights.
    pub lpips: Option<f64>,
    /// Whether the metrics are masked by the eval camera's mask.
    pub masked: bool,
}

/// Write `rows` to `path` atomically (one row group).
pub fn write(path: &Path, rows: &[MetricRow], provenance: &Provenance) -> Result<()> {
    let s = |f: fn(&MetricRow) -> &str| -> ArrayRef {
        Arc::new(StringArray::from_iter_values(rows.iter().map(f)))
    };
    let cols: Vec<ArrayRef> = vec![
        s(|r| &r.scene),
        s(|r| &r.method),
        s(|r| &r.camera),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.frame))),
        Arc::new(Float32Array::from_iter(rows.iter().map(|r| r.angle_offset_deg))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.psnr))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.ssim))),
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.lpips))),
        Arc::new(BooleanArray::from_iter(rows.iter().map(|r| Some(r.masked)))),
    ];
    write_table::<MetricsTable>(path, provenance, [batch::<MetricsTable>(cols)])
}

/// Read and validate the rows of `path`.
pub fn read(path: &Path) -> Result<Vec<MetricRow>> {
    let reader = TableReader::open::<MetricsTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let scene = c.strings("scene")?;
    let method = c.strings("method")?;
    let camera = c.strings("camera")?;
    let frame = c.values::<UInt32Type>("frame")?;
    let angle = c.opt_values::<Float32Type>("angle_offset_deg")?;
    let psnr = c.values::<Float64Type>("psnr")?;
    let ssim = c.values::<Float64Type>("ssim")?;
    let lpips = c.opt_values::<Float64Type>("lpips")?;
    let masked = c.bools("masked")?;
    let bad = |column: &str, row: usize, msg: String| Error::Value {
        path: path.to_path_buf(),
        column: column.into(),
        row: row as u64,
        msg,
    };
    let mut seen = std::collections::HashMap::new();
    let mut rows = Vec::with_capacity(b.num_rows());
    for i in 0..b.num_rows() {
        if psnr[i].is_nan() || psnr[i] == f64::NEG_INFINITY {
            return Err(bad("psnr", i, format!("value {} (expected a number or +inf)", psnr[i])));
        }
        if ssim[i].is_nan() || ssim[i].abs() > 1.0 {
            return Err(bad("ssim", i, format!("value {} outside [-1, 1]", ssim[i])));
        }
        if let Some(l) = lpips[i]
            && !(l.is_finite() && l >= 0.0)
        {
            return Err(bad("lpips", i, format!("value {l} (expected finite and >= 0)")));
        }
        if let Some(a) = angle[i]
            && !a.is_finite()
        {
            return Err(bad("angle_offset_deg", i, format!("non-finite value {a}")));
        }
        if let Some(first) =
            seen.insert((scene[i].clone(), method[i].clone(), camera[i].clone(), frame[i]), i)
        {
            return Err(bad(
                "camera",
                i,
                format!("camera '{}' frame {} repeats row {first}", camera[i], frame[i]),
            ));
        }
        rows.push(MetricRow {
            scene: scene[i].clone(),
            method: method[i].clone(),
            camera: camera[i].clone(),
            frame: frame[i],
            angle_offset_deg: angle[i],
            psnr: psnr[i],
            ssim: ssim[i],
            lpips: lpips[i],
            masked: masked[i],
        });
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(camera: &str, frame: u32, psnr: f64) -> MetricRow {
        MetricRow {
            scene: "s".into(),
            method: "m".into(),
            camera: camera.into(),
            frame,
            angle_offset_deg: Some(30.0),
            psnr,
            ssim: 0.9,
            lpips: None,
            masked: false,
        }
    }

    #[test]
    fn round_trip_keeps_inf_and_nulls() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("metrics.parquet");
        let mut rows = vec![row("cam01", 0, f64::INFINITY), row("cam01", 1, 20.5)];
        rows[1].lpips = Some(0.25);
        rows[1].angle_offset_deg = None;
        write(&p, &rows, &Provenance::default()).unwrap();
        assert_eq!(read(&p).unwrap(), rows);
    }

    #[test]
    fn bad_values_name_column_and_row() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("metrics.parquet");
        write(&p, &[row("cam01", 0, 20.0), row("cam01", 1, f64::NAN)], &Provenance::default())
            .unwrap();
        let e = read(&p).unwrap_err().to_string();
        assert_eq!(
            e,
            format!("{}: column 'psnr', row 1: value NaN (expected a number or +inf)", p.display())
        );
        write(&p, &[row("cam01", 0, 20.0), row("cam01", 0, 21.0)], &Provenance::default()).unwrap();
        let e = read(&p).unwrap_err().to_string();
        assert_eq!(
            e,
            format!(
                "{}: column 'camera', row 1: camera 'cam01' frame 0 repeats row 0",
                p.display()
            )
        );
    }
}
