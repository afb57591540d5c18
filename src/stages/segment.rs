//! Motion segmentation (paper Sec. 5.3, "Further analysis", Fig. 5): spectral clustering
//! of the key graph, non-keys inheriting their keys' groups.
//!
//! The key-key weight matrix W (directed edges, symmetrised to (W + Wᵀ)/2) is clustered by
//! the normalised spectral method ([`super::graph::spectral`]): the K leading eigenvectors
//! of D^{-1/2} W D^{-1/2}, row-normalised, then seeded k-means++. K is given or picked by
//! the largest eigengap. Each non-key takes the segment with the largest summed weight of
//! its nonkey-key edges. The PNG shows W with keys reordered by segment: a block-diagonal
//! matrix when the motions separate (dark = strong weight).

use std::collections::BTreeMap;
use std::path::PathBuf;

use super::graph::spectral::{self, SparseSym};
use crate::context::Context;
use crate::formats::png::Image;
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::segments::Segments;

/// Parameters of `usplat4d segment`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SegmentParams {
    /// Directory holding edges.parquet.
    #[arg(long, value_name = "DIR")]
    pub edges: PathBuf,
    /// Output directory (segments.parquet, weights.png).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Number of segments, at most the number of key nodes (default: by the largest eigengap
    /// up to --max-k).
    #[arg(long, value_parser = crate::stages::params::check::count)]
    #[serde(default)]
    pub k: Option<usize>,
    /// Largest K the eigengap may pick.
    #[arg(long, default_value_t = 10, value_parser = crate::stages::params::check::count)]
    #[serde(default = "default_max_k")]
    pub max_k: usize,
    /// Seed of the eigensolver start and of k-means++.
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub seed: u64,
}

fn default_max_k() -> usize {
    10
}

/// The result of [`segment`]: labels and the reordered key weight matrix.
#[derive(Debug, Clone)]
pub struct Segmentation {
    /// One label per Gaussian of the edges table, sorted by id.
    pub segments: Segments,
    /// Number of segments K.
    pub k: usize,
    /// Leading eigenvalues of D^{-1/2} W D^{-1/2}, descending.
    pub eigenvalues: Vec<f64>,
    /// Symmetrised key weight matrix, keys in ascending id order.
    pub weights: SparseSym,
    /// Key indices (into `weights`) ordered by segment, then id.
    pub order: Vec<usize>,
}

/// The key nodes of `edges` (every destination, and both ends of key-key edges), ascending.
pub fn key_ids(edges: &Edges) -> Vec<u32> {
    let mut ids: Vec<u32> = (0..edges.len())
        .flat_map(|e| match edges.kind[e] {
            EdgeKind::KeyKey => vec![edges.src[e], edges.dst[e]],
            EdgeKind::NonkeyKey => vec![edges.dst[e]],
        })
        .collect();
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// Cluster the key graph of `edges` into `k` segments (or by eigengap up to `max_k`).
pub fn segment(edges: &Edges, k: Option<usize>, max_k: usize, seed: u64) -> Segmentation {
    let key_ids = key_ids(edges);
    let index: BTreeMap<u32, u32> =
        key_ids.iter().enumerate().map(|(i, id)| (*id, i as u32)).collect();
    let nk = key_ids.len();
    let weights = SparseSym::symmetrised(
        nk,
        (0..edges.len())
            .filter(|&e| edges.kind[e] == EdgeKind::KeyKey)
            .map(|e| (index[&edges.src[e]], index[&edges.dst[e]], edges.weight[e] as f64)),
    );
    let want = k.unwrap_or(max_k).max(1);
    let (eigenvalues, vectors) = spectral::leading_eigenvectors(&weights, (want + 4).min(nk), seed);
    let k = k.unwrap_or_else(|| spectral::eigengap(&eigenvalues, max_k)).clamp(1, nk.max(1));
    let embedding: Vec<Vec<f64>> = (0..nk)
        .map(|i| {
            let row: Vec<f64> = (0..k.min(vectors.len())).map(|c| vectors[c][i]).collect();
            let norm = row.iter().map(|x| x * x).sum::<f64>().sqrt();
            if norm > 0.0 { row.iter().map(|x| x / norm).collect() } else { row }
        })
        .collect();
    let raw = spectral::kmeans(&embedding, k, seed, 8);
    // Canonical labels: numbered in order of first appearance by key id.
    let mut relabel = BTreeMap::new();
    let labels: Vec<u32> = raw
        .iter()
        .map(|l| {
            let next = relabel.len() as u32;
            *relabel.entry(*l).or_insert(next)
        })
        .collect();
    let mut votes: BTreeMap<u32, BTreeMap<u32, f64>> = BTreeMap::new();
    for e in (0..edges.len()).filter(|&e| edges.kind[e] == EdgeKind::NonkeyKey) {
        let seg = labels[index[&edges.dst[e]] as usize];
        *votes.entry(edges.src[e]).or_default().entry(seg).or_insert(0.0) += edges.weight[e] as f64;
    }
    let mut rows: Vec<(u32, u32, bool)> =
        key_ids.iter().zip(&labels).map(|(id, l)| (*id, *l, true)).collect();
    for (id, v) in &votes {
        if index.contains_key(id) {
            continue;
        }
        let seg =
            v.iter().max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(a.0))).map_or(0, |(s, _)| *s);
        rows.push((*id, seg, false));
    }
    rows.sort_unstable();
    let mut order: Vec<usize> = (0..nk).collect();
    order.sort_by_key(|&i| (labels[i], i));
    Segmentation {
        segments: Segments {
            id: rows.iter().map(|r| r.0).collect(),
            segment: rows.iter().map(|r| r.1).collect(),
            is_key: rows.iter().map(|r| r.2).collect(),
        },
        k: relabel.len().max(1),
        eigenvalues,
        weights,
        order,
    }
}

