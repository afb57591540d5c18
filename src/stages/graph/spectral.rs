//! Spectral clustering of a sparse symmetric weight matrix (von Luxburg 2007, normalised
//! variant of Ng, Jordan and Weiss), used by `segment` on the key graph.
//!
//! The leading eigenvectors of M = D^{-1/2} W D^{-1/2} (the smallest of the normalised
//! Laplacian L = I − M) come from subspace iteration on (M + I)/2 with Rayleigh-Ritz
//! steps (a small Jacobi eigensolver), so only sparse products with M are needed:
//! O(nnz·p) per iteration for p vectors, no dense n×n matrix. Rows of the embedding are
//! normalised and clustered by k-means with seeded k-means++ restarts. Everything runs in
//! a fixed order, so results do not depend on the thread count.

use rayon::prelude::*;

use crate::util::rng::Rng;

/// A sparse symmetric matrix in compressed rows `[n]`, each row `(column, value)` sorted.
#[derive(Debug, Clone, Default)]
pub struct SparseSym {
    /// Rows.
    pub rows: Vec<Vec<(u32, f64)>>,
}

impl SparseSym {
    /// Symmetrised (W + Wᵀ)/2 of the directed weighted edges `(i, j, w)` on `n` nodes
    /// (duplicates summed, self-loops dropped).
    pub fn symmetrised(n: usize, edges: impl IntoIterator<Item = (u32, u32, f64)>) -> Self {
        let mut rows: Vec<Vec<(u32, f64)>> = vec![Vec::new(); n];
        for (i, j, w) in edges {
            if i != j {
                rows[i as usize].push((j, 0.5 * w));
                rows[j as usize].push((i, 0.5 * w));
            }
        }
        for r in &mut rows {
            r.sort_unstable_by_key(|e| e.0);
            let mut merged: Vec<(u32, f64)> = Vec::with_capacity(r.len());
            for &(j, w) in r.iter() {
                match merged.last_mut() {
                    Some(last) if last.0 == j => last.1 += w,
                    _ => merged.push((j, w)),
                }
            }
            *r = merged;
        }
        SparseSym { rows }
    }

    /// Number of nodes n.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether the matrix is empty.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Weight of entry (i, j) (0 when absent).
    pub fn get(&self, i: usize, j: usize) -> f64 {
        let r = &self.rows[i];
        r.binary_search_by_key(&(j as u32), |e| e.0).map_or(0.0, |k| r[k].1)
    }
}

/// The `p` largest eigenpairs of M = D^{-1/2} W D^{-1/2}: eigenvalues descending and the
/// eigenvectors `[p][n]` (orthonormal).
pub fn leading_eigenvectors(w: &SparseSym, p: usize, seed: u64) -> (Vec<f64>, Vec<Vec<f64>>) {
    let n = w.len();
    let p = p.min(n);
    let dinv: Vec<f64> = w
        .rows
        .iter()
        .map(|r| {
            let d: f64 = r.iter().map(|e| e.1).sum();
            if d > 0.0 { 1.0 / d.sqrt() } else { 0.0 }
        })
        .collect();
    // B = (M + I) / 2, eigenvalues in [0, 1], same eigenvectors as M.
    let apply = |x: &[f64], y: &mut [f64]| {
        y.par_iter_mut().enumerate().for_each(|(i, yi)| {
            let s: f64 = w.rows[i].iter().map(|&(j, v)| v * dinv[j as usize] * x[j as usize]).sum();
            *yi = 0.5 * (x[i] + dinv[i] * s);
        });
    };
    let mut rng = Rng::new(seed);
    let mut v: Vec<Vec<f64>> = (0..p).map(|_| (0..n).map(|_| rng.normal()).collect()).collect();
    orthonormalise(&mut v);
    let mut tmp = vec![0.0; n];
    let mut values = vec![0.0; p];
    // The last few vectors only guard the convergence of the leading ones.
    let watched = p.saturating_sub(3).max(1).min(p);
    for iter in 1..=3000 {
        for x in v.iter_mut() {
            apply(x, &mut tmp);
            x.copy_from_slice(&tmp);
        }
        orthonormalise(&mut v);
        if iter % 10 == 0 {
            let old = values.clone();
            values = rayleigh_ritz(&mut v, &apply);
            if values.iter().zip(&old).take(watched).all(|(a, b)| (a - b).abs() < 1e-9) {
                break;
            }
        }
    }
    (values.iter().map(|b| 2.0 * b - 1.0).collect(), v)
}

