//! Shared Parquet machinery: atomic writers with one row group per call, provenance
//! metadata, and readers that validate the whole schema and read one row group at a time.
//!
//! Writers go to a temporary file in the destination directory, are closed explicitly and
//! then renamed into place, so a killed process never leaves a file a later run trusts.
//!
//! Readers never hand parquet-rs a file it could panic on: [`load_metadata`] checks the magic
//! bytes and that every column chunk lies inside the file before anything is decoded, and
//! [`read_row_groups`] feeds the decoder through [`super::pages::CheckedPages`], which rejects
//! the corrupt pages parquet-rs 60 would panic on.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{Array, RecordBatch};
use arrow::datatypes::{DataType, Field, SchemaRef};
use bytes::Bytes;
use parquet::arrow::arrow_reader::{ArrowReaderMetadata, ParquetRecordBatchReader, RowGroups};
use parquet::arrow::{ArrowWriter, ProjectionMask, parquet_to_arrow_field_levels};
use parquet::basic::{Compression, ZstdLevel};
use parquet::column::page::{PageIterator, PageReader};
use parquet::file::metadata::{KeyValue, ParquetMetaData, RowGroupMetaData};
use parquet::file::properties::WriterProperties;
use parquet::file::reader::ChunkReader;
use parquet::file::serialized_reader::SerializedPageReader;

use super::pages::CheckedPages;
use super::{Error, Result};
use crate::util::fs::{IoError, PathError};

/// Metadata key naming the table kind (e.g. `trajectories`).
pub const KEY_TABLE: &str = "usplat4d.table";
/// Metadata key of the table's schema version.
pub const KEY_SCHEMA_VERSION: &str = "usplat4d.schema_version";
/// Metadata key of the producing stage.
pub const KEY_STAGE: &str = "usplat4d.stage";
/// Metadata key of the tool version.
pub const KEY_TOOL_VERSION: &str = "usplat4d.tool_version";
/// Metadata key of the stage parameters (JSON).
pub const KEY_PARAMS: &str = "usplat4d.params";

/// A table kind: its name, schema version and Arrow schema.
pub trait Table {
    /// Table name, also the file stem (`<name>.parquet`) and the `data_schema/<name>.md` doc.
    const NAME: &'static str;
    /// Schema version; bump when columns change.
    const VERSION: u32;
    /// The Arrow schema.
    fn schema() -> SchemaRef;
    /// The conventional file name inside a stage directory.
    fn file_name() -> String {
        format!("{}.parquet", Self::NAME)
    }
}

/// Who produced a table: embedded in its key-value metadata.
#[derive(Debug, Clone, Default)]
pub struct Provenance {
    /// The stage (subcommand) that wrote the table.
    pub stage: String,
    /// The stage's parameters as JSON.
    pub params: serde_json::Value,
    /// Further key-value metadata written after the standard keys (e.g. a model property).
    pub metadata: Vec<(String, String)>,
}

impl Provenance {
    /// Provenance of `stage` with parameters serialised from `params`, less the output path
    /// (every key `out`, at any depth): a table's bytes do not depend on where it was written.
    pub fn new(stage: &str, params: &impl serde::Serialize) -> Self {
        fn strip_out(v: &mut serde_json::Value) {
            match v {
                serde_json::Value::Object(m) => {
                    m.remove("out");
                    m.values_mut().for_each(strip_out);
                }
                serde_json::Value::Array(a) => a.iter_mut().for_each(strip_out),
                _ => {}
            }
        }
        let mut params = serde_json::to_value(params).unwrap_or(serde_json::Value::Null);
        strip_out(&mut params);
        Provenance { stage: stage.to_string(), params, metadata: Vec::new() }
    }

    /// The same provenance with one more key-value metadata entry.
    pub fn with_metadata(mut self, key: &str, value: &str) -> Self {
        self.metadata.push((key.to_string(), value.to_string()));
        self
    }
}

/// Writes one table atomically; each [`TableWriter::write_group`] call is one row group.
pub struct TableWriter {
    path: PathBuf,
    tmp: tempfile::NamedTempFile,
    writer: ArrowWriter<File>,
    schema: SchemaRef,
}

