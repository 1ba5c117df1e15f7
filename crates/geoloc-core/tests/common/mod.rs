//! Independent references for the Lie-group tests: central differences and a matrix
//! exponential by scaling-and-squaring of the Taylor series (no Lie closed forms).
#![allow(dead_code)]

use nalgebra::{SMatrix, SVector};

/// Step of the central differences (O(h²) truncation, O(ε/h) round-off ≈ 1e-10).
pub const FD_STEP: f64 = 1e-6;

/// Central-difference Jacobian of `f` at `x`: column i is (f(x + h eᵢ) − f(x − h eᵢ))/(2h).
pub fn central_difference<const N: usize, const M: usize>(
    f: impl Fn(&SVector<f64, N>) -> SVector<f64, M>,
    x: &SVector<f64, N>,
    h: f64,
) -> SMatrix<f64, M, N> {
    let mut j = SMatrix::<f64, M, N>::zeros();
    for i in 0..N {
        let mut xp = *x;
        let mut xm = *x;
        xp[i] += h;
        xm[i] -= h;
        j.set_column(i, &((f(&xp) - f(&xm)) / (2.0 * h)));
    }
    j
}

/// exp(A) = (exp(A/2ˢ))^(2ˢ) with a 20-term Taylor series for the scaled matrix.
pub fn matrix_exp<const N: usize>(a: &SMatrix<f64, N, N>) -> SMatrix<f64, N, N> {
    let norm = a.abs().row_sum().max();
    let squarings = if norm > 0.5 { (norm / 0.5).log2().ceil() as i32 } else { 0 };
    let scaled = a / 2f64.powi(squarings);
    let mut term = SMatrix::<f64, N, N>::identity();
    let mut sum = term;
    for k in 1..=20 {
        term = term * scaled / k as f64;
        sum += term;
    }
    for _ in 0..squarings {
        sum = sum * sum;
    }
    sum
}

/// max |a − b| / max(1, max |b|).
pub fn relative_error<const R: usize, const C: usize>(
    a: &SMatrix<f64, R, C>,
    b: &SMatrix<f64, R, C>,
) -> f64 {
    (a - b).abs().max() / b.abs().max().max(1.0)
}