/// Modified Gram-Schmidt, twice for stability; a vanishing vector is replaced by zeros.
fn orthonormalise(v: &mut [Vec<f64>]) {
    for _ in 0..2 {
        for a in 0..v.len() {
            for b in 0..a {
                let d: f64 = v[a].iter().zip(&v[b]).map(|(x, y)| x * y).sum();
                let (lo, hi) = v.split_at_mut(a);
                hi[0].iter_mut().zip(&lo[b]).for_each(|(x, y)| *x -= d * y);
            }
            let norm = v[a].iter().map(|x| x * x).sum::<f64>().sqrt();
            let s = if norm > 1e-300 { 1.0 / norm } else { 0.0 };
            v[a].iter_mut().for_each(|x| *x *= s);
        }
    }
}

/// Rotate the orthonormal basis `v` onto the Ritz vectors of the operator; returns the Ritz
/// values, descending.
fn rayleigh_ritz(v: &mut [Vec<f64>], apply: &impl Fn(&[f64], &mut [f64])) -> Vec<f64> {
    let p = v.len();
    let n = v.first().map_or(0, |x| x.len());
    let av: Vec<Vec<f64>> = v
        .iter()
        .map(|x| {
            let mut y = vec![0.0; n];
            apply(x, &mut y);
            y
        })
        .collect();
    let mut h = vec![vec![0.0; p]; p];
    for a in 0..p {
        for b in 0..p {
            h[a][b] = v[a].iter().zip(&av[b]).map(|(x, y)| x * y).sum();
        }
    }
    for a in 0..p {
        for b in 0..a {
            let s = 0.5 * (h[a][b] + h[b][a]);
            h[a][b] = s;
            h[b][a] = s;
        }
    }
    let (vals, vecs) = jacobi_eigen(h);
    let mut order: Vec<usize> = (0..p).collect();
    order.sort_by(|&a, &b| vals[b].total_cmp(&vals[a]).then(a.cmp(&b)));
    let rotated: Vec<Vec<f64>> = order
        .iter()
        .map(|&c| {
            let mut x = vec![0.0; n];
            for a in 0..p {
                let s = vecs[a][c];
                x.iter_mut().zip(&v[a]).for_each(|(xi, vi)| *xi += s * vi);
            }
            x
        })
        .collect();
    for (dst, src) in v.iter_mut().zip(rotated) {
        *dst = src;
    }
    order.iter().map(|&c| vals[c]).collect()
}

/// Eigen-decomposition of a small symmetric matrix by cyclic Jacobi rotations: eigenvalues
/// and the eigenvector matrix (column c is the vector of value c).
pub fn jacobi_eigen(mut a: Vec<Vec<f64>>) -> (Vec<f64>, Vec<Vec<f64>>) {
    let n = a.len();
    let mut v: Vec<Vec<f64>> =
        (0..n).map(|i| (0..n).map(|j| if i == j { 1.0 } else { 0.0 }).collect()).collect();
    for _ in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k][p], v[k][q]);
                    v[k][p] = c * vkp - s * vkq;
                    v[k][q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i][i]).collect(), v)
}

/// The number of clusters by the largest eigengap: with M's eigenvalues λ descending,
/// K = argmax_{1 ≤ K ≤ k_max} (λ_K − λ_{K+1}).
pub fn eigengap(values: &[f64], k_max: usize) -> usize {
    (1..=k_max.min(values.len().saturating_sub(1)))
        .max_by(|&a, &b| {
            (values[a - 1] - values[a]).total_cmp(&(values[b - 1] - values[b])).then(b.cmp(&a))
        })
        .unwrap_or(1)
}