impl TableWriter {
    /// Start writing table `T` to `path` (created or replaced on [`TableWriter::finish`]).
    pub fn create<T: Table>(path: &Path, provenance: &Provenance) -> Result<Self> {
        Self::create_named(path, T::NAME, T::VERSION, T::schema(), provenance)
    }

    /// Start writing a table given by name, version and schema (for generic tools).
    pub fn create_named(
        path: &Path,
        name: &str,
        version: u32,
        schema: SchemaRef,
        provenance: &Provenance,
    ) -> Result<Self> {
        let io = IoError::at(path);
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&dir).map_err(io)?;
        let tmp = tempfile::Builder::new()
            .prefix(".tmp-")
            .suffix(".parquet")
            .tempfile_in(&dir)
            .map_err(io)?;
        let file = tmp.reopen().map_err(io)?;
        let mut kv = vec![
            KeyValue::new(KEY_TABLE.into(), name.to_string()),
            KeyValue::new(KEY_SCHEMA_VERSION.into(), version.to_string()),
            KeyValue::new(KEY_STAGE.into(), provenance.stage.clone()),
            KeyValue::new(KEY_TOOL_VERSION.into(), crate::VERSION.to_string()),
            KeyValue::new(KEY_PARAMS.into(), provenance.params.to_string()),
        ];
        kv.extend(provenance.metadata.iter().map(|(k, v)| KeyValue::new(k.clone(), v.clone())));
        // PLAIN + zstd, no dictionaries: nearly every value of a per-Gaussian table is
        // distinct, so a dictionary only costs a hash per value before falling back (the
        // 46,444 × 121 trajectories table: 243 MB with dictionaries, 158 MB without).
        let props = WriterProperties::builder()
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(3).unwrap_or_default()))
            .set_dictionary_enabled(false)
            .set_key_value_metadata(Some(kv))
            .set_max_row_group_row_count(None)
            .set_max_row_group_bytes(None)
            .set_created_by(format!("usplat4d {}", crate::VERSION))
            .build();
        let writer =
            ArrowWriter::try_new(file, schema.clone(), Some(props)).map_err(PathError::at(path))?;
        Ok(TableWriter { path: path.to_path_buf(), tmp, writer, schema })
    }

    /// Write `batch` as one row group (one frame of a per-frame table).
    pub fn write_group(&mut self, batch: &RecordBatch) -> Result<()> {
        let pq = PathError::at(&self.path);
        if batch.schema().fields() != self.schema.fields() {
            return Err(Error::Schema {
                path: self.path.clone(),
                table: "(writer)",
                problems: format!("batch schema {:?} differs from table schema", batch.schema()),
            });
        }
        self.writer.write(batch).map_err(pq)?;
        self.writer.flush().map_err(pq)?;
        Ok(())
    }

    /// Close the file and rename it into place.
    pub fn finish(self) -> Result<()> {
        let path = self.path;
        self.writer.close().map_err(PathError::at(&path))?;
        self.tmp.as_file().sync_all().map_err(IoError::at(&path))?;
        self.tmp.persist(&path).map_err(|e| IoError { path: path.clone(), cause: e.error })?;
        Ok(())
    }
}

/// Writes a per-frame table: frames 0, 1, 2, ... one row group each, every frame with the
/// same number of rows, atomically on [`FrameWriter::finish`]. The per-frame tables
/// (trajectories, uncertainty, tracks) wrap it with their typed `write`.
pub struct FrameWriter {
    inner: TableWriter,
    rows: usize,
    next: u32,
}

impl FrameWriter {
    /// Start writing table `T` with `rows` rows per frame to `path`.
    pub fn create<T: Table>(path: &Path, rows: usize, provenance: &Provenance) -> Result<Self> {
        Ok(FrameWriter { inner: TableWriter::create::<T>(path, provenance)?, rows, next: 0 })
    }

    /// Rows per frame.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// The frame the next [`FrameWriter::write`] stores.
    pub fn next_frame(&self) -> u32 {
        self.next
    }

    /// Append the next frame's row group.
    pub fn write(&mut self, batch: &RecordBatch) -> Result<()> {
        assert_eq!(batch.num_rows(), self.rows, "every frame has the same rows");
        self.inner.write_group(batch)?;
        self.next += 1;
        Ok(())
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.inner.finish()
    }
}

