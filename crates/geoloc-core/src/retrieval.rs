//! Exact nearest-neighbour search over global image descriptors.
//!
//! [`DescriptorIndex`] answers exact 1-NN / k-NN queries in the Euclidean metric — the same
//! neighbours as a brute-force scan (ties broken by the lower index). It uses a kiddo k-d
//! tree where k-d trees win (dimension ≤ [`KDTREE_MAX_DIM`]) and a flat, cache-friendly
//! parallel scan above that (k-d trees degrade to worse than a scan in tens of dimensions).
//! Many identical descriptors (a stopped camera) are fine: should the tree's construction
//! panic on them anyway, the index falls back to the scan instead of unwinding into the
//! caller.
//!
//! Both fast paths compute squared distances in f32, which overflow above |x| ≈ 1.8·10¹⁹ and
//! underflow below ≈ 10⁻¹⁹. Where the data or the queries hold magnitudes outside
//! [[`F32_SAFE_MIN_ABS`], [`F32_SAFE_MAX_ABS`]] (zeros aside), the query runs as an exact
//! scan in f64 instead (every finite f32 squares without overflow or underflow there), so
//! results are exact for every finite input. Returned distances are rounded to f32 and
//! saturate at `f32::MAX`.

use std::num::NonZero;

use crate::error::{GeolocError, Result};
use crate::parallel::map_indices;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

/// Highest dimension served by the k-d tree (kiddo's dimension is a compile-time constant).
pub const KDTREE_MAX_DIM: usize = 8;
/// Queries per parallel task in batched searches.
const QUERY_CHUNK: usize = 16;
/// Largest magnitude served by the f32 paths: (2·10¹⁵)²·D stays far below `f32::MAX` for
/// any realistic D, with room for the matrix-product scan's rounding bound.
pub const F32_SAFE_MAX_ABS: f32 = 1e15;
/// Smallest non-zero magnitude served by the f32 paths (squared differences of smaller values
/// underflow and tie).
pub const F32_SAFE_MIN_ABS: f32 = 1e-15;

/// (smallest non-zero |x|, largest |x|) of `values` (∞, 0 when all are zero). Eight
/// independent lanes, so the loop vectorizes (it runs over every descriptor value).
fn magnitude_range(values: &[f32]) -> (f32, f32) {
    const LANES: usize = 8;
    let (mut lo, mut hi) = ([f32::INFINITY; LANES], [0.0_f32; LANES]);
    let mut update = |lane: usize, v: f32| {
        let a = v.abs();
        hi[lane] = if a > hi[lane] { a } else { hi[lane] };
        lo[lane] = if a > 0.0 && a < lo[lane] { a } else { lo[lane] };
    };
    let chunks = values.chunks_exact(LANES);
    let tail = chunks.remainder();
    for chunk in chunks {
        for (lane, &v) in chunk.iter().enumerate() {
            update(lane, v);
        }
    }
    for (lane, &v) in tail.iter().enumerate() {
        update(lane, v);
    }
    (lo.into_iter().fold(f32::INFINITY, f32::min), hi.into_iter().fold(0.0, f32::max))
}

/// Whether the f32 paths are exact for values of this range.
fn f32_safe((lo, hi): (f32, f32)) -> bool {
    hi <= F32_SAFE_MAX_ABS && (lo >= F32_SAFE_MIN_ABS || lo.is_infinite())
}

/// Which search structure an index uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// kiddo's immutable k-d tree.
    KdTree,
    /// Exact parallel scan.
    Flat,
}

impl Backend {
    /// Every backend, in declaration order.
    pub const ALL: [Self; 2] = [Self::KdTree, Self::Flat];

    /// The name: `"kdtree"` or `"flat"` (the one place that spells it).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::KdTree => "kdtree",
            Self::Flat => "flat",
        }
    }
}

impl std::str::FromStr for Backend {
    type Err = GeolocError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|b| b.as_str() == s)
            .ok_or_else(|| GeolocError::invalid("backend", format!("expected \"kdtree\" or \"flat\", got {s:?}")))
    }
}

