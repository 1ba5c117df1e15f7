//! Local-descriptor matching between two images: brute force (parallel over the first
//! image's descriptors) with Hamming distance for binary descriptors (ORB: rows of bytes) and
//! Euclidean distance for float ones (SIFT), Lowe's ratio test, a mutual (cross) check, and an
//! epipolar check that uses the known poses of keyframes.
//!
//! Epipolar geometry for world_from_cam poses T_a, T_b: the relative pose b_from_a is
//! T_b⁻¹T_a = (R, t), the essential matrix E = t^ R maps a normalized point x_a of image a to
//! the epipolar line E x_a in image b, and F = K⁻ᵀ E K⁻¹ in pixels; a match is kept when the
//! Sampson distance (xᵦᵀFxₐ)² / (‖(Fxₐ)₁,₂‖² + ‖(Fᵀxᵦ)₁,₂‖²) is at most `max_px`².

use nalgebra::{Matrix3, Vector2, Vector3};

use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::{SE3, so3};

/// Descriptors of one image: N rows of `width` values.
#[derive(Clone, Copy, Debug)]
pub enum Descriptors<'a> {
    /// Binary descriptors, `width` bytes per row, compared by Hamming distance.
    Binary {
        /// Row-major bytes.
        data: &'a [u8],
        /// Bytes per descriptor.
        width: usize,
    },
    /// Float descriptors, `width` values per row, compared by Euclidean distance.
    Float {
        /// Row-major values.
        data: &'a [f32],
        /// Values per descriptor.
        width: usize,
    },
}

/// One descriptor row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Row<'a> {
    /// `width` bytes.
    Binary(&'a [u8]),
    /// `width` values.
    Float(&'a [f32]),
}

impl Row<'_> {
    /// **The** descriptor distance of geoloc, one meaning everywhere (matching, the BoW
    /// vocabulary, its k-means++ weights D²):
    /// * binary rows: the Hamming distance, in bits, d = Σ popcount(aᵢ ⊕ bᵢ);
    /// * float rows: the Euclidean distance d = √Σ(aᵢ − bᵢ)² (not squared), summed in f32.
    ///
    /// Rows of different kinds are infinitely far apart (entry points refuse mixing them).
    #[inline]
    pub fn distance(&self, other: &Row<'_>) -> f32 {
        match (*self, *other) {
            (Row::Binary(a), Row::Binary(b)) => hamming(a, b) as f32,
            (Row::Float(a), Row::Float(b)) => a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>().sqrt(),
            _ => f32::INFINITY,
        }
    }
}

impl<'a> Descriptors<'a> {
    /// Number of descriptors N (0 for a zero width, which [`Descriptors::check`] refuses).
    pub fn len(&self) -> usize {
        match *self {
            Self::Binary { data, width } => data.len().checked_div(width).unwrap_or(0),
            Self::Float { data, width } => data.len().checked_div(width).unwrap_or(0),
        }
    }

    /// Whether there are no descriptors.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes (binary) or values (float) per descriptor.
    pub fn width(&self) -> usize {
        match *self {
            Self::Binary { width, .. } | Self::Float { width, .. } => width,
        }
    }

    /// Whether the rows are binary (Hamming) descriptors.
    pub fn is_binary(&self) -> bool {
        matches!(self, Self::Binary { .. })
    }

    /// Row `i` (panics past the end, like slice indexing; callers index below [`Self::len`]).
    #[inline]
    pub fn row(&self, i: usize) -> Row<'a> {
        match *self {
            Self::Binary { data, width } => Row::Binary(&data[i * width..(i + 1) * width]),
            Self::Float { data, width } => Row::Float(&data[i * width..(i + 1) * width]),
        }
    }

    /// [`Row::distance`] between row `i` of `self` and row `j` of `other`.
    #[inline]
    pub fn distance(&self, i: usize, other: &Descriptors<'_>, j: usize) -> f32 {
        self.row(i).distance(&other.row(j))
    }

    /// Checks the view for argument `name`: a positive width, whole rows, finite values.
    ///
    /// # Errors
    /// [`GeolocError::InvalidInput`] for a zero width or a partial row,
    /// [`GeolocError::NonFinite`] (with the row) for NaN or ±∞ in float rows.
    pub fn check(&self, name: &str) -> Result<()> {
        let (values, width) = match *self {
            Self::Binary { data, width } => (data.len(), width),
            Self::Float { data, width } => (data.len(), width),
        };
        if width == 0 || !values.is_multiple_of(width) {
            return Err(GeolocError::invalid(
                name,
                format!("expected rows of a positive width, got {values} values for width {width}"),
            ));
        }
        if let Self::Float { data, width } = *self
            && let Some(i) = data.iter().position(|v| !v.is_finite())
        {
            return Err(GeolocError::NonFinite { name: name.to_owned(), index: i / width });
        }
        Ok(())
    }
}

