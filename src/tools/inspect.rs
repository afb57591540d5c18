//! `usplat4d inspect FILE.parquet`: schema, provenance, row count, per-column min/max/null
//! count and the first rows of any Parquet table, streamed batch by batch.

use std::fs::File;
use std::path::PathBuf;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::datatypes::DataType;

use crate::context::Context;
use crate::tables::Error;
use crate::tables::io::type_name;
use crate::util::fs::PathError;

/// Parameters of `usplat4d inspect`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct InspectParams {
    /// The Parquet file to describe.
    pub file: PathBuf,
    /// Number of leading rows to print.
    #[arg(long, default_value_t = 5)]
    #[serde(default = "default_head")]
    pub head: usize,
}

fn default_head() -> usize {
    5
}

/// Running statistics of one column.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColumnStats {
    /// Column name.
    pub name: String,
    /// Short type name (as in `data_schema/`).
    pub type_name: String,
    /// Number of nulls.
    pub nulls: u64,
    /// Smallest value, as text (`-` where not ordered, e.g. lists).
    pub min: Option<String>,
    /// Largest value, as text.
    pub max: Option<String>,
    num_min: Option<f64>,
    num_max: Option<f64>,
}

impl ColumnStats {
    fn update(&mut self, a: &ArrayRef) {
        self.nulls += a.null_count() as u64;
        let numeric: Option<Vec<f64>> = match a.data_type() {
            DataType::Boolean
            | DataType::UInt8
            | DataType::UInt16
            | DataType::UInt32
            | DataType::UInt64
            | DataType::Int32
            | DataType::Int64
            | DataType::Float32
            | DataType::Float64 => arrow::compute::cast(a, &DataType::Float64).ok().map(|c| {
                c.as_primitive::<arrow::datatypes::Float64Type>().iter().flatten().collect()
            }),
            DataType::Utf8 => {
                for s in a.as_string::<i32>().iter().flatten() {
                    if self.min.as_deref().is_none_or(|m| s < m) {
                        self.min = Some(s.to_string());
                    }
                    if self.max.as_deref().is_none_or(|m| s > m) {
                        self.max = Some(s.to_string());
                    }
                }
                None
            }
            _ => None,
        };
        if let Some(v) = numeric {
            for x in v {
                if x.is_nan() {
                    continue;
                }
                self.num_min = Some(self.num_min.map_or(x, |m| m.min(x)));
                self.num_max = Some(self.num_max.map_or(x, |m| m.max(x)));
            }
            self.min = self.num_min.map(fmt_num);
            self.max = self.num_max.map(fmt_num);
        }
    }
}

fn fmt_num(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 { format!("{x:.0}") } else { format!("{x:.6}") }
}

/// What `inspect` reports about a file.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Total rows.
    pub rows: u64,
    /// Row groups (frames of per-frame tables).
    pub row_groups: usize,
    /// Key-value metadata (`usplat4d.*` provenance among it).
    pub metadata: Vec<(String, String)>,
    /// Per-column statistics, schema order.
    pub columns: Vec<ColumnStats>,
    /// The first rows, formatted as a table.
    pub head: String,
}

/// Describe the Parquet file at `path`, reading it batch by batch.
pub fn summarize(path: &std::path::Path, head: usize) -> Result<Summary, Error> {
    let file = File::open(path).map_err(crate::util::fs::IoError::at(path))?;
    let arrow_meta = crate::tables::io::load_metadata(path, &file)?;
    let meta = arrow_meta.metadata().clone();
    let schema = arrow_meta.schema().clone();
    let groups = (0..meta.num_row_groups()).collect();
    let reader = crate::tables::io::read_row_groups(path, file, &arrow_meta, groups, 65536)?;
    let mut columns: Vec<ColumnStats> = schema
        .fields()
        .iter()
        .map(|f| ColumnStats {
            name: f.name().clone(),
            type_name: type_name(f.data_type()),
            ..Default::default()
        })
        .collect();
    let mut first: Vec<RecordBatch> = Vec::new();
    let mut taken = 0;
    for b in reader {
        let b = b.map_err(PathError::at(path))?;
        for (s, c) in columns.iter_mut().zip(b.columns()) {
            s.update(c);
        }
        if taken < head {
            let n = (head - taken).min(b.num_rows());
            first.push(b.slice(0, n));
            taken += n;
        }
    }
    let head = arrow::util::pretty::pretty_format_batches(&first)
        .map(|t| t.to_string())
        .map_err(PathError::at(path))?;
    let metadata = meta
        .file_metadata()
        .key_value_metadata()
        .map(|kv| kv.iter().map(|k| (k.key.clone(), k.value.clone().unwrap_or_default())).collect())
        .unwrap_or_default();
    Ok(Summary {
        rows: meta.file_metadata().num_rows().max(0) as u64,
        row_groups: meta.num_row_groups(),
        metadata,
        columns,
        head,
    })
}

/// Run `usplat4d inspect`: print the summary to stdout.
pub fn run(p: &InspectParams, _ctx: &Context) -> anyhow::Result<()> {
    use std::io::Write;
    let s = summarize(&p.file, p.head)?;
    let mut out = std::io::stdout().lock();
    writeln!(out, "file: {}", p.file.display())?;
    for (k, v) in &s.metadata {
        if k.starts_with("usplat4d.") {
            writeln!(out, "{}: {v}", k.trim_start_matches("usplat4d."))?;
        }
    }
    writeln!(out, "rows: {}  row groups: {}", s.rows, s.row_groups)?;
    writeln!(out, "{:<20} {:<10} {:>8} {:>16} {:>16}", "column", "type", "nulls", "min", "max")?;
    for c in &s.columns {
        writeln!(
            out,
            "{:<20} {:<10} {:>8} {:>16} {:>16}",
            c.name,
            c.type_name,
            c.nulls,
            c.min.as_deref().unwrap_or("-"),
            c.max.as_deref().unwrap_or("-")
        )?;
    }
    if p.head > 0 {
        writeln!(out, "first {} rows:\n{}", p.head.min(s.rows as usize), s.head)?;
    }
    Ok(())
}
