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
pub fn relative_error<const R: usize, const C: usize>(a: &SMatrix<f64, R, C>, b: &SMatrix<f64, R, C>) -> f64 {
    (a - b).abs().max() / b.abs().max().max(1.0)
}

use geoloc_core::camera::{Camera, project};
use geoloc_core::lie::SE3;
use geoloc_core::stats::chi2::CHI2_6_95;
use geoloc_core::testing::SplitMix64;
use nalgebra::{Matrix6, Vector2, Vector3, Vector6};

pub use geoloc_core::testing::look_at;

/// `n_cams` cameras on a 1 m arc around the origin looking at a cloud of `n_points` points
/// 4–6 m away; returns (camera, poses, points).
pub fn arc_scene(rng: &mut SplitMix64, n_cams: usize, n_points: usize) -> (Camera, Vec<SE3>, Vec<Vector3<f64>>) {
    let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid intrinsics");
    let target = Vector3::new(0.0, 0.0, 5.0);
    let poses = (0..n_cams)
        .map(|i| {
            let a = (i as f64 / (n_cams.max(2) - 1) as f64 - 0.5) * 0.4;
            let c = Vector3::new(a * 2.5, rng.uniform_in(-0.1, 0.1), rng.uniform_in(-0.1, 0.1));
            look_at(&c, &target)
        })
        .collect();
    let points = (0..n_points)
        .map(|_| Vector3::new(rng.uniform_in(-1.5, 1.5), rng.uniform_in(-1.0, 1.0), rng.uniform_in(4.0, 6.0)))
        .collect();
    (camera, poses, points)
}

/// Pixel of `x` in `pose`, plus isotropic Gaussian noise of `sigma` px.
pub fn observe(rng: &mut SplitMix64, camera: &Camera, pose: &SE3, x: &Vector3<f64>, sigma: f64) -> Vector2<f64> {
    project(camera, pose, x).uv + Vector2::new(rng.normal(), rng.normal()) * sigma
}

/// One Monte-Carlo trial's pose: the truth, the estimate (world_from_cam) and its 6×6
/// covariance (right perturbation, translation first).
pub struct Sample {
    pub truth: SE3,
    pub estimate: SE3,
    pub covariance: Matrix6<f64>,
}

impl Sample {
    /// The error e = log(T_true⁻¹ T_est)^∨ in the covariance's tangent space.
    pub fn error(&self) -> Vector6<f64> {
        (self.truth.inverse() * self.estimate).log()
    }
}

/// The Monte-Carlo harness of the pose-covariance tests: `trials` trials drawn from one
/// generator seeded `seed`, and how often the truth falls inside the 95 % regions of the
/// returned covariance — the 6-DoF NEES eᵀC⁻¹e ≤ χ²₆(0.95) and per axis |e_a| ≤ 1.96 √C_aa —
/// with the squared position errors ‖t_est − t_true‖² for the RMS.
#[derive(Debug, Default)]
pub struct Coverage {
    /// Trials that gave a pose (a trial returning None is not counted).
    pub trials: usize,
    pub nees_inside: usize,
    pub axis_inside: [usize; 6],
    pub sum_sq_position_m2: f64,
}

impl Coverage {
    pub fn run(seed: u64, trials: usize, mut trial: impl FnMut(&mut SplitMix64) -> Option<Sample>) -> Self {
        let mut rng = SplitMix64::new(seed);
        let mut out = Self::default();
        for _ in 0..trials {
            let Some(sample) = trial(&mut rng) else { continue };
            let (e, cov) = (sample.error(), sample.covariance);
            out.trials += 1;
            let c_inv = cov.try_inverse().expect("spd");
            out.nees_inside += usize::from((e.transpose() * c_inv * e)[0] <= CHI2_6_95);
            for i in 0..6 {
                out.axis_inside[i] += usize::from(e[i].abs() <= 1.96 * cov[(i, i)].sqrt());
            }
            out.sum_sq_position_m2 += (sample.estimate.translation - sample.truth.translation).norm_squared();
        }
        out
    }

    /// Share of trials with NEES ≤ χ²₆(0.95).
    pub fn nees(&self) -> f64 {
        self.nees_inside as f64 / self.trials as f64
    }

    /// Share of trials inside the 95 % interval, per axis.
    pub fn axes(&self) -> [f64; 6] {
        self.axis_inside.map(|a| a as f64 / self.trials as f64)
    }

    /// RMS position error (m).
    pub fn rms_position_m(&self) -> f64 {
        (self.sum_sq_position_m2 / self.trials as f64).sqrt()
    }
}