/// Owned descriptors (of one image, or a vocabulary's centres).
#[derive(Clone, Debug, PartialEq)]
pub enum DescriptorSet {
    /// Binary, `width` bytes per keypoint (ORB).
    Binary {
        /// Row-major bytes.
        data: Vec<u8>,
        /// Bytes per descriptor.
        width: usize,
    },
    /// Float, `width` values per keypoint (SIFT).
    Float {
        /// Row-major values.
        data: Vec<f32>,
        /// Values per descriptor.
        width: usize,
    },
}

impl DescriptorSet {
    /// A borrowed view.
    pub fn view(&self) -> Descriptors<'_> {
        match self {
            Self::Binary { data, width } => Descriptors::Binary { data, width: *width },
            Self::Float { data, width } => Descriptors::Float { data, width: *width },
        }
    }

    /// Number of descriptors (see [`Descriptors::len`]).
    pub fn len(&self) -> usize {
        self.view().len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The rows of `parts` one after the other (all of the first part's kind and width; a
    /// part of another kind is skipped — callers check kinds first). Empty float rows of
    /// width 0 for no parts.
    pub fn stack<'a>(parts: impl IntoIterator<Item = &'a DescriptorSet>) -> Self {
        let mut parts = parts.into_iter().peekable();
        match parts.peek() {
            Some(Self::Binary { width, .. }) => {
                let width = *width;
                let data = parts.filter_map(|p| if let Self::Binary { data, .. } = p { Some(data) } else { None });
                Self::Binary { data: data.flatten().copied().collect(), width }
            }
            Some(Self::Float { width, .. }) => {
                let width = *width;
                let data = parts.filter_map(|p| if let Self::Float { data, .. } = p { Some(data) } else { None });
                Self::Float { data: data.flatten().copied().collect(), width }
            }
            None => Self::Float { data: Vec::new(), width: 0 },
        }
    }

    /// The rows `rows`, in that order.
    pub fn select(&self, rows: &[usize]) -> Self {
        match self {
            Self::Binary { data, width } => Self::Binary {
                data: rows.iter().flat_map(|&r| data[r * width..(r + 1) * width].iter().copied()).collect(),
                width: *width,
            },
            Self::Float { data, width } => Self::Float {
                data: rows.iter().flat_map(|&r| data[r * width..(r + 1) * width].iter().copied()).collect(),
                width: *width,
            },
        }
    }
}

/// Hamming distance of two byte strings, eight bytes per popcount.
#[inline]
pub fn hamming(a: &[u8], b: &[u8]) -> u32 {
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: u32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| (x ^ y).count_ones()).sum();
    ca.zip(cb)
        .map(|(x, y)| {
            let x = u64::from_le_bytes(x.try_into().expect("invariant: chunks of 8"));
            let y = u64::from_le_bytes(y.try_into().expect("invariant: chunks of 8"));
            (x ^ y).count_ones()
        })
        .sum::<u32>()
        + tail
}

