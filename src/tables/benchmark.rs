//! The `benchmark` table: the paper's Table 2 / Table 3 / Table 8 numbers of a benchmark
//! run in long form, one row per (scene, method, view range), written by
//! `usplat4d benchmark` beside `benchmark.md`. Scene `mean` rows average the scenes.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float64Array, StringArray, UInt32Array};
use arrow::datatypes::{DataType, Float64Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, nullable, write_table};
use super::{Provenance, Result};

/// Marker type of the `benchmark` table.
pub struct BenchmarkTable;

impl Table for BenchmarkTable {
    const NAME: &'static str = "benchmark";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("scene", DataType::Utf8),
            field("method", DataType::Utf8),
            field("views", DataType::Utf8),
            field("images", DataType::UInt32),
            field("psnr", DataType::Float64),
            field("ssim", DataType::Float64),
            nullable("lpips", DataType::Float64),
            nullable("epe", DataType::Float64),
            nullable("pck_5", DataType::Float64),
            nullable("pck_10", DataType::Float64),
        ]))
    }
}

/// One row: a method's means over one view range of one scene (or of all scenes).
#[derive(Debug, Clone, PartialEq)]
pub struct BenchmarkRow {
    /// Scene label, or `mean` for the average over scenes.
    pub scene: String,
    /// Method label.
    pub method: String,
    /// View range label (`(0°, 60°]`, ...) or `all`.
    pub views: String,
    /// Images averaged (summed over scenes in `mean` rows).
    pub images: u32,
    /// Mean PSNR, dB.
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS, when every image has one.
    pub lpips: Option<f64>,
    /// 3D end-point error (`all` rows of evaluations that scored tracks).
    pub epe: Option<f64>,
    /// 3D PCK at 5% of the bounding-box diagonal.
    pub pck_5: Option<f64>,
    /// 3D PCK at 10%.
    pub pck_10: Option<f64>,
}

/// Write `rows` to `path` atomically (one row group).
pub fn write(path: &Path, rows: &[BenchmarkRow], provenance: &Provenance) -> Result<()> {
    let s = |f: fn(&BenchmarkRow) -> &str| -> ArrayRef {
        Arc::new(StringArray::from_iter_values(rows.iter().map(f)))
    };
    let f = |f: fn(&BenchmarkRow) -> Option<f64>| -> ArrayRef {
        Arc::new(Float64Array::from_iter(rows.iter().map(f)))
    };
    let cols: Vec<ArrayRef> = vec![
        s(|r| &r.scene),
        s(|r| &r.method),
        s(|r| &r.views),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.images))),
        f(|r| Some(r.psnr)),
        f(|r| Some(r.ssim)),
        f(|r| r.lpips),
        f(|r| r.epe),
        f(|r| r.pck_5),
        f(|r| r.pck_10),
    ];
    write_table::<BenchmarkTable>(path, provenance, [batch::<BenchmarkTable>(cols)])
}

/// Read the rows of `path`.
pub fn read(path: &Path) -> Result<Vec<BenchmarkRow>> {
    let reader = TableReader::open::<BenchmarkTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let (scene, method, views) = (c.strings("scene")?, c.strings("method")?, c.strings("views")?);
    let images = c.values::<UInt32Type>("images")?;
    let (psnr, ssim) = (c.values::<Float64Type>("psnr")?, c.values::<Float64Type>("ssim")?);
    let lpips = c.opt_values::<Float64Type>("lpips")?;
    let epe = c.opt_values::<Float64Type>("epe")?;
    let pck_5 = c.opt_values::<Float64Type>("pck_5")?;
    let pck_10 = c.opt_values::<Float64Type>("pck_10")?;
    Ok((0..b.num_rows())
        .map(|i| BenchmarkRow {
            scene: scene[i].clone(),
            method: method[i].clone(),
            views: views[i].clone(),
            images: images[i],
            psnr: psnr[i],
            ssim: ssim[i],
            lpips: lpips[i],
            epe: epe[i],
            pck_5: pck_5[i],
            pck_10: pck_10[i],
        })
        .collect())
}
