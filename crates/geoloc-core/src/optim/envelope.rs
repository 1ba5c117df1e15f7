//! Block-envelope (skyline) Cholesky of a symmetric positive definite matrix of 6×6 blocks,
//! and its selected inverse: the linear algebra of bundle adjustment's reduced camera system.
//!
//! A symmetric matrix A of n × n blocks (6×6 each) is stored by block rows, row i holding
//! the blocks A_ij for j = first(i) … i (its *envelope*; blocks left of first(i) are zero).
//! Keyframes in capture order co-observe points mostly with their neighbours in time, so the
//! envelope is narrow except where the camera revisits a place (and in the last row when it
//! holds a parameter every keyframe shares). The Cholesky factor L (A = L Lᵀ) has no fill
//! outside the envelope:
//!
//!   L_ij = (A_ij − Σ_{k = max(first(i), first(j))}^{j−1} L_ik L_jkᵀ) L_jj⁻ᵀ,   j < i
//!   L_ii = chol(A_ii − Σ_{k = first(i)}^{i−1} L_ik L_ikᵀ).
//!
//! The selected inverse Z = A⁻¹ restricted to the envelope follows from Lᵀ Z = L⁻¹
//! (Takahashi's recurrence), column j from the last to the first, with
//! C(j) = {k > j : first(k) ≤ j} the rows below the diagonal of column j:
//!
//!   Z_ji = −L_jj⁻ᵀ Σ_{k ∈ C(j)} L_kjᵀ Z_ki   (i ∈ C(j)),
//!   Z_jj = L_jj⁻ᵀ (L_jj⁻¹ − Σ_{k ∈ C(j)} L_kjᵀ Z_kj),
//!
//! every Z_ki it needs (k, i ∈ C(j)) lying in the envelope already computed. The diagonal
//! blocks of Z are the marginal covariances of a Gauss–Newton problem whose normal matrix
//! is A; the off-diagonal ones inside the envelope are the cross-covariances of parameters
//! that share an observation.
//!
//! Every sum runs in index order on one thread: the same matrix gives the same bits.

use nalgebra::Matrix6;

/// A symmetric matrix of 6×6 blocks stored by its lower block envelope (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct BlockEnvelope {
    /// first(i): the first block column of row i (≤ i).
    first: Vec<usize>,
    /// Row i: the blocks (i, first(i)) … (i, i).
    rows: Vec<Vec<Matrix6<f64>>>,
}

impl BlockEnvelope {
    /// The zero matrix with envelope `first` (each `first[i]` is clamped to ≤ i).
    pub fn zeros(first: &[usize]) -> Self {
        let first: Vec<usize> = first.iter().enumerate().map(|(i, &f)| f.min(i)).collect();
        let rows = first.iter().enumerate().map(|(i, &f)| vec![Matrix6::zeros(); i - f + 1]).collect();
        Self { first, rows }
    }

    /// Number of block rows.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether the matrix has no block.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// first(i).
    pub fn first(&self, i: usize) -> usize {
        self.first[i]
    }

    /// Whether block (i, j), i ≥ j, lies in the envelope.
    pub fn contains(&self, i: usize, j: usize) -> bool {
        j <= i && j >= self.first[i]
    }

    /// Block (i, j) for i ≥ j inside the envelope.
    ///
    /// # Panics
    /// Outside the envelope (a caller's indexing bug).
    pub fn block(&self, i: usize, j: usize) -> &Matrix6<f64> {
        &self.rows[i][j - self.first[i]]
    }

    /// Mutable block (i, j) for i ≥ j inside the envelope.
    ///
    /// # Panics
    /// Outside the envelope.
    pub fn block_mut(&mut self, i: usize, j: usize) -> &mut Matrix6<f64> {
        &mut self.rows[i][j - self.first[i]]
    }

    /// Block (i, j) of the symmetric matrix for any i, j inside the envelope (transposed
    /// when i < j).
    pub fn symmetric_block(&self, i: usize, j: usize) -> Matrix6<f64> {
        if i >= j { *self.block(i, j) } else { self.block(j, i).transpose() }
    }

