//! Checkpoints of a training run, so that a killed run started again resumes and ends with
//! the same bytes as an uninterrupted one. One file, `OUT.ckpt/checkpoint.bin` beside the
//! output directory (the pipeline removes and trusts only the declared output), written to a
//! temporary file and renamed. It holds everything the remaining steps depend on: the
//! training state, the Adam moments and step count, the density-control accumulators, the
//! next free id, the graph's own tensors and the log rows so far. The frame order and the
//! random edge subsets are pure functions of (seed, step), so no generator state is needed.
//! A fingerprint of the resolved settings and the input files guards against resuming a
//! different run; a mismatching checkpoint is ignored (and replaced).
//!
//! Format: magic `USP4DCK1`, the 32-byte fingerprint, then little-endian fields in the order
//! of [`Checkpoint`]; vectors are a u64 length followed by their items. Both directions
//! stream through a buffer: a checkpoint holds the poses and their two Adam moments (8 GB at
//! T = 475, N = 200,000), which must not be copied whole beside the training state.

use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use super::adam::{Adam, Group};
use super::density::DensityStats;
use super::poses::Poses;
use super::state::TrainState;
use crate::tables::training_log::LogRow;

const MAGIC: &[u8; 8] = b"USP4DCK1";

/// Everything a resumed run needs.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    /// Steps completed.
    pub step: u32,
    /// Next unused `gaussian_id`.
    pub next_id: u32,
    /// The trained parameters.
    pub state: TrainState,
    /// Adam moments and step count.
    pub adam: Adam,
    /// Density-control accumulators.
    pub density: DensityStats,
    /// Named flat tensors of the graph objective.
    pub graph: Vec<(String, Vec<f32>)>,
    /// Log rows of the completed steps.
    pub log: Vec<LogRow>,
}

/// The checkpoint directory of output directory `out`: `OUT.ckpt` beside it.
pub fn dir_of(out: &Path) -> PathBuf {
    let mut name = out.file_name().map(|n| n.to_os_string()).unwrap_or_else(|| "out".into());
    name.push(".ckpt");
    out.with_file_name(name)
}

/// Path of the checkpoint file of output `out`.
pub fn path_of(out: &Path) -> PathBuf {
    dir_of(out).join("checkpoint.bin")
}

/// Fingerprint of a run: blake3 of `settings` (JSON) and of every input file's bytes.
pub fn fingerprint(settings: &serde_json::Value, inputs: &[PathBuf]) -> anyhow::Result<[u8; 32]> {
    let mut h = blake3::Hasher::new();
    h.update(settings.to_string().as_bytes());
    for p in inputs {
        let mut f = std::fs::File::open(p).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
        h.update(p.to_string_lossy().as_bytes());
        std::io::copy(&mut f, &mut h).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?;
    }
    Ok(*h.finalize().as_bytes())
}

/// Encode and write atomically to `path` (parent created).
pub fn save(path: &Path, fp: &[u8; 32], c: &Checkpoint) -> anyhow::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
    let tmp = tempfile::NamedTempFile::new_in(dir)
        .map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
    let mut e = Enc(BufWriter::with_capacity(BUFFER, tmp.as_file()));
    encode(&mut e, fp, c)
        .and_then(|_| e.0.flush())
        .and_then(|_| tmp.as_file().sync_all())
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    drop(e);
    tmp.persist(path).map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.error))?;
    Ok(())
}

/// Bytes of the read and write buffers.
const BUFFER: usize = 1 << 20;