/// Options of [`match_descriptors`], the same for both descriptor kinds because every test
/// is in the units of [`Row::distance`] of the kind at hand:
/// * `ratio` is unit-free (d₁ < r·d₂ with d the Hamming distance in bits for binary rows and
///   the Euclidean distance, not its square, for float rows), so Lowe's 0.8 means the same
///   for ORB, SIFT (rows of norm ≈ 512 from OpenCV) and RootSIFT (rows of norm 1). Measured
///   on 7-Scenes kitchen training pairs with known poses (mutual nearest neighbours; true:
///   Sampson < 1 px, false: > 10 px), ORB at 0.8 keeps 78 % of the true and 10 % of the false
///   matches; from the same seed keyframes SIFT with 0.8 gives more PnP inliers
///   than ORB (median 35 vs 19 on the 0–99 fold).
/// * `max_distance` is off by default: it is an absolute distance whose scale depends on
///   the kind (bits out of 256 for ORB, ≈ 0…512 for SIFT, 0…√2 for RootSIFT); a value set
///   for one kind is meaningless for another.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchOptions {
    /// Lowe's ratio: keep a match when best < ratio · second best (None: no ratio test;
    /// default 0.8).
    pub ratio: Option<f32>,
    /// Keep only matches that are each other's best (default true).
    pub mutual: bool,
    /// Keep only matches with d₁ ≤ this, in [`Row::distance`] units of the kind (None: no
    /// limit, the default).
    pub max_distance: Option<f32>,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self { ratio: Some(0.8), mutual: true, max_distance: None }
    }
}

/// One correspondence: index in a, index in b, descriptor distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    /// Row of the first image's descriptors.
    pub a: usize,
    /// Row of the second image's descriptors.
    pub b: usize,
    /// Hamming (bits) or Euclidean distance.
    pub distance: f32,
}

/// Best and second-best of `i` (of `from`) among all rows of `to`: (best index, best, second).
fn best_two(from: &Descriptors<'_>, i: usize, to: &Descriptors<'_>) -> (usize, f32, f32) {
    // the kind is matched once per query row, not once per distance (the hot loop)
    match (from.row(i), *to) {
        (Row::Binary(q), Descriptors::Binary { data, width }) => binary_best_two(q, data, width),
        (q @ Row::Float(_), Descriptors::Float { data, width }) => {
            best_two_of(data.chunks_exact(width).map(|r| q.distance(&Row::Float(r))))
        }
        _ => (usize::MAX, f32::INFINITY, f32::INFINITY),
    }
}

/// [`best_two`] of binary row `q` among the rows of `rows`: the hot loop of ORB matching.
/// Its speed rests on `u64::count_ones` being one instruction: `.cargo/config.toml` enables
/// `popcnt` for x86-64 (the baseline target does not assume it; without it the bit count is
/// a dozen instructions per 8 bytes and ORB matching about twice as slow).
/// ORB's 32-byte rows go through [`best_two_words`] (the query held in registers, integer
/// compares); other widths through [`hamming`].
fn binary_best_two(q: &[u8], rows: &[u8], width: usize) -> (usize, f32, f32) {
    if width == 32 {
        return best_two_words::<4>(q, rows);
    }
    best_two_of(rows.chunks_exact(width).map(|r| hamming(q, r) as f32))
}

/// [`binary_best_two`] for rows of exactly `8·W` bytes: the same (index, best, second) as
/// [`best_two_of`] over [`hamming`] (first index on ties; ∞ for a missing second).
fn best_two_words<const W: usize>(q: &[u8], rows: &[u8]) -> (usize, f32, f32) {
    let qw = row_words::<W>(q);
    let (mut best, mut d1, mut d2) = (usize::MAX, u32::MAX, u32::MAX);
    for (j, r) in rows.chunks_exact(8 * W).enumerate() {
        let rw = row_words::<W>(r);
        let d: u32 = (0..W).map(|w| (qw[w] ^ rw[w]).count_ones()).sum();
        if d < d1 {
            (d2, d1, best) = (d1, d, j);
        } else if d < d2 {
            d2 = d;
        }
    }
    (best, bits_as_f32(d1), bits_as_f32(d2))
}

/// The first `8·W` bytes of `row` as W little-endian words.
#[inline]
fn row_words<const W: usize>(row: &[u8]) -> [u64; W] {
    std::array::from_fn(|w| u64::from_le_bytes(row[8 * w..8 * w + 8].try_into().expect("invariant: 8 bytes")))
}

/// A Hamming distance in bits as a [`Row::distance`]; `u32::MAX` (no row) as ∞.
#[inline]
fn bits_as_f32(d: u32) -> f32 {
    if d == u32::MAX { f32::INFINITY } else { d as f32 }
}

/// Rows of the first image per block of [`mutual_best_words`] (one parallel task).
const MUTUAL_BLOCK_ROWS: usize = 64;

