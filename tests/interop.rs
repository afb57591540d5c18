//! Every table opens in Python polars and pandas with the expected dtypes and values (this is
//! how users inspect intermediates). Requires `python3` with polars, pandas and pyarrow (the
//! README's set-up command and CI install them).

use std::process::Command;
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, FixedSizeListArray, ListArray, RecordBatch, StringArray,
};
use arrow::buffer::OffsetBuffer;
use arrow::datatypes::DataType;
use serde_json::Value;
use usplat4d::tables::{Provenance, TableWriter, registry};

const ROWS: usize = 3;

/// A deterministic column of `t`: row i holds a value derived from i (nulls at row 1 when
/// the field is nullable).
fn column(t: &DataType, nullable: bool) -> ArrayRef {
    let valid = |i: usize| !(nullable && i == 1);
    match t {
        DataType::Boolean => {
            Arc::new(BooleanArray::from_iter((0..ROWS).map(|i| valid(i).then_some(i % 2 == 0))))
        }
        DataType::UInt8 => Arc::new(arrow::array::UInt8Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as u8)),
        )),
        DataType::UInt32 => Arc::new(arrow::array::UInt32Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as u32)),
        )),
        DataType::UInt64 => Arc::new(arrow::array::UInt64Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as u64)),
        )),
        DataType::Int32 => Arc::new(arrow::array::Int32Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as i32)),
        )),
        DataType::Float32 => Arc::new(arrow::array::Float32Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as f32 * 0.5)),
        )),
        DataType::Float64 => Arc::new(arrow::array::Float64Array::from_iter(
            (0..ROWS).map(|i| valid(i).then_some(i as f64 * 0.25)),
        )),
        DataType::Utf8 => {
            Arc::new(StringArray::from_iter((0..ROWS).map(|i| valid(i).then(|| format!("s{i}")))))
        }
        DataType::FixedSizeList(item, n) => {
            let values = column_n(item.data_type(), ROWS * *n as usize);
            let nulls = nullable.then(|| (0..ROWS).map(valid).collect::<Vec<_>>().into());
            Arc::new(FixedSizeListArray::new(item.clone(), *n, values, nulls))
        }
        DataType::List(item) => {
            let lens: Vec<usize> = (0..ROWS).collect();
            let values = column_n(item.data_type(), lens.iter().sum());
            Arc::new(ListArray::new(item.clone(), OffsetBuffer::from_lengths(lens), values, None))
        }
        other => panic!("interop test has no generator for {other}"),
    }
}

fn column_n(t: &DataType, n: usize) -> ArrayRef {
    match t {
        DataType::Float32 => {
            Arc::new(arrow::array::Float32Array::from_iter_values((0..n).map(|i| i as f32)))
        }
        DataType::Float64 => {
            Arc::new(arrow::array::Float64Array::from_iter_values((0..n).map(|i| i as f64)))
        }
        other => panic!("interop test has no list-item generator for {other}"),
    }
}

/// The dtype names polars and pandas report for a column of `t`.
fn expected_dtypes(t: &DataType, nullable: bool) -> (String, String) {
    let pandas_int = |name: &str| if nullable { "float64".to_string() } else { name.to_string() };
    match t {
        DataType::Boolean => {
            ("Boolean".into(), if nullable { "object".into() } else { "bool".into() })
        }
        DataType::UInt8 => ("UInt8".into(), pandas_int("uint8")),
        DataType::UInt32 => ("UInt32".into(), pandas_int("uint32")),
        DataType::UInt64 => ("UInt64".into(), pandas_int("uint64")),
        DataType::Int32 => ("Int32".into(), pandas_int("int32")),
        DataType::Float32 => ("Float32".into(), "float32".into()),
        DataType::Float64 => ("Float64".into(), "float64".into()),
        DataType::Utf8 => ("String".into(), "str".into()),
        DataType::FixedSizeList(item, n) => (
            format!("Array({}, shape=({n},))", expected_dtypes(item.data_type(), false).0),
            "object".into(),
        ),
        DataType::List(item) => {
            (format!("List({})", expected_dtypes(item.data_type(), false).0), "object".into())
        }
        other => panic!("no expectation for {other}"),
    }
}