trait Tree: Send + Sync {
    fn nearest(&self, query: &[f32], k: usize) -> Vec<(f32, usize)>;
}

struct KiddoTree<const K: usize>(ImmutableKdTree<f32, u32, K, 32>);

impl<const K: usize> Tree for KiddoTree<K> {
    fn nearest(&self, query: &[f32], k: usize) -> Vec<(f32, usize)> {
        let q: [f32; K] = query.try_into().expect("invariant: query rows have the index dimension");
        let n = NonZero::new(k).expect("invariant: k ≥ 1 is checked by the caller");
        // the k-th distance: k = 1 (global-descriptor retrieval) without nearest_n's result
        // collection (an allocation per query)
        let worst = if k == 1 {
            self.0.nearest_one::<SquaredEuclidean>(&q).distance
        } else {
            let found = self.0.nearest_n::<SquaredEuclidean>(&q, n);
            let Some(worst) = found.iter().map(|f| f.distance).reduce(f32::max) else { return Vec::new() };
            worst
        };
        // everything as close as the k-th: ties at the boundary must be resolved by index,
        // exactly as a scan would (a stopped camera yields thousands of them)
        let all = NonZero::new(self.0.size().max(1)).expect("invariant: max(1) is non-zero");
        self.0
            .nearest_n_within::<SquaredEuclidean>(&q, worst, all, false)
            .into_iter()
            .map(|f| (f.distance, f.item as usize))
            .collect()
    }
}

fn build_tree<const K: usize>(data: &[f32]) -> Option<Box<dyn Tree>> {
    let rows: Vec<[f32; K]> =
        data.chunks_exact(K).map(|c| c.try_into().expect("invariant: chunks have K values")).collect();
    // kiddo has panicked on degenerate inputs in past versions: never let that unwind out
    std::panic::catch_unwind(|| ImmutableKdTree::<f32, u32, K, 32>::new_from_slice(&rows))
        .ok()
        .map(|t| Box::new(KiddoTree(t)) as Box<dyn Tree>)
}

/// An exact nearest-neighbour index over N descriptors of dimension D (row-major f32).
pub struct DescriptorIndex {
    dim: usize,
    data: Vec<f32>,
    /// ‖x‖² per row (for the matrix-product scan).
    norms: Vec<f32>,
    /// The flat backend's rows again, as (≤ [`GEMM_ROW_BLOCK`] × D) column-major blocks: the
    /// left operand of the scan's matrix product X·Qᵀ, whose result then holds one contiguous
    /// column per query (empty with the tree).
    row_blocks: Vec<nalgebra::DMatrix<f32>>,
    /// (smallest non-zero |x|, largest |x|) of the data.
    magnitudes: (f32, f32),
    tree: Option<Box<dyn Tree>>,
}

impl std::fmt::Debug for DescriptorIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DescriptorIndex")
            .field("len", &self.len())
            .field("dim", &self.dim)
            .field("backend", &self.backend())
            .finish()
    }
}

impl DescriptorIndex {
    /// Builds the index (the backend is chosen by dimension; see the module doc).
    ///
    /// # Errors
    /// Empty input, a length that is not a multiple of `dim`, or non-finite values.
    pub fn new(data: Vec<f32>, dim: usize) -> Result<Self> {
        Self::with_backend(data, dim, None)
    }