/// Both directions of a mutual match of binary rows of exactly `8·W` bytes, every distance
/// computed once: per row i of `a` its best two in `b` — (index, d₁, d₂), as
/// [`best_two_words`] — and per row j of `b` its nearest row of `a`, the first index on ties
/// (what [`best_two_words`] of row j against `a` gives as its best). Separate scans in the two
/// directions computed each of the |a|·|b| distances twice.
///
/// The rows of `a` are cut into blocks of [`MUTUAL_BLOCK_ROWS`] scanned in parallel, each
/// keeping its own minimum per row of `b` (the first row on ties, as its rows are scanned in
/// order); the blocks' minima are merged in block order, a later block winning only with a
/// strictly smaller distance — the same result whatever the schedule or thread count.
fn mutual_best_words<const W: usize>(a: &[u8], b: &[u8]) -> (BestTwo, Vec<usize>) {
    let row_bytes = 8 * W;
    let b_words: Vec<[u64; W]> = b.chunks_exact(row_bytes).map(row_words::<W>).collect();
    let a_rows: Vec<&[u8]> = a.chunks_exact(row_bytes).collect();
    let blocks = crate::parallel::map_indices(a_rows.len().div_ceil(MUTUAL_BLOCK_ROWS), 2, |k| {
        let start = k * MUTUAL_BLOCK_ROWS;
        let end = (start + MUTUAL_BLOCK_ROWS).min(a_rows.len());
        let mut nearest_in_block = vec![(u32::MAX, usize::MAX); b_words.len()];
        let mut best_two = Vec::with_capacity(end - start);
        for (i, row) in a_rows.iter().enumerate().take(end).skip(start) {
            let q = row_words::<W>(row);
            let (mut best, mut d1, mut d2) = (usize::MAX, u32::MAX, u32::MAX);
            for (j, (r, nearest)) in b_words.iter().zip(nearest_in_block.iter_mut()).enumerate() {
                let d: u32 = (0..W).map(|w| (q[w] ^ r[w]).count_ones()).sum();
                if d < d1 {
                    (d2, d1, best) = (d1, d, j);
                } else if d < d2 {
                    d2 = d;
                }
                if d < nearest.0 {
                    *nearest = (d, i);
                }
            }
            best_two.push((best, bits_as_f32(d1), bits_as_f32(d2)));
        }
        (best_two, nearest_in_block)
    });
    let mut forward = Vec::with_capacity(a_rows.len());
    let mut nearest = vec![(u32::MAX, usize::MAX); b_words.len()];
    for (best_two, nearest_in_block) in blocks {
        forward.extend(best_two);
        for (n, m) in nearest.iter_mut().zip(nearest_in_block) {
            if m.0 < n.0 {
                *n = m;
            }
        }
    }
    (forward, nearest.into_iter().map(|(_, i)| i).collect())
}

/// (index of the smallest, smallest, second smallest) of `distances` (first index on ties).
#[inline]
fn best_two_of(distances: impl Iterator<Item = f32>) -> (usize, f32, f32) {
    let (mut best, mut d1, mut d2) = (usize::MAX, f32::INFINITY, f32::INFINITY);
    for (j, d) in distances.enumerate() {
        if d < d1 {
            (d2, d1, best) = (d1, d, j);
        } else if d < d2 {
            d2 = d;
        }
    }
    (best, d1, d2)
}

/// Per row of `from`: (nearest row of `to`, its distance, the second-nearest distance).
type BestTwo = Vec<(usize, f32, f32)>;

/// Rows per parallel task below which matching stays on the calling thread.
const MATCH_PARALLEL_MIN_ROWS: usize = 64;

