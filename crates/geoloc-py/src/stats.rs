//! Bindings of `geoloc_core::stats::chi2`: the constants and the quantile function, so the
//! Python evaluation uses the core's χ² and never a copy of it.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use pyo3::prelude::*;

use crate::errors::invalid;

/// The p-quantile of χ² with `dof` degrees of freedom for each p in [0, 1) (N,) → (N,).
#[pyfunction]
pub fn chi2_quantile<'py>(
    py: Python<'py>,
    p: PyReadonlyArray1<'py, f64>,
    dof: usize,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let p = p.as_slice()?;
    if dof == 0 {
        return Err(invalid("dof", "must be ≥ 1"));
    }
    if let Some(i) = p.iter().position(|v| !(0.0..1.0).contains(v)) {
        return Err(invalid("p", format!("entry {i} is not a probability in [0, 1)")));
    }
    let q: Vec<f64> = py.detach(|| p.iter().map(|&v| geoloc_core::stats::chi2::quantile(dof, v)).collect());
    Ok(q.into_pyarray(py))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("CHI2_6_95", geoloc_core::stats::chi2::CHI2_6_95)?;
    m.add("CHI2_6_999", geoloc_core::stats::chi2::CHI2_6_999)?;
    m.add_function(wrap_pyfunction!(chi2_quantile, m)?)?;
    Ok(())
}