    /// As [`DescriptorIndex::new`], forcing a backend (`KdTree` needs dim ≤ [`KDTREE_MAX_DIM`]).
    ///
    /// # Errors
    /// As [`DescriptorIndex::new`], or `KdTree` requested above its dimension limit.
    pub fn with_backend(data: Vec<f32>, dim: usize, backend: Option<Backend>) -> Result<Self> {
        if dim == 0 || data.is_empty() || !data.len().is_multiple_of(dim) {
            return Err(GeolocError::invalid(
                "descriptors",
                format!("expected a non-empty (N, D) array, got {} values for D = {dim}", data.len()),
            ));
        }
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(GeolocError::NonFinite { name: "descriptors".into(), index: i / dim });
        }
        let use_tree = match backend {
            Some(Backend::Flat) => false,
            Some(Backend::KdTree) if dim > KDTREE_MAX_DIM => {
                return Err(GeolocError::invalid(
                    "backend",
                    format!("the k-d tree serves D ≤ {KDTREE_MAX_DIM}, got D = {dim}"),
                ));
            }
            Some(Backend::KdTree) => true,
            None => dim <= KDTREE_MAX_DIM,
        };
        let tree = if use_tree { build_for_dim(&data, dim) } else { None };
        let norms = data.chunks_exact(dim).map(|r| r.iter().map(|v| v * v).sum()).collect();
        let magnitudes = magnitude_range(&data);
        let row_blocks = match tree {
            Some(_) => Vec::new(),
            None => data
                .chunks(GEMM_ROW_BLOCK * dim)
                .map(|block| nalgebra::DMatrix::from_row_slice(block.len() / dim, dim, block))
                .collect(),
        };
        Ok(Self { dim, data, norms, row_blocks, magnitudes, tree })
    }

    /// N.
    pub fn len(&self) -> usize {
        self.data.len() / self.dim
    }

    /// Whether the index holds no descriptors (never: construction refuses that).
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// D.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The backend in use.
    pub fn backend(&self) -> Backend {
        if self.tree.is_some() { Backend::KdTree } else { Backend::Flat }
    }

    /// The k nearest descriptors of each query row (Q × D, row-major): Euclidean distances
    /// and indices, each Q × k row-major, nearest first, ties by lower index.
    ///
    /// # Errors
    /// Wrong query width, non-finite queries, k = 0 or k > N.
    pub fn query(&self, queries: &[f32], k: usize) -> Result<(Vec<f32>, Vec<usize>)> {
        if !queries.len().is_multiple_of(self.dim) {
            return Err(GeolocError::invalid("queries", format!("rows must have D = {} values", self.dim)));
        }
        if let Some(i) = queries.iter().position(|v| !v.is_finite()) {
            return Err(GeolocError::NonFinite { name: "queries".into(), index: i / self.dim });
        }
        if k == 0 || k > self.len() {
            return Err(GeolocError::invalid("k", format!("must be in 1..={}, got {k}", self.len())));
        }
        let q_count = queries.len() / self.dim;
        let (q_lo, q_hi) = magnitude_range(queries);
        // one Vec of q·k (distance, index) pairs per block of queries, in query order
        let found: Vec<Vec<(f32, usize)>> = if f32_safe((self.magnitudes.0.min(q_lo), self.magnitudes.1.max(q_hi))) {
            let block = if self.tree.is_some() { QUERY_CHUNK } else { GEMM_QUERY_BLOCK };
            map_indices(q_count.div_ceil(block), 2, |chunk| {
                let first = chunk * block;
                let rows = &queries[first * self.dim..(first + block).min(q_count) * self.dim];
                self.search_f32(rows, k)
            })
        } else {
            map_indices(q_count, 2, |q| self.scan_f64(&queries[q * self.dim..(q + 1) * self.dim], k))
        };
        let mut distances = Vec::with_capacity(q_count * k);
        let mut indices = Vec::with_capacity(q_count * k);
        for &(d, i) in found.iter().flatten() {
            distances.push(d);
            indices.push(i);
        }
        Ok((distances, indices))
    }

    /// The k nearest (distance, index) of each of a block of queries, by the f32 paths,
    /// concatenated (k per query, in query order).
    fn search_f32(&self, rows: &[f32], k: usize) -> Vec<(f32, usize)> {
        let mut out = Vec::with_capacity(rows.len() / self.dim * k);
        let mut emit = |mut found: Vec<(f32, usize)>| {
            // a canonical order: distance, then index (trees may order ties freely)
            found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            out.extend(found.into_iter().take(k).map(|(d2, i)| (d2.max(0.0).sqrt(), i)));
        };
        match &self.tree {
            Some(tree) => rows.chunks_exact(self.dim).for_each(|q| emit(tree.nearest(q, k))),
            None if rows.len() == self.dim => emit(self.scan(rows, k)),
            None => self.scan_block(rows, k).into_iter().for_each(emit),
        }
        out
    }

    /// Exact scan in f64 for one query (any finite magnitudes): Σ (xᵢ − qᵢ)² in f64, the k
    /// best by (distance, index), distances rounded to f32 and saturated at `f32::MAX`.
    fn scan_f64(&self, query: &[f32], k: usize) -> Vec<(f32, usize)> {
        let mut best = TopK::<f64>::new(k);
        for (i, row) in self.data.chunks_exact(self.dim).enumerate() {
            let d2: f64 = row.iter().zip(query).map(|(&x, &q)| (f64::from(x) - f64::from(q)).powi(2)).sum();
            best.push(d2, i);
        }
        best.into_sorted().into_iter().map(|(d2, i)| (d2.sqrt().min(f64::from(f32::MAX)) as f32, i)).collect()
    }

    /// Brute force for one query: squared distances to every row, keeping the k best.
    fn scan(&self, query: &[f32], k: usize) -> Vec<(f32, usize)> {
        let mut best = TopK::new(k);
        for (i, row) in self.data.chunks_exact(self.dim).enumerate() {
            best.push(squared_distance(row, query), i);
        }
        best.into_sorted()
    }
}