    /// The Cholesky factor L (A = L Lᵀ), or None when A is not positive definite.
    pub fn cholesky(&self) -> Option<EnvelopeCholesky> {
        let n = self.len();
        let mut rows: Vec<Vec<Matrix6<f64>>> = Vec::with_capacity(n);
        let mut diagonal_inverse: Vec<Matrix6<f64>> = Vec::with_capacity(n);
        for i in 0..n {
            let fi = self.first[i];
            let mut row = self.rows[i].clone();
            for j in fi..i {
                let fj = self.first[j];
                let mut s = row[j - fi];
                for k in fi.max(fj)..j {
                    s -= row[k - fi] * rows[j][k - fj].transpose();
                }
                row[j - fi] = s * diagonal_inverse[j].transpose();
            }
            let mut d = row[i - fi];
            for k in fi..i {
                d -= row[k - fi] * row[k - fi].transpose();
            }
            let d = (d + d.transpose()) * 0.5;
            let l = d.cholesky()?.l();
            let l_inv = l.try_inverse()?;
            if l_inv.iter().any(|v| !v.is_finite()) {
                return None;
            }
            row[i - fi] = l;
            rows.push(row);
            diagonal_inverse.push(l_inv);
        }
        Some(EnvelopeCholesky { factor: Self { first: self.first.clone(), rows }, diagonal_inverse })
    }
}

/// The Cholesky factor of a [`BlockEnvelope`] (see the module doc).
#[derive(Clone, Debug)]
pub struct EnvelopeCholesky {
    /// L on the envelope.
    factor: BlockEnvelope,
    /// L_ii⁻¹ per block row.
    diagonal_inverse: Vec<Matrix6<f64>>,
}

impl EnvelopeCholesky {
    /// x with A x = b (b of length 6n, block i at 6i…6i+5).
    ///
    /// # Panics
    /// `b` of another length.
    pub fn solve(&self, b: &[f64]) -> Vec<f64> {
        let n = self.factor.len();
        assert_eq!(b.len(), 6 * n, "right-hand side of the wrong length");
        let block = |v: &[f64], i: usize| nalgebra::Vector6::from_column_slice(&v[6 * i..6 * i + 6]);
        // L y = b, row by row
        let mut y: Vec<nalgebra::Vector6<f64>> = Vec::with_capacity(n);
        for i in 0..n {
            let fi = self.factor.first[i];
            let mut s = block(b, i);
            for k in fi..i {
                s -= self.factor.rows[i][k - fi] * y[k];
            }
            y.push(self.diagonal_inverse[i] * s);
        }
        // Lᵀ x = y, from the last row, scattering each solved block into the rows above
        let mut x = vec![0.0; 6 * n];
        for i in (0..n).rev() {
            let fi = self.factor.first[i];
            let xi = self.diagonal_inverse[i].transpose() * y[i];
            for k in fi..i {
                y[k] -= self.factor.rows[i][k - fi].transpose() * xi;
            }
            x[6 * i..6 * i + 6].copy_from_slice(xi.as_slice());
        }
        x
    }

