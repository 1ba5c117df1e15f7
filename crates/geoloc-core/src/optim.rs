//! Small nonlinear least-squares machinery: robust kernels for IRLS and one generic
//! Levenberg–Marquardt that reports instead of failing.

pub mod lm;
pub mod robust;

pub use lm::{
    LeastSquares, LmOptions, LmReport, Termination, levenberg_marquardt, levenberg_marquardt_with_information,
};
pub use robust::RobustLoss;
