//! The `training_log` table: one row per optimisation step of `usplat4d optimize` (loss
//! terms, Gaussian count, learning rates, wall time), written beside the trained model.
//!
//! One row group. Loss terms and learning-rate groups are fixed columns
//! ([`LOSS_TERMS`], [`LR_GROUPS`]); a term the run's recipe does not use is null.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, Float64Array, UInt32Array};
use arrow::datatypes::{DataType, Field, Float32Type, Float64Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, nullable, write_table};
use super::{Provenance, Result};

/// Loss terms with a `loss_<term>` column, in column order (see `data_schema/training_log.md`).
pub const LOSS_TERMS: &[&str] = &[
    "rgb",
    "mask",
    "depth",
    "track",
    "key_anchor",
    "nonkey_anchor",
    "nonkey_dqb",
    "nonkey_dqb_rotation",
    "nonkey_dweight",
    "nonkey_offset",
    "key_isometry",
    "key_rigidity",
    "key_rotation",
    "key_rigidity_long",
    "key_rigidity_10",
    "nonkey_isometry",
    "nonkey_rigidity",
    "nonkey_rotation",
    "knn_isometry",
    "knn_rigidity",
    "velocity",
    "acceleration",
];

/// Adam groups with an `lr_<group>` column, in column order.
pub const LR_GROUPS: &[&str] =
    &["position", "rotation", "scale", "opacity", "color", "sh_rest", "graph", "lengths"];

/// Marker type of the `training_log` table.
pub struct TrainingLogTable;

impl Table for TrainingLogTable {
    const NAME: &'static str = "training_log";
    /// 2: `loss_nonkey_dweight`, `loss_nonkey_offset`; 3: `loss_nonkey_isometry`,
    /// `loss_nonkey_rigidity`, `loss_nonkey_rotation`.
    const VERSION: u32 = 3;
    fn schema() -> SchemaRef {
        let mut f: Vec<Field> = vec![
            field("step", DataType::UInt32),
            field("num_gaussians", DataType::UInt32),
            field("seconds", DataType::Float64),
            field("loss", DataType::Float64),
        ];
        f.extend(LOSS_TERMS.iter().map(|t| nullable(&format!("loss_{t}"), DataType::Float64)));
        f.extend(LR_GROUPS.iter().map(|g| nullable(&format!("lr_{g}"), DataType::Float32)));
        Arc::new(Schema::new(f))
    }
}

/// One step of the log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogRow {
    /// Step index 0..steps-1.
    pub step: u32,
    /// Gaussians in the model after the step.
    pub num_gaussians: u32,
    /// Wall-clock seconds of the step (the only column that differs between identical runs).
    pub seconds: f64,
    /// Total loss.
    pub loss: f64,
    /// `(term, value)` for the terms the recipe uses; each must be in [`LOSS_TERMS`].
    pub terms: Vec<(String, f64)>,
    /// `(group, learning rate)`; each must be in [`LR_GROUPS`].
    pub lr: Vec<(String, f32)>,
}

/// Write `rows` to `path` atomically. A term or group without a column is a programming
/// error and panics.
pub fn write(path: &Path, rows: &[LogRow], provenance: &Provenance) -> Result<()> {
    for r in rows {
        for (t, _) in &r.terms {
            assert!(LOSS_TERMS.contains(&t.as_str()), "loss term '{t}' has no training_log column");
        }
        for (g, _) in &r.lr {
            assert!(LR_GROUPS.contains(&g.as_str()), "Adam group '{g}' has no training_log column");
        }
    }
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.step))),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.num_gaussians))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.seconds))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.loss))),
    ];
    for t in LOSS_TERMS {
        let v = rows.iter().map(|r| r.terms.iter().find(|(k, _)| k == t).map(|(_, v)| *v));
        cols.push(Arc::new(Float64Array::from_iter(v)));
    }
    for g in LR_GROUPS {
        let v = rows.iter().map(|r| r.lr.iter().find(|(k, _)| k == g).map(|(_, v)| *v));
        cols.push(Arc::new(Float32Array::from_iter(v)));
    }
    write_table::<TrainingLogTable>(path, provenance, [batch::<TrainingLogTable>(cols)])
}

/// Read `path`.
pub fn read(path: &Path) -> Result<Vec<LogRow>> {
    let reader = TableReader::open::<TrainingLogTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let step = c.values::<UInt32Type>("step")?;
    let num = c.values::<UInt32Type>("num_gaussians")?;
    let seconds = c.values::<Float64Type>("seconds")?;
    let loss = c.values::<Float64Type>("loss")?;
    let mut rows: Vec<LogRow> = (0..step.len())
        .map(|i| LogRow {
            step: step[i],
            num_gaussians: num[i],
            seconds: seconds[i],
            loss: loss[i],
            ..LogRow::default()
        })
        .collect();
    for t in LOSS_TERMS {
        for (r, v) in rows.iter_mut().zip(c.opt_values::<Float64Type>(&format!("loss_{t}"))?) {
            if let Some(v) = v {
                r.terms.push((t.to_string(), v));
            }
        }
    }
    for g in LR_GROUPS {
        for (r, v) in rows.iter_mut().zip(c.opt_values::<Float32Type>(&format!("lr_{g}"))?) {
            if let Some(v) = v {
                r.lr.push((g.to_string(), v));
            }
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_with_unused_terms_null() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("training_log.parquet");
        let rows = vec![
            LogRow {
                step: 0,
                num_gaussians: 10,
                seconds: 0.5,
                loss: 1.5,
                terms: vec![("rgb".into(), 1.0), ("velocity".into(), 0.5)],
                lr: vec![("position".into(), 1.6e-4)],
            },
            LogRow { step: 1, num_gaussians: 12, ..LogRow::default() },
        ];
        write(&path, &rows, &Provenance::default()).unwrap();
        assert_eq!(read(&path).unwrap(), rows);
    }
}
