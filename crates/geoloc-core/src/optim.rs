//! Small nonlinear least-squares machinery: robust kernels for IRLS, one generic
//! Levenberg–Marquardt / Gauss–Newton driver that reports instead of failing, and the
//! covariance helpers the solvers share.

pub mod covariance;
pub mod envelope;
pub mod lm;
pub mod robust;

pub use lm::{
    DampedStep, Evaluation, LeastSquares, Linearization, LmOptions, LmReport, Termination, levenberg_marquardt,
    levenberg_marquardt_with_information, solve,
};
pub use robust::RobustLoss;

use nalgebra::Matrix6;

use crate::lie::SE3;

/// A pose estimated by a least-squares solve, with its covariance and the solve's report;
/// `details` holds what the particular estimator adds (the motion model's velocity, the
/// fusion's source). The result type of [`crate::motion`] and [`crate::fusion`].
#[derive(Clone, Debug, PartialEq)]
pub struct PoseEstimate<X> {
    /// The estimate (world_from_cam).
    pub world_from_cam: SE3,
    /// 6×6 covariance in the right-perturbation tangent space, translation first.
    pub covariance: Matrix6<f64>,
    /// The last solve's report (None when no solve ran, e.g. a gated fusion).
    pub report: Option<LmReport>,
    /// Estimator-specific details.
    pub details: X,
}