/// Write `c` in the module's format.
fn encode(e: &mut Enc<impl Write>, fp: &[u8; 32], c: &Checkpoint) -> io::Result<()> {
    e.raw(MAGIC)?;
    e.raw(fp)?;
    e.u32(c.step)?;
    e.u32(c.next_id)?;
    let s = &c.state;
    e.u32s(&s.ids)?;
    e.bytes(&s.dynamic.iter().map(|d| *d as u8).collect::<Vec<_>>())?;
    e.u32s(&s.origin)?;
    e.u64(s.poses.frames as u64)?;
    e.f32s(s.poses.position.as_flattened())?;
    e.f32s(s.poses.rotation.as_flattened())?;
    e.f32s(s.log_scale.as_flattened())?;
    e.f32s(&s.logit_opacity)?;
    e.f32s(s.color.as_flattened())?;
    e.bytes(&[s.sh_degree])?;
    e.f32s(&s.sh_rest)?;
    e.u64(c.adam.t)?;
    e.u64(c.adam.groups.len() as u64)?;
    for g in &c.adam.groups {
        e.bytes(g.name.as_bytes())?;
        e.f32s(&[g.lr])?;
        e.f32s(&g.m)?;
        e.f32s(&g.v)?;
    }
    e.f32s(&c.density.grad)?;
    e.u32s(&c.density.count)?;
    e.u64(c.graph.len() as u64)?;
    for (name, v) in &c.graph {
        e.bytes(name.as_bytes())?;
        e.f32s(v)?;
    }
    e.u64(c.log.len() as u64)?;
    for r in &c.log {
        e.u32(r.step)?;
        e.u32(r.num_gaussians)?;
        e.f64(r.seconds)?;
        e.f64(r.loss)?;
        e.u64(r.terms.len() as u64)?;
        for (k, v) in &r.terms {
            e.bytes(k.as_bytes())?;
            e.f64(*v)?;
        }
        e.u64(r.lr.len() as u64)?;
        for (k, v) in &r.lr {
            e.bytes(k.as_bytes())?;
            e.f32s(&[*v])?;
        }
    }
    Ok(())
}

/// Read the checkpoint at `path` if it exists and belongs to the run with fingerprint `fp`.
pub fn load(path: &Path, fp: &[u8; 32]) -> anyhow::Result<Option<Checkpoint>> {
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => anyhow::bail!("{}: {e}", path.display()),
    };
    let size = file.metadata().map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?.len();
    let mut d = Dec { r: BufReader::with_capacity(BUFFER, file), left: size, error: None };
    // A read error other than the end of the file names itself; else the file is at fault.
    let fail = |d: Dec<_>, what: &str| match d
        .error
        .filter(|e| e.kind() != io::ErrorKind::UnexpectedEof)
    {
        Some(e) => anyhow::anyhow!("{}: {e}", path.display()),
        None => anyhow::anyhow!("{}: {what} (delete it to start over)", path.display()),
    };
    let mut head = [0u8; 40];
    if d.fill(&mut head).is_none() || &head[..8] != MAGIC {
        return Err(fail(d, "not a usplat4d optimize checkpoint"));
    }
    if &head[8..40] != fp {
        return Ok(None);
    }
    match decode(&mut d) {
        Some(c) => Ok(Some(c)),
        None => Err(fail(d, "truncated or corrupt checkpoint")),
    }
}