/// Σ (aᵢ − bᵢ)², the reference distance every backend is exact against.
#[inline]
fn squared_distance(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// A squared distance (f32 on the fast paths, f64 on the exact fallback).
trait Distance: Copy {
    const INFINITY: Self;
    fn total_cmp(&self, other: &Self) -> std::cmp::Ordering;
}

impl Distance for f32 {
    const INFINITY: Self = f32::INFINITY;
    fn total_cmp(&self, other: &Self) -> std::cmp::Ordering {
        f32::total_cmp(self, other)
    }
}

impl Distance for f64 {
    const INFINITY: Self = f64::INFINITY;
    fn total_cmp(&self, other: &Self) -> std::cmp::Ordering {
        f64::total_cmp(self, other)
    }
}

/// The k smallest (distance, index) pairs seen, ties by index.
struct TopK<D> {
    k: usize,
    best: Vec<(D, usize)>,
}

impl<D: Distance> TopK<D> {
    fn new(k: usize) -> Self {
        Self { k, best: Vec::with_capacity(k + 1) }
    }

    fn worst(&self) -> D {
        if self.best.len() < self.k { D::INFINITY } else { self.best[self.k - 1].0 }
    }

    #[inline]
    fn push(&mut self, d2: D, i: usize) {
        if self.best.len() == self.k && d2.total_cmp(&self.worst()).is_gt() {
            return;
        }
        // ties are exact equalities of identically computed distances: order by index
        let pos = self.best.partition_point(|&(d, j)| d.total_cmp(&d2).then(j.cmp(&i)).is_lt());
        if pos < self.k {
            self.best.insert(pos, (d2, i));
            self.best.truncate(self.k);
        }
    }

    fn into_sorted(self) -> Vec<(D, usize)> {
        self.best
    }
}

/// Queries per block of the matrix-product scan.
const GEMM_QUERY_BLOCK: usize = 256;
/// Rows the scan checks at once against a query's threshold (one vectorized comparison).
const LANES: usize = 16;
/// Database rows per block of the matrix-product scan (keeps the product in cache).
const GEMM_ROW_BLOCK: usize = 2048;

impl DescriptorIndex {
    /// The flat backend for many queries: ‖q − x‖² = ‖x‖² + ‖q‖² − 2 q·x with the dot
    /// products of a block of queries against a block of rows computed as one matrix product
    /// (nalgebra → matrixmultiply's SIMD kernels). That form rounds differently from the
    /// reference Σ(qᵢ − xᵢ)², so it only *selects*: every row whose estimate is within a
    /// rounding bound of the k-th best is re-scored exactly, and the k best of those are
    /// returned — the same neighbours as the reference scan.
    fn scan_block(&self, queries: &[f32], k: usize) -> Vec<Vec<(f32, usize)>> {
        use nalgebra::DMatrix;
        let dim = self.dim;
        let b = queries.len() / dim;
        // rounding bound of the f32 expansion, B_q = γ_{D+3} (max‖x‖ + ‖q‖)² with γ_m ≈ m ε:
        // a true top-k row has estimate ≤ d + B ≤ (k-th estimate + B) + B
        let gamma = (dim as f32 + 3.0) * f32::EPSILON;
        let max_norm = self.norms.iter().fold(0.0_f32, |m, &v| m.max(v)).sqrt();
        let q_norm: Vec<f32> = queries.chunks_exact(dim).map(|q| q.iter().map(|v| v * v).sum()).collect();
        let margin: Vec<f32> = q_norm.iter().map(|&qn| 2.0 * gamma * (max_norm + qn.sqrt()).powi(2)).collect();
        // (D × b) column-major is exactly the row-major (b × D) queries
        let q_mat = DMatrix::from_column_slice(dim, b, queries);
        let mut candidates: Vec<Vec<(f32, usize)>> = vec![Vec::new(); b];
        let mut estimates: Vec<TopK<f32>> = (0..b).map(|_| TopK::new(k)).collect();
        for (block, x_mat) in self.row_blocks.iter().enumerate() {
            let (start, rows) = (block * GEMM_ROW_BLOCK, x_mat.nrows());
            let dots = x_mat * &q_mat; // rows × b, column-major: one contiguous column per query
            let x_norms = &self.norms[start..start + rows];
            for (q, column) in dots.as_slice().chunks_exact(rows).enumerate() {
                let (found, cands) = (&mut estimates[q], &mut candidates[q]);
                let mut threshold = found.worst() + margin[q];
                let estimate = |dot: f32, x_norm: f32| x_norm + q_norm[q] - 2.0 * dot;
                for (lane, (dots, x_norms)) in column.chunks(LANES).zip(x_norms.chunks(LANES)).enumerate() {
                    // a branch-free (vectorized) look first: most lanes of most chunks miss
                    let any = dots.iter().zip(x_norms).fold(false, |any, (&d, &x)| any | (estimate(d, x) <= threshold));
                    if !any {
                        continue;
                    }
                    for (r, (&d, &x)) in dots.iter().zip(x_norms).enumerate() {
                        let (e, row) = (estimate(d, x), start + lane * LANES + r);
                        if e <= threshold {
                            cands.push((e, row));
                            found.push(e, row);
                            threshold = found.worst() + margin[q];
                        }
                    }
                }
            }
        }
        let thresholds: Vec<f32> = estimates.iter().zip(&margin).map(|(e, m)| e.worst() + m).collect();
        candidates
            .into_iter()
            .enumerate()
            .map(|(q, cands)| {
                let query = &queries[q * dim..(q + 1) * dim];
                let mut best = TopK::new(k);
                for (estimate, i) in cands {
                    if estimate <= thresholds[q] {
                        best.push(squared_distance(&self.data[i * dim..(i + 1) * dim], query), i);
                    }
                }
                best.into_sorted()
            })
            .collect()
    }
}

fn build_for_dim(data: &[f32], dim: usize) -> Option<Box<dyn Tree>> {
    match dim {
        1 => build_tree::<1>(data),
        2 => build_tree::<2>(data),
        3 => build_tree::<3>(data),
        4 => build_tree::<4>(data),
        5 => build_tree::<5>(data),
        6 => build_tree::<6>(data),
        7 => build_tree::<7>(data),
        8 => build_tree::<8>(data),
        _ => None,
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact zero distances to identical descriptors
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    fn brute(data: &[f32], dim: usize, q: &[f32], k: usize) -> Vec<(f32, usize)> {
        let mut all: Vec<(f32, usize)> = data
            .chunks_exact(dim)
            .enumerate()
            .map(|(i, r)| (r.iter().zip(q).map(|(a, b)| (a - b) * (a - b)).sum::<f32>(), i))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        all
    }

    fn random(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.normal() as f32).collect()
    }

    #[test]
    fn equals_brute_force_for_every_backend_and_dimension() {
        let mut rng = SplitMix64::new(1);
        for dim in [1, 2, 3, 5, 8, 16, 33] {
            let data = random(&mut rng, 500 * dim);
            let queries = random(&mut rng, 40 * dim);
            for backend in [Backend::KdTree, Backend::Flat] {
                if backend == Backend::KdTree && dim > KDTREE_MAX_DIM {
                    continue;
                }
                let index = DescriptorIndex::with_backend(data.clone(), dim, Some(backend)).expect("valid");
                assert_eq!(index.backend(), backend);
                let (d, i) = index.query(&queries, 5).expect("valid");
                for q in 0..40 {
                    let want = brute(&data, dim, &queries[q * dim..(q + 1) * dim], 5);
                    for s in 0..5 {
                        assert_eq!(i[q * 5 + s], want[s].1, "dim {dim} {backend:?} query {q}");
                        assert!((d[q * 5 + s] - want[s].0.sqrt()).abs() < 1e-5);
                    }
                }
            }
        }
    }

    /// A stopped camera: thousands of identical descriptors must not panic, and ties come
    /// back by index.
    /// The matrix-product scan across several row blocks, query blocks and partial lane
    /// chunks (N, Q not multiples of the block sizes or of the lane width), with exact
    /// duplicates planted at the block edges: the same neighbours and ties as brute force.
    #[test]
    fn flat_scan_across_blocks_equals_brute_force() {
        let mut rng = SplitMix64::new(7);
        let (n, q_count, dim) = (2 * GEMM_ROW_BLOCK + 37, GEMM_QUERY_BLOCK + 19, 12);
        let mut data = random(&mut rng, n * dim);
        for (from, to) in [(3, GEMM_ROW_BLOCK - 1), (5, GEMM_ROW_BLOCK), (9, n - 1)] {
            let row = data[from * dim..(from + 1) * dim].to_vec();
            data[to * dim..(to + 1) * dim].copy_from_slice(&row);
        }
        let mut queries = random(&mut rng, q_count * dim);
        queries[..dim].copy_from_slice(&data[3 * dim..4 * dim]);
        queries[GEMM_QUERY_BLOCK * dim..(GEMM_QUERY_BLOCK + 1) * dim].copy_from_slice(&data[9 * dim..10 * dim]);
        let index = DescriptorIndex::with_backend(data.clone(), dim, Some(Backend::Flat)).expect("valid");
        let k = 3;
        let (d, i) = index.query(&queries, k).expect("valid");
        for q in 0..q_count {
            let want = brute(&data, dim, &queries[q * dim..(q + 1) * dim], k);
            let got: Vec<usize> = i[q * k..(q + 1) * k].to_vec();
            assert_eq!(got, want.iter().map(|w| w.1).collect::<Vec<_>>(), "query {q}");
            for s in 0..k {
                assert!((d[q * k + s] - want[s].0.sqrt()).abs() < 1e-5, "query {q}");
            }
        }
        assert_eq!(&i[..2], &[3, GEMM_ROW_BLOCK - 1], "a duplicate across a block edge: ties by index");
    }

    #[test]
    fn many_identical_descriptors() {
        for dim in [3, 8, 32] {
            let mut data = vec![0.5_f32; 5000 * dim];
            data.extend(vec![1.0_f32; 10 * dim]);
            let index = DescriptorIndex::new(data, dim).expect("valid");
            let (d, i) = index.query(&vec![0.5_f32; dim], 3).expect("valid");
            assert_eq!(i, vec![0, 1, 2], "dim {dim}");
            assert!(d.iter().all(|&x| x == 0.0));
            let (_, i) = index.query(&vec![1.0_f32; dim], 1).expect("valid");
            assert_eq!(i, vec![5000]);
        }
    }

    /// Brute force in f64: the reference at magnitudes where f32 squares overflow or underflow.
    fn brute_f64(data: &[f32], dim: usize, q: &[f32], k: usize) -> Vec<(f64, usize)> {
        let mut all: Vec<(f64, usize)> = data
            .chunks_exact(dim)
            .enumerate()
            .map(|(i, r)| (r.iter().zip(q).map(|(&a, &b)| (f64::from(a) - f64::from(b)).powi(2)).sum::<f64>(), i))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        all
    }

    /// Finite values near 10²⁰ (and near 10⁻²⁵) used to give NaN/∞/0 distances in
    /// f32 and index 0 for every query; every backend now equals brute force in f64.
    #[test]
    fn exact_at_extreme_magnitudes() {
        let mut rng = SplitMix64::new(4);
        for scale in [1e20_f32, 3e37, 1e-25, 1e-40] {
            for dim in [3, 32] {
                let data: Vec<f32> = (0..100 * dim).map(|_| rng.normal() as f32 * scale).collect();
                let mut queries: Vec<f32> = data[7 * dim..8 * dim].to_vec();
                queries.extend_from_slice(&data[42 * dim..43 * dim]);
                queries.extend((0..dim).map(|_| rng.normal() as f32 * scale));
                for backend in [Backend::KdTree, Backend::Flat] {
                    if backend == Backend::KdTree && dim > KDTREE_MAX_DIM {
                        continue;
                    }
                    let index = DescriptorIndex::with_backend(data.clone(), dim, Some(backend)).expect("valid");
                    let (d, i) = index.query(&queries, 3).expect("finite input");
                    assert_eq!(&i[..1], &[7]);
                    assert_eq!(&i[3..4], &[42]);
                    for q in 0..3 {
                        let want = brute_f64(&data, dim, &queries[q * dim..(q + 1) * dim], 3);
                        for s in 0..3 {
                            assert_eq!(i[q * 3 + s], want[s].1, "scale {scale} dim {dim} {backend:?} query {q}");
                            let w = want[s].0.sqrt().min(f64::from(f32::MAX)) as f32;
                            assert!(d[q * 3 + s].is_finite() && d[q * 3 + s] == w, "{} vs {w}", d[q * 3 + s]);
                        }
                    }
                }
            }
        }
    }

    /// A huge query against ordinary data also takes the exact path.
    #[test]
    fn huge_query_against_ordinary_data() {
        let data: Vec<f32> = vec![0.0, 0.0, 1e25, 0.0, 0.0, 1e25];
        let index = DescriptorIndex::new(data, 2).expect("valid");
        let (d, i) = index.query(&[1e30, 0.0], 3).expect("finite");
        assert_eq!(i, vec![1, 0, 2]);
        assert!(d.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn backend_names_round_trip() {
        for b in Backend::ALL {
            assert_eq!(b.as_str().parse::<Backend>(), Ok(b));
        }
        assert!(matches!("ann".parse::<Backend>(), Err(GeolocError::InvalidInput { name, .. }) if name == "backend"));
    }

    #[test]
    fn bad_input() {
        assert!(DescriptorIndex::new(vec![], 3).is_err());
        assert!(DescriptorIndex::new(vec![1.0; 7], 3).is_err());
        assert!(DescriptorIndex::new(vec![f32::NAN; 6], 3).is_err());
        assert!(DescriptorIndex::with_backend(vec![1.0; 20], 10, Some(Backend::KdTree)).is_err());
        let index = DescriptorIndex::new(vec![1.0; 6], 3).expect("valid");
        assert!(index.query(&[1.0; 4], 1).is_err());
        assert!(index.query(&[1.0; 3], 0).is_err());
        assert!(index.query(&[1.0; 3], 3).is_err());
        assert!(index.query(&[f32::INFINITY, 0.0, 0.0], 1).is_err());
        let (d, i) = index.query(&[], 1).expect("no queries is fine");
        assert!(d.is_empty() && i.is_empty());
        let name_of = |e: GeolocError| match e {
            GeolocError::InvalidInput { name, .. } | GeolocError::NonFinite { name, .. } => name,
            other => panic!("{other:?}"),
        };
        assert_eq!(name_of(index.query(&[1.0; 3], 3).expect_err("k > N")), "k");
        assert_eq!(name_of(index.query(&[1.0; 4], 1).expect_err("ragged")), "queries");
        assert_eq!(name_of(index.query(&[0.0, f32::NAN, 0.0], 1).expect_err("NaN")), "queries");
        assert_eq!(name_of(DescriptorIndex::new(vec![f32::NAN; 6], 3).expect_err("NaN")), "descriptors");
    }
}
