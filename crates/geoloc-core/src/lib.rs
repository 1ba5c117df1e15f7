//! geoloc-core: the math of geoloc — image-based 6-DoF camera localization with calibrated
//! uncertainty — in pure Rust (no Python types anywhere).
//!
//! Conventions, held throughout the crate:
//! * a pose `T` is **world_from_cam** (camera-to-world), 4×4 homogeneous, f64;
//! * twists are ξ = (ρ, φ) ∈ R⁶, **translation first**, T = exp(ξ^);
//! * perturbations are on the **right**, T ⊞ δ = T·exp(δ^); pose covariances live there;
//! * metres and radians.

pub mod adjust;
pub mod bow;
pub mod camera;
pub mod checksum;
pub mod error;
pub mod essential;
pub mod files;
pub mod frames;
pub mod fusion;
pub mod keyframes;
pub mod lie;
pub mod localizer;
pub mod map;
pub mod matching;
pub mod motion;
pub mod optim;
pub mod parallel;
pub mod pnp;
pub mod retrieval;
pub mod rng;
pub mod selfcal;
pub mod stats;
pub mod testing;
pub mod triangulate;

pub use error::{GeolocError, Result};

/// The README's code blocks that rustdoc takes for Rust (none today), compiled and run by
/// `cargo test` so that one added there cannot rot.
#[doc = include_str!("../../../README.md")]
#[cfg(doctest)]
pub struct ReadmeDoctests;

/// The getting-started guide's Rust example, compiled and run by `cargo test` so it cannot rot.
#[doc = include_str!("../../../docs/getting-started.md")]
#[cfg(doctest)]
pub struct GettingStartedDoctests;