    /// The selected inverse: A⁻¹ on the envelope (see the module doc).
    pub fn selected_inverse(&self) -> BlockEnvelope {
        let l = &self.factor;
        let n = l.len();
        let mut below: Vec<Vec<usize>> = vec![Vec::new(); n];
        for k in 0..n {
            for j in l.first[k]..k {
                below[j].push(k);
            }
        }
        let mut z = BlockEnvelope::zeros(&l.first);
        for j in (0..n).rev() {
            let lt_inv = self.diagonal_inverse[j].transpose();
            let column = &below[j];
            // Z_kj for k ∈ C(j) (stored as Z_kj = Z_jkᵀ in row k)
            let mut zkj: Vec<Matrix6<f64>> = Vec::with_capacity(column.len());
            for &i in column {
                let mut s = Matrix6::zeros();
                for &k in column {
                    s += l.block(k, j).transpose() * z.symmetric_block(k, i);
                }
                // Z_ji = −L_jj⁻ᵀ s; row i (> j) stores Z_ij = Z_jiᵀ
                zkj.push(-(lt_inv * s).transpose());
            }
            for (&i, zij) in column.iter().zip(&zkj) {
                *z.block_mut(i, j) = *zij;
            }
            let mut s = self.diagonal_inverse[j];
            for (&k, zk) in column.iter().zip(&zkj) {
                s -= l.block(k, j).transpose() * zk;
            }
            let d = lt_inv * s;
            *z.block_mut(j, j) = (d + d.transpose()) * 0.5;
        }
        z
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::DMatrix;

    use super::*;
    use crate::testing::SplitMix64;

    /// A random SPD matrix with envelope `first`: B Bᵀ restricted to the envelope would fill
    /// it, so build A = Σ (sparse rank-6 terms inside the envelope) + n·I.
    fn random_spd(first: &[usize], rng: &mut SplitMix64) -> (BlockEnvelope, DMatrix<f64>) {
        let n = first.len();
        let mut dense = DMatrix::<f64>::zeros(6 * n, 6 * n);
        for i in 0..n {
            for j in first[i]..=i {
                let b = Matrix6::from_fn(|_, _| rng.uniform_in(-1.0, 1.0));
                let block = if i == j { b * b.transpose() + Matrix6::identity() * (6.0 * n as f64) } else { b };
                dense.view_mut((6 * i, 6 * j), (6, 6)).copy_from(&block);
                if i != j {
                    dense.view_mut((6 * j, 6 * i), (6, 6)).copy_from(&block.transpose());
                }
            }
        }
        let mut env = BlockEnvelope::zeros(first);
        for i in 0..n {
            for j in first[i]..=i {
                *env.block_mut(i, j) = dense.fixed_view::<6, 6>(6 * i, 6 * j).into_owned();
            }
        }
        (env, dense)
    }

    /// A banded envelope with a revisit (row 9 reaches back to 1) and a last row that
    /// couples to everything.
    fn pattern() -> Vec<usize> {
        vec![0, 0, 0, 1, 2, 3, 3, 5, 6, 1, 8, 0]
    }

    #[test]
    fn solve_matches_the_dense_cholesky() {
        let mut rng = SplitMix64::new(3);
        let (env, dense) = random_spd(&pattern(), &mut rng);
        let b: Vec<f64> = (0..dense.nrows()).map(|_| rng.uniform_in(-2.0, 2.0)).collect();
        let x = env.cholesky().expect("SPD").solve(&b);
        let reference = dense.clone().cholesky().expect("SPD").solve(&nalgebra::DVector::from_vec(b));
        let err = x.iter().zip(reference.iter()).map(|(a, r)| (a - r).abs()).fold(0.0, f64::max);
        assert!(err < 1e-12 * reference.amax().max(1.0), "{err}");
    }

    #[test]
    fn selected_inverse_matches_the_dense_inverse_on_the_envelope() {
        let mut rng = SplitMix64::new(5);
        let first = pattern();
        let (env, dense) = random_spd(&first, &mut rng);
        let z = env.cholesky().expect("SPD").selected_inverse();
        let inverse = dense.try_inverse().expect("invertible");
        for i in 0..first.len() {
            for j in first[i]..=i {
                let want = inverse.fixed_view::<6, 6>(6 * i, 6 * j).into_owned();
                let err = (z.block(i, j) - want).amax();
                assert!(err < 1e-12 * inverse.amax(), "block ({i}, {j}): {err}");
            }
        }
    }

    #[test]
    fn an_indefinite_matrix_has_no_factor() {
        let mut env = BlockEnvelope::zeros(&[0, 0]);
        *env.block_mut(0, 0) = Matrix6::identity();
        *env.block_mut(1, 1) = Matrix6::identity();
        *env.block_mut(1, 0) = Matrix6::identity() * 2.0;
        assert!(env.cholesky().is_none());
    }
}
