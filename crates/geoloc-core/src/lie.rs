//! Lie groups SO(3) and SE(3): exponential and logarithm maps, Jacobians, adjoints,
//! distances and interpolation.
//!
//! Conventions: poses are world_from_cam; twists are ξ = (ρ, φ),
//! translation first, T = exp(ξ^); perturbations are on the right, T ⊞ δ = T exp(δ^);
//! Jacobians and the Q block follow Barfoot, *State Estimation for Robotics* (2017).

pub mod se3;
mod series;
pub mod so3;

pub use se3::check_twist;
pub use se3::{SE3, Twist};
pub use series::TAYLOR_THRESHOLD_RAD;
pub use so3::{
    MAX_ROTATION_VECTOR_NORM, NEAR_ROTATION_TOLERANCE, ROTATION_TOLERANCE, SO3, check_rotation_vector, rotation_angle,
    try_rotation_angle,
};
