//! Bindings of `geoloc_core::parallel`'s environment check, so that the Python front end names
//! a `GEOLOC_NUM_THREADS` the core ignores or caps, as `geoloc-rs` does.

use pyo3::prelude::*;

/// What is wrong with a `GEOLOC_NUM_THREADS` value (None: nothing, or unset/empty).
#[pyfunction]
#[pyo3(signature = (value))]
pub fn num_threads_warning(value: Option<&str>) -> Option<String> {
    geoloc_core::parallel::num_threads_warning(value)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("MAX_THREADS", geoloc_core::parallel::MAX_THREADS)?;
    m.add_function(wrap_pyfunction!(num_threads_warning, m)?)?;
    Ok(())
}
