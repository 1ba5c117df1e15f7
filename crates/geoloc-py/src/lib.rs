//! `geoloc._core`: the compiled half of the `geoloc` Python package.
//!
//! This crate holds no math: each function validates and borrows its numpy inputs, calls
//! geoloc-core without the GIL, and converts the outputs.

mod adjust;
mod bow;
mod convert;
mod errors;
mod frames;
mod geometry;
mod lie;
mod localizer;
mod matching;
mod options;
mod parallel;
mod retrieval;
mod stats;
mod temporal;

use pyo3::prelude::*;

/// The compiled extension module.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("PARALLEL_MIN_ITEMS", geoloc_core::parallel::PARALLEL_MIN_ITEMS)?;
    m.add("MIN_NOISE_SAMPLES", geoloc_core::localizer::MIN_NOISE_SAMPLES)?;
    lie::register(m)?;
    adjust::register(m)?;
    geometry::register(m)?;
    temporal::register(m)?;
    retrieval::register(m)?;
    matching::register(m)?;
    bow::register(m)?;
    localizer::register(m)?;
    frames::register(m)?;
    options::register(m)?;
    parallel::register(m)?;
    stats::register(m)?;
    Ok(())
}