/// Row group `t` of a per-frame table whose rows carry ids in `id_column`, in the order
/// `expected_id(row)` (`order` says which, for the error), with its frame column and ids
/// checked; returns the batch and its first file row (for error messages).
pub fn read_frame_group(
    reader: &TableReader,
    t: usize,
    id_column: &str,
    expected_id: impl Fn(usize) -> u32,
    order: &str,
) -> Result<(RecordBatch, u64)> {
    let path = reader.path();
    let b = reader.read_group(t)?;
    let row0 = reader.row_group_offset(t);
    let c = Columns::new(path, &b);
    super::validate::frame_column(
        path,
        t,
        row0,
        c.values::<arrow::datatypes::UInt32Type>("frame")?,
    )?;
    let ids = c.values::<arrow::datatypes::UInt32Type>(id_column)?;
    super::validate::ids_in_order(path, id_column, row0, ids, expected_id, order)?;
    Ok((b, row0))
}

/// Write a whole table of one row group per batch, atomically.
pub fn write_table<T: Table>(
    path: &Path,
    provenance: &Provenance,
    batches: impl IntoIterator<Item = RecordBatch>,
) -> Result<()> {
    let mut w = TableWriter::create::<T>(path, provenance)?;
    for b in batches {
        w.write_group(&b)?;
    }
    w.finish()
}

/// A byte source a [`TableReader`] can open more than once: a file or bytes in memory.
pub trait Source: ChunkReader + 'static {
    /// An independent handle on the same bytes.
    fn dup(&self) -> std::io::Result<Self>
    where
        Self: Sized;
}

impl Source for File {
    fn dup(&self) -> std::io::Result<Self> {
        self.try_clone()
    }
}

impl Source for Bytes {
    fn dup(&self) -> std::io::Result<Self> {
        Ok(self.clone())
    }
}

/// Reads a validated table, whole or one row group (frame) at a time.
pub struct TableReader<R: Source = File> {
    path: PathBuf,
    source: R,
    meta: ArrowReaderMetadata,
}

impl TableReader<File> {
    /// Open `path` as table `T`, validating the whole schema.
    pub fn open<T: Table>(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(IoError::at(path))?;
        Self::new::<T>(path, file)
    }
}

impl<R: Source> TableReader<R> {
    /// Read table `T` from `source`; `path` names it in errors.
    pub fn new<T: Table>(path: &Path, source: R) -> Result<Self> {
        let meta = load_metadata(path, &source)?;
        let problems = schema_problems(&T::schema(), meta.schema());
        let kv_table = meta
            .metadata()
            .file_metadata()
            .key_value_metadata()
            .and_then(|kv| kv.iter().find(|k| k.key == KEY_TABLE))
            .and_then(|k| k.value.clone());
        let mut problems = problems;
        if let Some(name) = kv_table
            && name != T::NAME
        {
            problems.insert(0, format!("it is a '{name}' table"));
        }
        if !problems.is_empty() {
            return Err(Error::Schema {
                path: path.to_path_buf(),
                table: T::NAME,
                problems: problems.join("; "),
            });
        }
        Ok(TableReader { path: path.to_path_buf(), source, meta })
    }

    /// The file this reader reads (for error messages).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Number of rows in the file.
    pub fn num_rows(&self) -> u64 {
        self.meta.metadata().file_metadata().num_rows().max(0) as u64
    }

    /// Number of row groups (frames, for per-frame tables).
    pub fn num_row_groups(&self) -> usize {
        self.meta.metadata().num_row_groups()
    }

    /// Rows in row group `i`.
    pub fn row_group_rows(&self, i: usize) -> u64 {
        self.meta.metadata().row_group(i).num_rows().max(0) as u64
    }

    /// First file row of row group `i` (for error messages).
    pub fn row_group_offset(&self, i: usize) -> u64 {
        (0..i).map(|g| self.row_group_rows(g)).sum()
    }

    /// A key-value metadata entry.
    pub fn metadata_value(&self, key: &str) -> Option<String> {
        self.meta
            .metadata()
            .file_metadata()
            .key_value_metadata()
            .and_then(|kv| kv.iter().find(|k| k.key == key))
            .and_then(|k| k.value.clone())
    }