/// k-means of `points` `[n][d]` into `k` clusters: `restarts` seeded k-means++
/// initialisations, Lloyd iterations, the labelling of lowest inertia.
pub fn kmeans(points: &[Vec<f64>], k: usize, seed: u64, restarts: usize) -> Vec<u32> {
    let n = points.len();
    if n == 0 || k <= 1 {
        return vec![0; n];
    }
    let k = k.min(n);
    let d2 = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>();
    let mut best: Option<(f64, Vec<u32>)> = None;
    let mut rng = Rng::new(seed);
    for _ in 0..restarts.max(1) {
        let mut centres: Vec<Vec<f64>> = vec![points[(rng.next_u64() % n as u64) as usize].clone()];
        let mut dist: Vec<f64> = points.iter().map(|p| d2(p, &centres[0])).collect();
        while centres.len() < k {
            let total: f64 = dist.iter().sum();
            let pick = if total > 0.0 {
                let mut r = rng.uniform() * total;
                dist.iter()
                    .position(|d| {
                        r -= d;
                        r < 0.0
                    })
                    .unwrap_or(n - 1)
            } else {
                (rng.next_u64() % n as u64) as usize
            };
            centres.push(points[pick].clone());
            for (i, p) in points.iter().enumerate() {
                dist[i] = dist[i].min(d2(p, &points[pick]));
            }
        }
        let mut labels = vec![u32::MAX; n];
        for _ in 0..300 {
            let mut changed = false;
            for (i, p) in points.iter().enumerate() {
                let c = (0..k).min_by(|&a, &b| {
                    d2(p, &centres[a]).total_cmp(&d2(p, &centres[b])).then(a.cmp(&b))
                });
                let c = c.unwrap_or(0) as u32;
                changed |= labels[i] != c;
                labels[i] = c;
            }
            if !changed {
                break;
            }
            for (c, centre) in centres.iter_mut().enumerate() {
                let members: Vec<&Vec<f64>> = points
                    .iter()
                    .zip(&labels)
                    .filter(|(_, l)| **l == c as u32)
                    .map(|(p, _)| p)
                    .collect();
                if !members.is_empty() {
                    for (k, x) in centre.iter_mut().enumerate() {
                        *x = members.iter().map(|m| m[k]).sum::<f64>() / members.len() as f64;
                    }
                }
            }
        }
        let inertia: f64 =
            points.iter().zip(&labels).map(|(p, l)| d2(p, &centres[*l as usize])).sum();
        if best.as_ref().is_none_or(|b| inertia < b.0) {
            best = Some((inertia, labels));
        }
    }
    best.map(|b| b.1).unwrap_or_default()
}

/// Adjusted Rand index of two labellings (1 = identical partitions, ~0 = chance).
pub fn adjusted_rand_index(a: &[u32], b: &[u32]) -> f64 {
    let mut table = std::collections::BTreeMap::new();
    let mut ra = std::collections::BTreeMap::new();
    let mut rb = std::collections::BTreeMap::new();
    for (x, y) in a.iter().zip(b) {
        *table.entry((*x, *y)).or_insert(0u64) += 1;
        *ra.entry(*x).or_insert(0u64) += 1;
        *rb.entry(*y).or_insert(0u64) += 1;
    }
    let c2 = |n: u64| (n * n.saturating_sub(1)) as f64 / 2.0;
    let index: f64 = table.values().map(|&n| c2(n)).sum();
    let sa: f64 = ra.values().map(|&n| c2(n)).sum();
    let sb: f64 = rb.values().map(|&n| c2(n)).sum();
    let expected = sa * sb / c2(a.len() as u64).max(1.0);
    let max = 0.5 * (sa + sb);
    if (max - expected).abs() < 1e-12 { 1.0 } else { (index - expected) / (max - expected) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_diagonalises() {
        let a = vec![vec![2.0, 1.0, 0.0], vec![1.0, 2.0, 0.5], vec![0.0, 0.5, 1.0]];
        let (vals, v) = jacobi_eigen(a.clone());
        for c in 0..3 {
            for i in 0..3 {
                let av: f64 = (0..3).map(|j| a[i][j] * v[j][c]).sum();
                assert!((av - vals[c] * v[i][c]).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn two_cliques_give_two_clusters() {
        // two 10-cliques joined by one weak edge
        let mut e = Vec::new();
        for g in 0..2u32 {
            for i in 0..10 {
                for j in 0..10 {
                    if i != j {
                        e.push((g * 10 + i, g * 10 + j, 1.0));
                    }
                }
            }
        }
        e.push((0, 10, 0.01));
        let w = SparseSym::symmetrised(20, e);
        let (vals, vecs) = leading_eigenvectors(&w, 5, 1);
        assert!((vals[0] - 1.0).abs() < 1e-8, "{vals:?}");
        assert_eq!(eigengap(&vals, 4), 2);
        let emb: Vec<Vec<f64>> = (0..20).map(|i| vec![vecs[0][i], vecs[1][i]]).collect();
        let labels = kmeans(&emb, 2, 3, 4);
        let truth: Vec<u32> = (0..20).map(|i| (i / 10) as u32).collect();
        assert_eq!(adjusted_rand_index(&labels, &truth), 1.0);
        assert!(adjusted_rand_index(&[0, 0, 1, 1], &[0, 1, 0, 1]) < 0.0);
    }
}
