//! A uniform grid over image points for radius queries (guided matching puts the model
//! points' projections in one and asks it around each query keypoint).
//!
//! Cells are squares of side `cell` px, indexed (⌊x/cell⌋, ⌊y/cell⌋) after shifting by the
//! points' minimum; the points of a cell are contiguous in one array (counting sort by
//! cell, then by index inside a cell). [`PointGrid::within`] visits the cells overlapping
//! the disc's bounding square and keeps the points with ‖p − c‖ ≤ r — exactly the set a
//! scan of all points keeps, in increasing index order per cell.

use nalgebra::Vector2;

/// Most cells along one side of the grid.
const MAX_SIDE: usize = 512;

/// (min, max) of the finite `points` per axis; None when there are none.
pub(super) fn bounds(points: &[Vector2<f64>]) -> Option<(Vector2<f64>, Vector2<f64>)> {
    let finite = || points.iter().filter(|k| k.x.is_finite() && k.y.is_finite());
    let lo = finite().fold(Vector2::repeat(f64::INFINITY), |m, k| m.inf(k));
    let hi = finite().fold(Vector2::repeat(f64::NEG_INFINITY), |m, k| m.sup(k));
    lo.x.is_finite().then_some((lo, hi))
}

/// Points bucketed by cell (see the module doc).
#[derive(Clone, Debug)]
pub(super) struct PointGrid<'a> {
    points: &'a [Vector2<f64>],
    origin: Vector2<f64>,
    cell: f64,
    cols: usize,
    rows: usize,
    /// Start of each cell's run in `order` (cols·rows + 1 entries).
    starts: Vec<usize>,
    /// Keypoint indices sorted by (cell, index).
    order: Vec<usize>,
}

impl<'a> PointGrid<'a> {
    /// Grid of `points` with square cells of side `cell` px (> 0, finite).
    pub(super) fn new(points: &'a [Vector2<f64>], cell: f64) -> Self {
        let (origin, spread) = bounds(points).map_or((Vector2::zeros(), Vector2::zeros()), |(lo, hi)| (lo, hi - lo));
        // at most MAX_SIDE cells a side: a huge spread only coarsens the grid, never breaks it
        let cell = cell.max(spread.x.max(spread.y) / (MAX_SIDE - 1) as f64);
        let (cols, rows) = ((spread.x / cell).floor() as usize + 1, (spread.y / cell).floor() as usize + 1);
        let mut grid = Self { points, origin, cell, cols, rows, starts: vec![0; cols * rows + 1], order: Vec::new() };
        let cells: Vec<Option<usize>> = points.iter().map(|k| grid.cell_of(k)).collect();
        for c in cells.iter().flatten() {
            grid.starts[c + 1] += 1;
        }
        for i in 0..cols * rows {
            grid.starts[i + 1] += grid.starts[i];
        }
        let mut next = grid.starts.clone();
        grid.order = vec![0; grid.starts[cols * rows]];
        for (i, c) in cells.iter().enumerate() {
            if let Some(c) = c {
                grid.order[next[*c]] = i;
                next[*c] += 1;
            }
        }
        grid
    }

    /// The cell of a finite point inside the grid (None outside or not finite).
    fn cell_of(&self, p: &Vector2<f64>) -> Option<usize> {
        let (cx, cy) = ((p.x - self.origin.x) / self.cell, (p.y - self.origin.y) / self.cell);
        let inside = cx >= 0.0 && cy >= 0.0 && cx < self.cols as f64 && cy < self.rows as f64;
        inside.then(|| cy as usize * self.cols + cx as usize)
    }