    fn read(&self, groups: Option<Vec<usize>>) -> Result<RecordBatch> {
        let src = self.source.dup().map_err(IoError::at(&self.path))?;
        let groups = groups.unwrap_or_else(|| (0..self.num_row_groups()).collect());
        let reader = read_row_groups(&self.path, src, &self.meta, groups, 1 << 20)?;
        let schema = arrow::array::RecordBatchReader::schema(&reader);
        let mut batches = Vec::new();
        for b in reader {
            batches.push(b.map_err(PathError::at(&self.path))?);
        }
        Ok(arrow::compute::concat_batches(&schema, &batches).map_err(PathError::at(&self.path))?)
    }

    /// All rows as one batch.
    pub fn read_all(&self) -> Result<RecordBatch> {
        self.read(None)
    }

    /// The rows of row group `i` (frame `i` of a per-frame table).
    pub fn read_group(&self, i: usize) -> Result<RecordBatch> {
        if i >= self.num_row_groups() {
            return Err(Error::Frame {
                path: self.path.clone(),
                frame: i as u64,
                msg: format!("out of range: the file has {} row groups", self.num_row_groups()),
            });
        }
        self.read(Some(vec![i]))
    }
}

/// Load the footer of the Parquet file `source` (`path` names it in errors) and check that
/// every column chunk lies inside the file, before anything is decoded.
pub fn load_metadata<R: ChunkReader>(path: &Path, source: &R) -> Result<ArrowReaderMetadata> {
    let pq = PathError::at(path);
    let corrupt = |msg: String| Error::Corrupt { path: path.to_path_buf(), msg };
    let len = source.len();
    if source.get_bytes(0, 4.min(len as usize)).map_err(pq)?.as_ref() != b"PAR1" {
        return Err(corrupt("not a Parquet file (it does not start with the bytes PAR1)".into()));
    }
    let meta = ArrowReaderMetadata::load(source, Default::default()).map_err(pq)?;
    // The footer (metadata, its 4-byte length, the magic) ends the file; the pages precede it.
    let tail = source.get_bytes(len.saturating_sub(8), 4).map_err(pq)?;
    let footer = u32::from_le_bytes([tail[0], tail[1], tail[2], tail[3]]) as u64;
    let data_end = len.saturating_sub(8 + footer) as i64;
    for (g, rg) in meta.metadata().row_groups().iter().enumerate() {
        if rg.num_rows() < 0 {
            return Err(corrupt(format!("row group {g} has {} rows", rg.num_rows())));
        }
        for c in rg.columns() {
            let data = c.data_page_offset();
            let start = c.dictionary_page_offset().unwrap_or(data);
            let size = c.compressed_size();
            let inside = start >= 4
                && size > 0
                && (start..start.saturating_add(size)).contains(&data)
                && start.saturating_add(size) <= data_end;
            if !inside {
                return Err(corrupt(format!(
                    "corrupt Parquet footer: row group {g}, column '{}': pages at bytes {start}..{} (data page at {data}) lie outside the data of the file (bytes 4..{data_end})",
                    c.column_path(),
                    start.saturating_add(size),
                )));
            }
        }
    }
    Ok(meta)
}

/// A decoder over row groups `groups` of `source`, whose page readers check the pages.
pub fn read_row_groups<R: ChunkReader + 'static>(
    path: &Path,
    source: R,
    meta: &ArrowReaderMetadata,
    groups: Vec<usize>,
    batch_size: usize,
) -> Result<ParquetRecordBatchReader> {
    let pq = PathError::at(path);
    let levels = parquet_to_arrow_field_levels(
        meta.parquet_schema(),
        ProjectionMask::all(),
        Some(meta.schema().fields()),
    )
    .map_err(pq)?;
    let row_groups = CheckedRowGroups { source: Arc::new(source), meta: meta.metadata(), groups };
    Ok(ParquetRecordBatchReader::try_new_with_row_groups(&levels, &row_groups, batch_size, None)
        .map_err(pq)?)
}

/// Row groups of a file whose column chunks are read through [`CheckedPages`].
struct CheckedRowGroups<'a, R> {
    source: Arc<R>,
    meta: &'a Arc<ParquetMetaData>,
    groups: Vec<usize>,
}

