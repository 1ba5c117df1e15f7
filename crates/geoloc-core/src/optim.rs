//! Small nonlinear least-squares machinery: robust kernels for IRLS and one generic
//! Levenberg–Marquardt that reports instead of failing.

pub mod lm;
pub mod robust;

pub use lm::{LeastSquares, LmOptions, LmReport, Termination, levenberg_marquardt};
pub use robust::RobustLoss;
