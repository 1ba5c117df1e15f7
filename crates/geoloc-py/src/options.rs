//! The user-facing options of a map build and of a localizer, between Python dicts and the
//! core's [`BuildOptions`] / [`LocalizerOptions`]. Every default is the core's `Default`:
//! a dict holds only what the caller set, and `build_defaults()` / `localizer_defaults()`
//! report the core's values so that Python, its CLI and `geoloc-rs` can show them.

use geoloc_core::localizer::{LocalizerOptions, Locator};
use geoloc_core::map::{BuildOptions, RetrievalMethod};
use geoloc_core::selfcal::IntrinsicsModel;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{count_usize, u64_arg};
use crate::errors::{invalid, to_py_err};

/// The build option names, in the order `build_defaults()` lists them.
const BUILD_KEYS: [&str; 9] = [
    "retrieval",
    "branching",
    "depth",
    "seed",
    "estimate_noise",
    "model",
    "refine_intrinsics",
    "intrinsics_model",
    "adjust_labels",
];

/// The localizer option names, in the order `localizer_defaults()` lists them.
const LOCALIZER_KEYS: [&str; 6] = ["pixel_sigma", "max_residual", "gate_sigma", "history", "locator", "top_k"];

fn flag(name: &str, value: &Bound<'_, PyAny>) -> PyResult<bool> {
    value.extract::<bool>().map_err(|_| invalid(name, "expected True or False"))
}

fn real(name: &str, value: &Bound<'_, PyAny>) -> PyResult<f64> {
    value.extract::<f64>().map_err(|_| invalid(name, "expected a real number"))
}

fn text(name: &str, value: &Bound<'_, PyAny>) -> PyResult<String> {
    value.extract::<String>().map_err(|_| invalid(name, "expected a string"))
}

/// The (key, value) pairs of `given` (keys must be strings; the callers refuse unknown ones).
fn given_items<'py>(given: Option<&Bound<'py, PyDict>>) -> PyResult<Vec<(String, Bound<'py, PyAny>)>> {
    let Some(given) = given else { return Ok(Vec::new()) };
    given.iter().map(|(key, value)| Ok((text("options", &key)?, value))).collect()
}

/// The error for a key that is none of `known`.
fn unknown(name: &str, known: &[&str]) -> PyErr {
    invalid(name, format!("not an option; expected one of {}", known.join(", ")))
}

/// The core's defaults with the options in `given` applied (each checked, errors naming it).
pub fn build_options(given: Option<&Bound<'_, PyDict>>) -> PyResult<BuildOptions> {
    let mut o = BuildOptions::default();
    for (key, value) in given_items(given)? {
        let name = key.as_str();
        match name {
            "retrieval" => o.retrieval = text(name, &value)?.parse::<RetrievalMethod>().map_err(to_py_err)?,
            "branching" => o.branching = count_usize(name, &value)?,
            "depth" => o.depth = count_usize(name, &value)?,
            "seed" => o.seed = u64_arg(Some(&value), name, 0)?,
            "estimate_noise" => o.estimate_noise = flag(name, &value)?,
            "model" => o.model = flag(name, &value)?,
            "refine_intrinsics" => o.refine_intrinsics = flag(name, &value)?,
            "intrinsics_model" => {
                o.intrinsics_model = text(name, &value)?.parse::<IntrinsicsModel>().map_err(to_py_err)?
            }
            "adjust_labels" => o.adjust_labels = flag(name, &value)?,
            _ => return Err(unknown(name, &BUILD_KEYS)),
        }
    }
    Ok(o)
}

/// The core's localizer defaults with the options in `given` applied (the solvers check the
/// values when the localizer is created).
pub fn localizer_options(given: Option<&Bound<'_, PyDict>>) -> PyResult<LocalizerOptions> {
    let mut o = LocalizerOptions::default();
    for (key, value) in given_items(given)? {
        let name = key.as_str();
        match name {
            "pixel_sigma" => o = o.with_pixel_noise(real(name, &value)?, o.max_residual_px()),
            "max_residual" => o = o.with_pixel_noise(o.pixel_sigma(), real(name, &value)?),
            "gate_sigma" => o.gate_sigma = real(name, &value)?,
            "history" => o.history = count_usize(name, &value)?,
            "locator" => o.locator = text(name, &value)?.parse::<Locator>().map_err(to_py_err)?,
            "top_k" => o.top_k = count_usize(name, &value)?,
            _ => return Err(unknown(name, &LOCALIZER_KEYS)),
        }
    }
    Ok(o)
}

/// `options` as the dict of its user-facing values (the keys [`build_options`] reads).
pub fn build_dict<'py>(py: Python<'py>, o: &BuildOptions) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("retrieval", o.retrieval.as_str())?;
    d.set_item("branching", o.branching)?;
    d.set_item("depth", o.depth)?;
    d.set_item("seed", o.seed)?;
    d.set_item("estimate_noise", o.estimate_noise)?;
    d.set_item("model", o.model)?;
    d.set_item("refine_intrinsics", o.refine_intrinsics)?;
    d.set_item("intrinsics_model", o.intrinsics_model.as_str())?;
    d.set_item("adjust_labels", o.adjust_labels)?;
    Ok(d)
}

/// `options` as the dict of its user-facing values (the keys [`localizer_options`] reads).
pub fn localizer_dict<'py>(py: Python<'py>, o: &LocalizerOptions) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("pixel_sigma", o.pixel_sigma())?;
    d.set_item("max_residual", o.max_residual_px())?;
    d.set_item("gate_sigma", o.gate_sigma)?;
    d.set_item("history", o.history)?;
    d.set_item("locator", o.locator.as_str())?;
    d.set_item("top_k", o.top_k)?;
    Ok(d)
}

/// The core's default map-build options, as a dict.
#[pyfunction]
fn build_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    build_dict(py, &BuildOptions::default())
}

/// The core's default localizer options, as a dict.
#[pyfunction]
fn localizer_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    localizer_dict(py, &LocalizerOptions::default())
}

/// Registers the functions on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(build_defaults, m)?)?;
    m.add_function(wrap_pyfunction!(localizer_defaults, m)?)
}