impl<R: ChunkReader + 'static> RowGroups for CheckedRowGroups<'_, R> {
    fn num_rows(&self) -> usize {
        self.groups.iter().map(|&g| self.meta.row_group(g).num_rows().max(0) as usize).sum()
    }

    fn column_chunks(&self, i: usize) -> parquet::errors::Result<Box<dyn PageIterator>> {
        let mut chunks: Vec<parquet::errors::Result<Box<dyn PageReader>>> = Vec::new();
        for &g in &self.groups {
            let rg = self.meta.row_group(g);
            let pages = SerializedPageReader::new(
                self.source.clone(),
                rg.column(i),
                rg.num_rows().max(0) as usize,
                None,
            )?;
            chunks.push(Ok(Box::new(CheckedPages::new(pages, rg.column(i).column_descr_ptr()))));
        }
        Ok(Box::new(Chunks(chunks.into_iter())))
    }

    fn row_groups(&self) -> Box<dyn Iterator<Item = &RowGroupMetaData> + '_> {
        Box::new(self.groups.iter().map(|&g| self.meta.row_group(g)))
    }

    fn metadata(&self) -> &ParquetMetaData {
        self.meta
    }
}

/// The page readers of one column, one per row group.
struct Chunks(std::vec::IntoIter<parquet::errors::Result<Box<dyn PageReader>>>);

impl Iterator for Chunks {
    type Item = parquet::errors::Result<Box<dyn PageReader>>;
    fn next(&mut self) -> Option<Self::Item> {
        self.0.next()
    }
}

impl PageIterator for Chunks {}

/// Every difference between the expected and the found schema, in words.
pub fn schema_problems(expected: &SchemaRef, found: &SchemaRef) -> Vec<String> {
    let mut problems = Vec::new();
    for f in expected.fields() {
        match found.field_with_name(f.name()) {
            Err(_) => problems.push(format!(
                "missing column '{}' ({})",
                f.name(),
                type_name(f.data_type())
            )),
            Ok(g) if !same_type(f.data_type(), g.data_type()) => problems.push(format!(
                "column '{}' has type {}, expected {}",
                f.name(),
                type_name(g.data_type()),
                type_name(f.data_type())
            )),
            Ok(g) if g.is_nullable() && !f.is_nullable() => {
                problems.push(format!("column '{}' is nullable, expected non-null", f.name()))
            }
            Ok(_) => {}
        }
    }
    for g in found.fields() {
        if expected.field_with_name(g.name()).is_err() {
            problems.push(format!("unexpected column '{}'", g.name()));
        }
    }
    problems
}

fn same_type(a: &DataType, b: &DataType) -> bool {
    match (a, b) {
        (DataType::List(x), DataType::List(y)) => same_type(x.data_type(), y.data_type()),
        (DataType::FixedSizeList(x, n), DataType::FixedSizeList(y, m)) => {
            n == m && same_type(x.data_type(), y.data_type())
        }
        _ => a == b,
    }
}

/// The short type name used in `data_schema/*.md` (`f32`, `u32`, `string`, `f64[16]`, ...).
pub fn type_name(t: &DataType) -> String {
    match t {
        DataType::Boolean => "bool".into(),
        DataType::UInt8 => "u8".into(),
        DataType::UInt16 => "u16".into(),
        DataType::UInt32 => "u32".into(),
        DataType::UInt64 => "u64".into(),
        DataType::Int32 => "i32".into(),
        DataType::Int64 => "i64".into(),
        DataType::Float32 => "f32".into(),
        DataType::Float64 => "f64".into(),
        DataType::Utf8 => "string".into(),
        DataType::List(f) => format!("list<{}>", type_name(f.data_type())),
        DataType::FixedSizeList(f, n) => format!("{}[{n}]", type_name(f.data_type())),
        other => format!("{other}"),
    }
}

/// A non-null field.
pub fn field(name: &str, t: DataType) -> Field {
    Field::new(name, t, false)
}

/// A nullable field.
pub fn nullable(name: &str, t: DataType) -> Field {
    Field::new(name, t, true)
}