/// The reordered weight matrix as a grey image of at most `max_side` pixels a side
/// (each pixel the largest weight of its block; white 0, black the largest weight).
pub fn weight_image(s: &Segmentation, max_side: usize) -> Image {
    let nk = s.order.len();
    let side = nk.clamp(1, max_side.max(1));
    let mut pos = vec![0usize; nk];
    for (p, &i) in s.order.iter().enumerate() {
        pos[i] = p;
    }
    let mut img = vec![0.0f64; side * side];
    for (i, row) in s.weights.rows.iter().enumerate() {
        for &(j, w) in row {
            let (y, x) = (pos[i] * side / nk, pos[j as usize] * side / nk);
            img[y * side + x] = img[y * side + x].max(w);
        }
    }
    let max = img.iter().cloned().fold(0.0, f64::max);
    let data = img.iter().map(|w| if max > 0.0 { (1.0 - w / max) as f32 } else { 1.0 }).collect();
    Image { width: side, height: side, channels: 1, data }
}

/// `usplat4d segment`: read the edges, cluster, write `OUT/segments.parquet` and
/// `OUT/weights.png`.
pub fn run(p: &SegmentParams, ctx: &Context) -> anyhow::Result<()> {
    use crate::tables::Table;
    let _span = tracing::info_span!("segment").entered();
    if p.k == Some(0) || p.max_k == 0 {
        anyhow::bail!("segment: --k and --max-k must be at least 1");
    }
    let path = p.edges.join(crate::tables::edges::EdgesTable::file_name());
    let edges = crate::tables::edges::read(&path)?;
    let keys = key_ids(&edges).len();
    if let Some(k) = p.k
        && k > keys
    {
        anyhow::bail!("segment: --k {k} is more than the {keys} key nodes of {}", path.display());
    }
    let s = segment(&edges, p.k, p.max_k, p.seed);
    ctx.info(format!(
        "segment: {} segments over {} Gaussians ({} keys); leading eigenvalues {:?}",
        s.k,
        s.segments.id.len(),
        s.order.len(),
        s.eigenvalues.iter().map(|v| (v * 1e4).round() / 1e4).collect::<Vec<_>>()
    ));
    let prov = crate::tables::Provenance::new(
        "segment",
        &serde_json::json!({ "params": p, "resolved": { "k": s.k } }),
    );
    crate::tables::segments::write(
        &p.out.join(crate::tables::segments::SegmentsTable::file_name()),
        &s.segments,
        &prov,
    )?;
    crate::formats::png::write_png(&p.out.join("weights.png"), &weight_image(&s, 1024))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tables::Table;

    /// `--k` above the number of key nodes is an error naming the option (it used to be
    /// clamped silently to the number of eigenvectors computed).
    #[test]
    fn k_above_the_number_of_keys_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut e = Edges::default();
        for (s, d) in [(0, 1), (1, 2), (2, 0), (5, 0), (6, 1)] {
            let kind = if s < 3 { EdgeKind::KeyKey } else { EdgeKind::NonkeyKey };
            e.push(s, d, kind, 1.0);
        }
        let path = dir.path().join(crate::tables::edges::EdgesTable::file_name());
        crate::tables::edges::write(&path, &e, &crate::tables::Provenance::default()).unwrap();
        let p = |k| SegmentParams {
            edges: dir.path().into(),
            out: dir.path().join("out"),
            k: Some(k),
            max_k: 10,
            seed: 0,
        };
        let err = run(&p(100_000), &Context::quiet()).unwrap_err().to_string();
        assert!(err.contains("--k 100000 is more than the 3 key nodes"), "{err}");
        run(&p(3), &Context::quiet()).unwrap();
    }
}