/// Matches the descriptors of two images; see the module doc. Sorted by `a`. Distances are
/// [`Row::distance`]s, exact for every finite input (float rows go through the exact
/// [`crate::retrieval::DescriptorIndex`] scan).
///
/// # Errors
/// Mixed binary/float descriptors, different widths, a zero width, non-finite float values
/// (named `descriptors_a` / `descriptors_b`), a ratio outside (0, 1], a negative or NaN
/// `max_distance`.
pub fn match_descriptors(a: &Descriptors<'_>, b: &Descriptors<'_>, options: &MatchOptions) -> Result<Vec<Match>> {
    a.check("descriptors_a")?;
    b.check("descriptors_b")?;
    if a.is_binary() != b.is_binary() {
        return Err(GeolocError::invalid("descriptors_b", "binary and float descriptors cannot be compared"));
    }
    if a.width() != b.width() {
        return Err(GeolocError::invalid(
            "descriptors_b",
            format!("width {} differs from descriptors_a's {}", b.width(), a.width()),
        ));
    }
    if let Some(r) = options.ratio
        && !(r > 0.0 && r <= 1.0)
    {
        return Err(GeolocError::invalid("ratio", format!("must be in (0, 1], got {r}")));
    }
    if let Some(m) = options.max_distance
        && (m.is_nan() || m < 0.0)
    {
        return Err(GeolocError::invalid("max_distance", format!("must be ≥ 0, got {m}")));
    }
    if a.is_empty() || b.is_empty() {
        return Ok(Vec::new());
    }
    let (forward, backward) = match (a, b) {
        (Descriptors::Float { data: da, width }, Descriptors::Float { data: db, .. }) => {
            (float_best_two(da, db, *width)?, options.mutual.then(|| float_nearest(db, da, *width)).transpose()?)
        }
        (Descriptors::Binary { data: da, width: 32 }, Descriptors::Binary { data: db, .. }) if options.mutual => {
            let (forward, backward) = mutual_best_words::<4>(da, db);
            (forward, Some(backward))
        }
        _ => (
            crate::parallel::map_indices(a.len(), MATCH_PARALLEL_MIN_ROWS, |i| best_two(a, i, b)),
            options
                .mutual
                .then(|| crate::parallel::map_indices(b.len(), MATCH_PARALLEL_MIN_ROWS, |j| best_two(b, j, a).0)),
        ),
    };
    Ok(forward
        .into_iter()
        .enumerate()
        .filter(|&(_, (j, d1, d2))| {
            j != usize::MAX && options.ratio.is_none_or(|r| d1 < r * d2) && options.max_distance.is_none_or(|m| d1 <= m)
        })
        .filter(|&(i, (j, _, _))| backward.as_ref().is_none_or(|back| back[j] == i))
        .map(|(i, (j, d, _))| Match { a: i, b: j, distance: d })
        .collect())
}

/// Float rows: the exact k-NN of the retrieval index (blocked matrix products + exact
/// re-scoring, an f64 scan at extreme magnitudes) finds the same two nearest as
/// [`best_two`], several times faster.
fn float_best_two(from: &[f32], to: &[f32], width: usize) -> Result<BestTwo> {
    use crate::retrieval::{Backend, DescriptorIndex};
    let index = DescriptorIndex::with_backend(to.to_vec(), width, Some(Backend::Flat))?;
    let k = index.len().min(2);
    let (dist, idx) = index.query(from, k)?;
    Ok((0..from.len() / width)
        .map(|i| (idx[i * k], dist[i * k], if k == 2 { dist[i * k + 1] } else { f32::INFINITY }))
        .collect())
}

/// Float rows: the nearest row of `to` for each row of `from`.
fn float_nearest(from: &[f32], to: &[f32], width: usize) -> Result<Vec<usize>> {
    use crate::retrieval::{Backend, DescriptorIndex};
    let index = DescriptorIndex::with_backend(to.to_vec(), width, Some(Backend::Flat))?;
    Ok(index.query(from, 1)?.1)
}

/// The fundamental matrix F (pixels) with x_bᵀ F x_a = 0 for images taken at world_from_cam
/// poses `pose_a` and `pose_b` by `camera`: F = K⁻ᵀ t^ R K⁻¹ with (R, t) = T_b⁻¹ T_a.
pub fn fundamental_matrix(camera: &Camera, pose_a: &SE3, pose_b: &SE3) -> Matrix3<f64> {
    let b_from_a = pose_b.inverse() * *pose_a;
    let e = so3::hat(&b_from_a.translation) * b_from_a.rotation.matrix();
    let k_inv = camera.inverse_matrix();
    k_inv.transpose() * e * k_inv
}

/// Sampson distance (pixels) of the pair (x_a, x_b) to the epipolar geometry F.
pub fn sampson_distance(f: &Matrix3<f64>, xa: &Vector2<f64>, xb: &Vector2<f64>) -> f64 {
    let (pa, pb) = (Vector3::new(xa.x, xa.y, 1.0), Vector3::new(xb.x, xb.y, 1.0));
    let fa = f * pa;
    let fb = f.transpose() * pb;
    let num = pb.dot(&fa);
    let den = fa.x * fa.x + fa.y * fa.y + fb.x * fb.x + fb.y * fb.y;
    if den <= 0.0 { f64::INFINITY } else { (num * num / den).sqrt() }
}