/// `f32[n]` / `f64[n]` fixed-size list type with non-null items.
pub fn fixed_list(item: DataType, n: i32) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", item, false)), n)
}

/// `list<item>` type with non-null items.
pub fn list(item: DataType) -> DataType {
    DataType::List(Arc::new(Field::new("item", item, false)))
}

/// Typed column access with errors naming the file and column.
pub struct Columns<'a> {
    path: &'a Path,
    batch: &'a RecordBatch,
}

impl<'a> Columns<'a> {
    /// Wrap `batch` read from `path`.
    pub fn new(path: &'a Path, batch: &'a RecordBatch) -> Self {
        Columns { path, batch }
    }

    /// Column `name` downcast to array type `A`.
    pub fn get<A: Array + 'static>(&self, name: &str) -> Result<&'a A> {
        let col = self.batch.column_by_name(name).ok_or_else(|| Error::Schema {
            path: self.path.to_path_buf(),
            table: "(reader)",
            problems: format!("missing column '{name}'"),
        })?;
        col.as_any().downcast_ref::<A>().ok_or_else(|| Error::Schema {
            path: self.path.to_path_buf(),
            table: "(reader)",
            problems: format!("column '{name}' has type {}", type_name(col.data_type())),
        })
    }

    /// A non-null primitive column's values.
    pub fn values<P: arrow::datatypes::ArrowPrimitiveType>(
        &self,
        name: &str,
    ) -> Result<&'a [P::Native]> {
        let a = self.get::<arrow::array::PrimitiveArray<P>>(name)?;
        self.no_nulls(name, a)?;
        Ok(a.values())
    }

    /// A non-null boolean column as `Vec<bool>`.
    pub fn bools(&self, name: &str) -> Result<Vec<bool>> {
        let a = self.get::<arrow::array::BooleanArray>(name)?;
        self.no_nulls(name, a)?;
        Ok(a.values().iter().collect())
    }

    /// A non-null string column as owned strings.
    pub fn strings(&self, name: &str) -> Result<Vec<String>> {
        let a = self.get::<arrow::array::StringArray>(name)?;
        self.no_nulls(name, a)?;
        Ok(a.iter().map(|s| s.unwrap_or_default().to_string()).collect())
    }

    /// A nullable string column.
    pub fn opt_strings(&self, name: &str) -> Result<Vec<Option<String>>> {
        let a = self.get::<arrow::array::StringArray>(name)?;
        Ok(a.iter().map(|s| s.map(str::to_string)).collect())
    }

    /// A nullable primitive column.
    pub fn opt_values<P: arrow::datatypes::ArrowPrimitiveType>(
        &self,
        name: &str,
    ) -> Result<Vec<Option<P::Native>>> {
        let a = self.get::<arrow::array::PrimitiveArray<P>>(name)?;
        Ok(a.iter().collect())
    }

    /// A non-null fixed-size list column of `f64`, flattened `[rows * n]`.
    pub fn fixed_f64(&self, name: &str, n: usize) -> Result<&'a [f64]> {
        let a = self.get::<arrow::array::FixedSizeListArray>(name)?;
        self.no_nulls(name, a)?;
        let v =
            a.values().as_any().downcast_ref::<arrow::array::Float64Array>().ok_or_else(|| {
                Error::Schema {
                    path: self.path.to_path_buf(),
                    table: "(reader)",
                    problems: format!("column '{name}' items are not f64"),
                }
            })?;
        let off = a.offset() * n;
        Ok(&v.values()[off..off + a.len() * n])
    }

    fn no_nulls(&self, name: &str, a: &dyn Array) -> Result<()> {
        if let Some(nulls) = a.logical_nulls()
            && let Some(row) = (0..a.len()).find(|&i| nulls.is_null(i))
        {
            return Err(Error::Value {
                path: self.path.to_path_buf(),
                column: name.to_string(),
                row: row as u64,
                msg: "null value in a non-null column".into(),
            });
        }
        Ok(())
    }
}

/// Build a [`RecordBatch`] of table `T` from columns in schema order.
pub fn batch<T: Table>(columns: Vec<arrow::array::ArrayRef>) -> RecordBatch {
    RecordBatch::try_new(T::schema(), columns).expect("columns built to match the table schema")
}