fn decode(d: &mut Dec<impl Read>) -> Option<Checkpoint> {
    let step = d.u32()?;
    let next_id = d.u32()?;
    let ids = d.u32s()?;
    let dynamic = d.bytes()?.iter().map(|b| *b != 0).collect();
    let origin = d.u32s()?;
    let frames = d.u64()? as usize;
    let n = ids.len();
    let position = d.arrays::<3>()?;
    let rotation = d.arrays::<4>()?;
    let log_scale = d.arrays::<3>()?;
    let logit_opacity = d.f32s()?;
    let color = d.arrays::<3>()?;
    let sh_degree = *d.bytes()?.first()?;
    let sh_rest = d.f32s()?;
    if position.len() != frames * n || rotation.len() != frames * n || log_scale.len() != n {
        return None;
    }
    let state = TrainState {
        ids,
        dynamic,
        origin,
        poses: Poses { frames, n, position, rotation },
        log_scale,
        logit_opacity,
        color,
        sh_degree,
        sh_rest,
    };
    let t = d.u64()?;
    let mut groups = Vec::new();
    for _ in 0..d.u64()? {
        let name = String::from_utf8(d.bytes()?).ok()?;
        let lr = *d.f32s()?.first()?;
        groups.push(Group { name, lr, m: d.f32s()?, v: d.f32s()? });
    }
    let density = DensityStats { grad: d.f32s()?, count: d.u32s()? };
    let mut graph = Vec::new();
    for _ in 0..d.u64()? {
        graph.push((String::from_utf8(d.bytes()?).ok()?, d.f32s()?));
    }
    let mut log = Vec::new();
    for _ in 0..d.u64()? {
        let mut r = LogRow {
            step: d.u32()?,
            num_gaussians: d.u32()?,
            seconds: d.f64()?,
            loss: d.f64()?,
            ..LogRow::default()
        };
        for _ in 0..d.u64()? {
            r.terms.push((String::from_utf8(d.bytes()?).ok()?, d.f64()?));
        }
        for _ in 0..d.u64()? {
            r.lr.push((String::from_utf8(d.bytes()?).ok()?, *d.f32s()?.first()?));
        }
        log.push(r);
    }
    (d.left == 0).then_some(Checkpoint {
        step,
        next_id,
        state,
        adam: Adam { t, groups },
        density,
        graph,
        log,
    })
}

/// Little-endian writer of the format's fields.
struct Enc<W: Write>(W);

impl<W: Write> Enc<W> {
    fn raw(&mut self, v: &[u8]) -> io::Result<()> {
        self.0.write_all(v)
    }
    fn u32(&mut self, v: u32) -> io::Result<()> {
        self.raw(&v.to_le_bytes())
    }
    fn u64(&mut self, v: u64) -> io::Result<()> {
        self.raw(&v.to_le_bytes())
    }
    fn f64(&mut self, v: f64) -> io::Result<()> {
        self.raw(&v.to_le_bytes())
    }
    fn bytes(&mut self, v: &[u8]) -> io::Result<()> {
        self.u64(v.len() as u64)?;
        self.raw(v)
    }
    fn u32s(&mut self, v: &[u32]) -> io::Result<()> {
        self.words(v, |x| x.to_le_bytes())
    }
    fn f32s(&mut self, v: &[f32]) -> io::Result<()> {
        self.words(v, |x| x.to_le_bytes())
    }
    /// The length, then the items' 4-byte encodings, a block at a time.
    fn words<T: Copy>(&mut self, v: &[T], le: impl Fn(T) -> [u8; 4]) -> io::Result<()> {
        self.u64(v.len() as u64)?;
        let mut block = [0u8; 4 * WORDS];
        for items in v.chunks(WORDS) {
            for (b, &x) in block.chunks_exact_mut(4).zip(items) {
                b.copy_from_slice(&le(x));
            }
            self.raw(&block[..4 * items.len()])?;
        }
        Ok(())
    }
}

/// Items per block of [`Enc::words`] and [`Dec::words`].
const WORDS: usize = 1024;

/// Reader of the format's fields: `None` once the input ends early or a length exceeds
/// the `left` bytes of the file (so a corrupt length allocates nothing), with the read
/// error kept in `error`.
struct Dec<R: Read> {
    r: R,
    left: u64,
    error: Option<io::Error>,
}