/// Which `pairs` have keypoints within `max_px` (Sampson) of the epipolar geometry of the
/// two known poses: a mask over `pairs` (true: kept). Keypoints are undistorted pixels.
///
/// # Errors
/// A pair indexing past the keypoints (`pairs`), or a non-positive `max_px`.
pub fn epipolar_filter(
    camera: &Camera,
    pose_a: &SE3,
    pose_b: &SE3,
    keypoints_a: &[Vector2<f64>],
    keypoints_b: &[Vector2<f64>],
    pairs: &[Match],
    max_px: f64,
) -> Result<Vec<bool>> {
    if !(max_px.is_finite() && max_px > 0.0) {
        return Err(GeolocError::invalid("max_px", format!("must be finite and > 0, got {max_px}")));
    }
    if let Some(i) = pairs.iter().position(|m| m.a >= keypoints_a.len() || m.b >= keypoints_b.len()) {
        return Err(GeolocError::invalid(
            "pairs",
            format!("pairs[{i}] = ({}, {}) indexes past the keypoints", pairs[i].a, pairs[i].b),
        ));
    }
    let f = fundamental_matrix(camera, pose_a, pose_b);
    Ok(pairs.iter().map(|m| sampson_distance(&f, &keypoints_a[m.a], &keypoints_b[m.b]) <= max_px).collect())
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // Hamming distances are small integers held exactly in f32
mod tests {
    use super::*;
    use crate::camera::project;
    use crate::error::GeolocError;
    use crate::testing::{SplitMix64, look_at};

    fn random_bytes(rng: &mut SplitMix64, n: usize) -> Vec<u8> {
        (0..n).map(|_| (rng.next_u64() & 0xff) as u8).collect()
    }

    #[test]
    fn hamming_known_value_and_brute_force_equality() {
        let a = [0b1111_0000u8, 0xff];
        let b = [0b0000_0000u8, 0xfe];
        let (da, db) = (Descriptors::Binary { data: &a, width: 2 }, Descriptors::Binary { data: &b, width: 2 });
        assert_eq!(da.distance(0, &db, 0), 5.0);
        let mut rng = SplitMix64::new(1);
        let x = random_bytes(&mut rng, 200 * 32);
        let y = random_bytes(&mut rng, 300 * 32);
        let (dx, dy) = (Descriptors::Binary { data: &x, width: 32 }, Descriptors::Binary { data: &y, width: 32 });
        let plain = MatchOptions { ratio: None, mutual: false, max_distance: None };
        let m = match_descriptors(&dx, &dy, &plain).expect("valid");
        assert_eq!(m.len(), 200);
        for mm in &m {
            let brute = (0..300).map(|j| dx.distance(mm.a, &dy, j)).fold(f32::INFINITY, f32::min);
            assert_eq!(mm.distance, brute);
        }
    }

    /// The binary scan gives the best two of a bit-by-bit count, widths with and without a
    /// partial 8-byte chunk.
    #[test]
    fn binary_scan_equals_a_bitwise_count() {
        let bits = |a: &[u8], b: &[u8]| -> u32 {
            a.iter().zip(b).map(|(x, y)| (0..8).filter(|k| ((x ^ y) >> k) & 1 == 1).count() as u32).sum()
        };
        let mut rng = SplitMix64::new(11);
        let one = random_bytes(&mut rng, 32);
        assert_eq!(binary_best_two(&one, &one, 32), (0, 0.0, f32::INFINITY));
        for width in [32, 61, 3] {
            let rows = random_bytes(&mut rng, 150 * width);
            for _ in 0..20 {
                let q = random_bytes(&mut rng, width);
                let mut d: Vec<(u32, usize)> =
                    rows.chunks_exact(width).enumerate().map(|(j, r)| (bits(&q, r), j)).collect();
                d.sort();
                let want = (d[0].1, d[0].0 as f32, d[1].0 as f32);
                assert_eq!(binary_best_two(&q, &rows, width), want, "width {width}");
            }
        }
    }

    /// The one-pass mutual scan gives what the two separate scans give — each row's best two,
    /// each column's nearest row with the first index on ties — for sizes on and off the
    /// block size, with many ties (descriptors of few distinct bits), on 1 and 2 threads.
    #[test]
    fn one_pass_mutual_scan_equals_two_scans() {
        use crate::parallel::{Parallelism, with_parallelism};
        use std::num::NonZero;
        let mut rng = SplitMix64::new(21);
        for (n_a, n_b, mask) in [(1, 1, 0xff), (64, 10, 0xff), (65, 200, 0x03), (300, 129, 0x01), (200, 300, 0xff)] {
            let mut bytes = |n: usize| -> Vec<u8> { (0..n * 32).map(|_| (rng.next_u64() & mask) as u8).collect() };
            let (a, b) = (bytes(n_a), bytes(n_b));
            let (da, db) = (Descriptors::Binary { data: &a, width: 32 }, Descriptors::Binary { data: &b, width: 32 });
            let forward: BestTwo = (0..n_a).map(|i| best_two(&da, i, &db)).collect();
            let backward: Vec<usize> = (0..n_b).map(|j| best_two(&db, j, &da).0).collect();
            for threads in [1, 2] {
                let p = Parallelism::Threads(NonZero::new(threads).expect("> 0"));
                let (f, back) = with_parallelism(&p, || mutual_best_words::<4>(&a, &b));
                assert_eq!(f, forward, "{n_a}×{n_b}, mask {mask:#x}, {threads} thread(s)");
                assert_eq!(back, backward, "{n_a}×{n_b}, mask {mask:#x}, {threads} thread(s)");
            }
        }
    }

    /// Float descriptors: perturbed copies match back to their originals through the ratio
    /// and mutual checks, distractors do not.
    #[test]
    fn perturbed_copies_match_back() {
        let mut rng = SplitMix64::new(2);
        let width = 128;
        let a: Vec<f32> = (0..500 * width).map(|_| rng.normal() as f32).collect();
        let perm: Vec<usize> = (0..500).rev().collect();
        let mut b = vec![0.0f32; 500 * width];
        for (i, &p) in perm.iter().enumerate() {
            for c in 0..width {
                b[p * width + c] = a[i * width + c] + 0.05 * rng.normal() as f32;
            }
        }
        let m = match_descriptors(
            &Descriptors::Float { data: &a, width },
            &Descriptors::Float { data: &b, width },
            &MatchOptions::default(),
        )
        .expect("valid");
        assert_eq!(m.len(), 500);
        assert!(m.iter().all(|mm| mm.b == perm[mm.a]));
    }

    /// Float descriptors near 10²⁰ (finite in f32, but their squares are not) used
    /// to find 0 of 50 self-matches.
    #[test]
    fn self_matches_at_extreme_magnitudes() {
        let mut rng = SplitMix64::new(8);
        for scale in [1e20_f32, 1e-30] {
            let x: Vec<f32> = (0..50 * 16).map(|_| rng.normal() as f32 * scale).collect();
            let d = Descriptors::Float { data: &x, width: 16 };
            let m = match_descriptors(&d, &d, &MatchOptions::default()).expect("finite input");
            assert_eq!(m.len(), 50, "scale {scale}");
            assert!(m.iter().all(|mm| mm.a == mm.b && mm.distance == 0.0));
        }
    }

    #[test]
    fn epipolar_check_keeps_consistent_pairs_only() {
        let cam = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
        let target = Vector3::new(0.0, 0.0, 5.0);
        let (pa, pb) =
            (look_at(&Vector3::new(-0.3, 0.0, 0.0), &target), look_at(&Vector3::new(0.3, 0.1, 0.0), &target));
        let mut rng = SplitMix64::new(3);
        let points: Vec<Vector3<f64>> = (0..100).map(|_| target + rng.unit_vector() * 1.5).collect();
        let ka: Vec<Vector2<f64>> = points.iter().map(|x| project(&cam, &pa, x).uv).collect();
        let mut kb: Vec<Vector2<f64>> = points.iter().map(|x| project(&cam, &pb, x).uv).collect();
        for k in kb.iter_mut().take(20) {
            *k += Vector2::new(0.0, 40.0); // off the epipolar line
        }
        let f = fundamental_matrix(&cam, &pa, &pb);
        assert!(sampson_distance(&f, &ka[50], &kb[50]) < 1e-9);
        let matches: Vec<Match> = (0..100).map(|i| Match { a: i, b: i, distance: 0.0 }).collect();
        let mask = epipolar_filter(&cam, &pa, &pb, &ka, &kb, &matches, 2.0).expect("valid");
        // the epipolar line of point i in image b, independently of F: through the projections
        // of two points of the ray of image a through it (the point itself and one twice as
        // far); the keypoint's distance to it bounds the Sampson distance, which moves both
        // keypoints (≈ d/√2 for views this alike)
        let line_distance = |i: usize| {
            let (c, x) = (pa.translation, points[i]);
            let (p, q) = (project(&cam, &pb, &x).uv, project(&cam, &pb, &(c + 2.0 * (x - c))).uv);
            let dir = (q - p).normalize();
            let r = kb[i] - p;
            (r - dir * r.dot(&dir)).norm()
        };
        let mut refused_shifted = 0;
        for (i, keep) in mask.iter().enumerate() {
            let d = line_distance(i);
            if d <= 2.0 {
                assert!(*keep, "pair {i}: {d} px from its epipolar line, refused");
            } else if d > 2.0 * 2f64.sqrt() * 1.2 {
                assert!(!*keep, "pair {i}: {d} px from its epipolar line, kept");
                refused_shifted += 1;
            }
        }
        // a vertical shift can lie along a near-vertical epipolar line for a few points
        assert!(mask[20..].iter().all(|k| *k) && refused_shifted >= 10, "{refused_shifted}");
    }

    #[test]
    fn bad_input() {
        let x = [0u8; 32];
        let y = [0.0f32; 32];
        assert!(
            match_descriptors(
                &Descriptors::Binary { data: &x, width: 32 },
                &Descriptors::Float { data: &y, width: 32 },
                &MatchOptions::default()
            )
            .is_err()
        );
        assert!(
            match_descriptors(
                &Descriptors::Binary { data: &x, width: 32 },
                &Descriptors::Binary { data: &x, width: 16 },
                &MatchOptions::default()
            )
            .is_err()
        );
        let bad = MatchOptions { ratio: Some(1.5), ..MatchOptions::default() };
        assert!(
            match_descriptors(
                &Descriptors::Binary { data: &x, width: 32 },
                &Descriptors::Binary { data: &x, width: 32 },
                &bad
            )
            .is_err()
        );
        let cam = Camera::new(1.0, 1.0, 0.0, 0.0).expect("valid");
        let m = [Match { a: 3, b: 0, distance: 0.0 }];
        fn name_of<T>(r: Result<T>) -> String {
            match r {
                Err(GeolocError::InvalidInput { name, .. } | GeolocError::NonFinite { name, .. }) => name,
                Err(other) => panic!("expected a named error, got {other:?}"),
                Ok(_) => panic!("expected a named error, got Ok"),
            }
        }
        let (i, k) = (SE3::identity(), [Vector2::zeros(); 4]);
        assert_eq!(name_of(epipolar_filter(&cam, &i, &i, &[], &[], &m, 1.0)), "pairs");
        assert_eq!(name_of(epipolar_filter(&cam, &i, &i, &k, &k, &[], 0.0)), "max_px");
        assert_eq!(name_of(epipolar_filter(&cam, &i, &i, &k, &k, &[], f64::NAN)), "max_px");
        let nan = [1.0, f32::NAN, 0.0, 0.0];
        let fine = [0.0f32; 4];
        let (dn, df) = (Descriptors::Float { data: &nan, width: 2 }, Descriptors::Float { data: &fine, width: 2 });
        assert_eq!(name_of(match_descriptors(&df, &dn, &MatchOptions::default())), "descriptors_b");
        assert_eq!(name_of(match_descriptors(&dn, &df, &MatchOptions::default())), "descriptors_a");
        let bad_max = MatchOptions { max_distance: Some(-1.0), ..MatchOptions::default() };
        assert_eq!(name_of(match_descriptors(&df, &df, &bad_max)), "max_distance");
        let ragged = Descriptors::Float { data: &fine[..3], width: 2 };
        assert_eq!(name_of(match_descriptors(&ragged, &df, &MatchOptions::default())), "descriptors_a");
    }
}