    /// The points within `r` px of `centre` (‖p − centre‖ ≤ r).
    pub(super) fn within(&self, centre: &Vector2<f64>, r: f64) -> impl Iterator<Item = usize> + '_ {
        // cells ⌊lo/cell⌋ ..= ⌊hi/cell⌋ clamped to 0..n; for x ≥ 0 the truncating `as usize`
        // is ⌊x⌋ (and saturates), which keeps libm's floor out of this hot loop
        let span = |lo: f64, hi: f64, n: usize| {
            let (lo, hi) = (lo / self.cell, hi / self.cell);
            if hi < 0.0 {
                return 0..0; // ⌊hi⌋ ≤ −1
            }
            let a = if lo > 0.0 { lo as usize } else { 0 };
            let b = (hi as usize).min(n - 1);
            if a <= b { a..b + 1 } else { 0..0 }
        };
        let d = centre - self.origin;
        let xs = span(d.x - r, d.x + r, self.cols);
        let ys = span(d.y - r, d.y + r, self.rows);
        let centre = *centre;
        // the squared test is exact where r² and the window are normal, finite numbers;
        // outside (absurd radii) every point takes the root
        let near =
            if r > 1e-150 && r < 1e150 { (r * r * (1.0 - 1e-9), r * r * (1.0 + 1e-9)) } else { (-1.0, f64::INFINITY) };
        ys.flat_map(move |y| {
            let row = y * self.cols;
            let (a, b) = (self.starts[row + xs.start], self.starts[row + xs.end]);
            self.order[a..b].iter().copied()
        })
        .filter(move |&i| {
            // ‖d‖ ≤ r decided on ‖d‖² away from r² (no square root); the root only within a
            // relative 1e-9 of it, where rounding could make the two tests differ
            let s = (self.points[i] - centre).norm_squared();
            s <= near.0 || (s <= near.1 && s.sqrt() <= r)
        })
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    proptest! {
        /// The grid's radius query is the brute-force scan, for clustered, spread and
        /// out-of-image centres, radii below and above the cell size.
        #[test]
        fn within_equals_a_scan(
            pts in prop::collection::vec((-50.0f64..700.0, -50.0f64..520.0), 0..300),
            centres in prop::collection::vec((-80.0f64..760.0, -80.0f64..560.0), 1..20),
            cell in 0.5f64..40.0,
            r in 0.0f64..60.0,
        ) {
            let keypoints: Vec<Vector2<f64>> = pts.iter().map(|&(x, y)| Vector2::new(x, y)).collect();
            let grid = PointGrid::new(&keypoints, cell);
            for &(x, y) in &centres {
                let c = Vector2::new(x, y);
                let mut got: Vec<usize> = grid.within(&c, r).collect();
                got.sort_unstable();
                let want: Vec<usize> = (0..keypoints.len()).filter(|&i| (keypoints[i] - c).norm() <= r).collect();
                prop_assert_eq!(got, want);
            }
        }
    }

    /// Keypoints on and a few ulps around the circle ‖k − c‖ = r, where the squared-distance
    /// shortcut could disagree with the root: the same set as the scan with ‖·‖ ≤ r.
    #[test]
    fn the_circle_itself_follows_the_norm() {
        let c = Vector2::new(311.37, 207.91);
        for r in [6.0, 0.1, 3.3, 7.000000001, 1e-3] {
            let mut keypoints = Vec::new();
            for i in 0..720 {
                let a = f64::from(i) * std::f64::consts::PI / 360.0;
                let k = c + Vector2::new(a.cos(), a.sin()) * r;
                for ulps in [-2i64, -1, 0, 1, 2] {
                    let nudge = |v: f64| f64::from_bits((v.to_bits() as i64 + ulps) as u64);
                    keypoints.push(Vector2::new(nudge(k.x), k.y));
                    keypoints.push(Vector2::new(k.x, nudge(k.y)));
                }
            }
            let grid = PointGrid::new(&keypoints, 6.0);
            let mut got: Vec<usize> = grid.within(&c, r).collect();
            got.sort_unstable();
            let want: Vec<usize> = (0..keypoints.len()).filter(|&i| (keypoints[i] - c).norm() <= r).collect();
            assert!(!want.is_empty() && want.len() < keypoints.len(), "r {r}: {}", want.len());
            assert_eq!(got, want, "r {r}");
        }
    }

    /// Radii whose square overflows or is subnormal: the scan's answer (the root decides).
    #[test]
    fn extreme_radii_follow_the_norm() {
        let cases = [
            (vec![Vector2::new(0.0, 0.0), Vector2::new(1.4e154, 1.4e154)], 1.5e154),
            (vec![Vector2::new(0.0, 0.0), Vector2::new(2.9e-162, 0.0)], 2.9e-162),
            (vec![Vector2::new(0.0, 0.0), Vector2::new(1e-160, 1e-160), Vector2::new(-3e-160, 0.0)], 2e-160),
        ];
        for (keypoints, r) in cases {
            let c = Vector2::zeros();
            let grid = PointGrid::new(&keypoints, 6.0);
            let mut got: Vec<usize> = grid.within(&c, r).collect();
            got.sort_unstable();
            let want: Vec<usize> = (0..keypoints.len()).filter(|&i| (keypoints[i] - c).norm() <= r).collect();
            assert_eq!(got, want, "r {r}");
        }
    }

    #[test]
    fn degenerate_inputs() {
        let none: Vec<Vector2<f64>> = Vec::new();
        assert_eq!(PointGrid::new(&none, 6.0).within(&Vector2::zeros(), 10.0).count(), 0);
        let odd = vec![Vector2::new(f64::NAN, 1.0), Vector2::new(3.0, 4.0), Vector2::new(1e12, -1e12)];
        let grid = PointGrid::new(&odd, 6.0);
        assert_eq!(grid.within(&Vector2::new(3.0, 4.0), 1.0).collect::<Vec<_>>(), vec![1]);
        assert_eq!(grid.within(&Vector2::new(1e12, -1e12), 1.0).collect::<Vec<_>>(), vec![2]);
    }
}