impl<R: Read> Dec<R> {
    fn fill(&mut self, buf: &mut [u8]) -> Option<()> {
        let n = buf.len() as u64;
        if n > self.left {
            return None;
        }
        if let Err(e) = self.r.read_exact(buf) {
            self.error = Some(e);
            return None;
        }
        self.left -= n;
        Some(())
    }
    fn array<const B: usize>(&mut self) -> Option<[u8; B]> {
        let mut b = [0u8; B];
        self.fill(&mut b)?;
        Some(b)
    }
    fn u32(&mut self) -> Option<u32> {
        self.array().map(u32::from_le_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.array().map(u64::from_le_bytes)
    }
    fn f64(&mut self) -> Option<f64> {
        self.array().map(f64::from_le_bytes)
    }
    fn len(&mut self, item: usize) -> Option<usize> {
        let n = usize::try_from(self.u64()?).ok()?;
        (n.checked_mul(item)? as u64 <= self.left).then_some(n)
    }
    fn bytes(&mut self) -> Option<Vec<u8>> {
        let mut v = vec![0u8; self.len(1)?];
        self.fill(&mut v)?;
        Some(v)
    }
    /// `count` items of `size` bytes each, decoded by `from`, a block of about
    /// [`WORDS`] words at a time.
    fn items<T>(&mut self, count: usize, size: usize, from: impl Fn(&[u8]) -> T) -> Option<Vec<T>> {
        let mut out = Vec::with_capacity(count);
        let mut block = [0u8; 4 * WORDS];
        let per_block = (block.len() / size).max(1);
        while out.len() < count {
            let k = (count - out.len()).min(per_block);
            self.fill(&mut block[..size * k])?;
            out.extend(block[..size * k].chunks_exact(size).map(&from));
        }
        Some(out)
    }
    fn u32s(&mut self) -> Option<Vec<u32>> {
        let n = self.len(4)?;
        self.items(n, 4, |c| u32::from_le_bytes(c.try_into().unwrap()))
    }
    fn f32s(&mut self) -> Option<Vec<f32>> {
        let n = self.len(4)?;
        self.items(n, 4, le_f32)
    }
    /// [`Self::f32s`] as `K`-arrays, read straight into them.
    fn arrays<const K: usize>(&mut self) -> Option<Vec<[f32; K]>> {
        let n = self.len(4)?;
        if n % K != 0 {
            return None;
        }
        self.items(n / K, 4 * K, |c| std::array::from_fn(|j| le_f32(&c[4 * j..4 * j + 4])))
    }
}

/// The f32 of 4 little-endian bytes.
fn le_f32(c: &[u8]) -> f32 {
    f32::from_le_bytes(c.try_into().unwrap())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_guard_and_truncation() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("model");
        assert_eq!(dir_of(&out), dir.path().join("model.ckpt"));
        let path = path_of(&out);
        let state = TrainState {
            ids: vec![3, 4],
            dynamic: vec![true, false],
            origin: vec![3, 3],
            poses: Poses::identity(2, 2),
            log_scale: vec![[0.5; 3]; 2],
            logit_opacity: vec![0.1, -0.2],
            color: vec![[0.3; 3]; 2],
            sh_degree: 0,
            sh_rest: vec![],
        };
        let c = Checkpoint {
            step: 7,
            next_id: 9,
            state,
            adam: Adam::new(&[("position", 1e-3, 12)]),
            density: DensityStats::new(2),
            graph: vec![("theta".into(), vec![1.0, 2.0])],
            log: vec![LogRow {
                step: 6,
                terms: vec![("rgb".into(), 0.25)],
                lr: vec![("position".into(), 1e-3)],
                ..LogRow::default()
            }],
        };
        save(&path, &[1; 32], &c).unwrap();
        assert_eq!(load(&path, &[1; 32]).unwrap(), Some(c));
        assert_eq!(load(&path, &[2; 32]).unwrap(), None, "another run's checkpoint is ignored");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let e = load(&path, &[1; 32]).unwrap_err().to_string();
        assert!(e.contains("truncated or corrupt checkpoint"), "{e}");
        for bad in [&b"USP4D"[..], &[7u8; 64][..]] {
            std::fs::write(&path, bad).unwrap();
            let e = load(&path, &[1; 32]).unwrap_err().to_string();
            assert!(e.contains("not a usplat4d optimize checkpoint"), "{e}");
        }
    }
}