fn expected_values(a: &ArrayRef) -> Vec<Value> {
    (0..a.len()).map(|i| to_json(a, i)).collect()
}

fn to_json(a: &ArrayRef, i: usize) -> Value {
    if a.is_null(i) {
        return Value::Null;
    }
    let num = |x: f64| serde_json::Number::from_f64(x).map(Value::Number).unwrap_or(Value::Null);
    match a.data_type() {
        DataType::Boolean => Value::Bool(a.as_boolean().value(i)),
        DataType::Utf8 => Value::String(a.as_string::<i32>().value(i).to_string()),
        DataType::FixedSizeList(..) => {
            let v = a.as_fixed_size_list().value(i);
            Value::Array((0..v.len()).map(|k| to_json(&v, k)).collect())
        }
        DataType::List(_) => {
            let v = a.as_list::<i32>().value(i);
            Value::Array((0..v.len()).map(|k| to_json(&v, k)).collect())
        }
        _ => {
            let f = arrow::compute::cast(a, &DataType::Float64).unwrap();
            num(f.as_primitive::<arrow::datatypes::Float64Type>().value(i))
        }
    }
}

fn same_number(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            (x.as_f64().unwrap() - y.as_f64().unwrap()).abs() < 1e-9
        }
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same_number(p, q))
        }
        _ => a == b,
    }
}

#[test]
fn every_table_reads_in_polars_and_pandas() {
    let dir = tempfile::tempdir().unwrap();
    let mut files = Vec::new();
    let mut expected = Vec::new();
    for kind in registry() {
        let cols: Vec<ArrayRef> =
            kind.schema.fields().iter().map(|f| column(f.data_type(), f.is_nullable())).collect();
        let batch = RecordBatch::try_new(kind.schema.clone(), cols.clone()).unwrap();
        let path = dir.path().join(format!("{}.parquet", kind.name));
        let mut w = TableWriter::create_named(
            &path,
            kind.name,
            kind.version,
            kind.schema.clone(),
            &Provenance::default(),
        )
        .unwrap();
        w.write_group(&batch).unwrap();
        w.finish().unwrap();
        files.push(path.to_string_lossy().into_owned());
        expected.push((path, kind.schema.clone(), cols));
    }
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/read_tables.py");
    let out = Command::new("python3")
        .arg(&script)
        .args(&files)
        .output()
        .expect("python3 must be installed");
    assert!(
        out.status.success(),
        "python could not read the tables (install polars, pandas and pyarrow):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let got: Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut problems = Vec::new();
    for (path, schema, cols) in expected {
        let g = &got[path.to_string_lossy().as_ref()];
        assert_eq!(g["rows"], ROWS, "{}", path.display());
        for (f, col) in schema.fields().iter().zip(&cols) {
            let (pl, pd) = expected_dtypes(f.data_type(), f.is_nullable());
            let name = f.name().as_str();
            if g["polars"][name] != pl.as_str() {
                problems.push(format!(
                    "{}.{name}: polars dtype {} expected {pl}",
                    path.display(),
                    g["polars"][name]
                ));
            }
            // pandas 3 names its string dtype "str"; pandas 2 used "object".
            let pandas_ok =
                g["pandas"][name] == pd.as_str() || (pd == "str" && g["pandas"][name] == "object");
            if !pandas_ok {
                problems.push(format!(
                    "{}.{name}: pandas dtype {} expected {pd}",
                    path.display(),
                    g["pandas"][name]
                ));
            }
            let want = expected_values(col);
            let have = g["values"][name].as_array().cloned().unwrap_or_default();
            if want.len() != have.len() || !want.iter().zip(&have).all(|(a, b)| same_number(a, b)) {
                problems.push(format!(
                    "{}.{name}: polars values {have:?} expected {want:?}",
                    path.display()
                ));
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}
