//! The user-facing options of a map build and of a localizer, between Python dicts and the
//! core's [`BuildOptions`] / [`LocalizerOptions`]. Every default is the core's `Default`:
//! a dict holds only what the caller set, and `build_defaults()` / `localizer_defaults()`
//! report the core's values so that Python, its CLI and `geoloc-rs` can show them.

use geoloc_core::localizer::{LocalizerOptions, Locator};
use geoloc_core::map::{BuildOptions, RetrievalMethod};
use geoloc_core::selfcal::IntrinsicsModel;
use pyo3::IntoPyObjectExt;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{count_usize, u64_arg};
use crate::errors::{invalid, to_py_err};

/// One user-facing option of `T`: its name (written once, here), how to read it from a
/// Python value (checked, errors naming it) and how to report it.
struct OptionField<T> {
    name: &'static str,
    set: fn(&mut T, &str, &Bound<'_, PyAny>) -> PyResult<()>,
    get: for<'py> fn(Python<'py>, &T) -> PyResult<Bound<'py, PyAny>>,
}

/// The map-build options, in the order `build_defaults()` lists them.
const BUILD: [OptionField<BuildOptions>; 9] = [
    OptionField {
        name: "retrieval",
        set: |o, n, v| text(n, v)?.parse::<RetrievalMethod>().map_err(to_py_err).map(|x| o.retrieval = x),
        get: |py, o| o.retrieval.as_str().into_bound_py_any(py),
    },
    OptionField {
        name: "branching",
        set: |o, n, v| count_usize(n, v).map(|x| o.branching = x),
        get: |py, o| o.branching.into_bound_py_any(py),
    },
    OptionField {
        name: "depth",
        set: |o, n, v| count_usize(n, v).map(|x| o.depth = x),
        get: |py, o| o.depth.into_bound_py_any(py),
    },
    OptionField {
        name: "seed",
        set: |o, n, v| u64_arg(Some(v), n, 0).map(|x| o.seed = x),
        get: |py, o| o.seed.into_bound_py_any(py),
    },
    OptionField {
        name: "estimate_noise",
        set: |o, n, v| flag(n, v).map(|x| o.estimate_noise = x),
        get: |py, o| o.estimate_noise.into_bound_py_any(py),
    },
    OptionField {
        name: "model",
        set: |o, n, v| flag(n, v).map(|x| o.model = x),
        get: |py, o| o.model.into_bound_py_any(py),
    },
    OptionField {
        name: "refine_intrinsics",
        set: |o, n, v| flag(n, v).map(|x| o.refine_intrinsics = x),
        get: |py, o| o.refine_intrinsics.into_bound_py_any(py),
    },
    OptionField {
        name: "intrinsics_model",
        set: |o, n, v| text(n, v)?.parse::<IntrinsicsModel>().map_err(to_py_err).map(|x| o.intrinsics_model = x),
        get: |py, o| o.intrinsics_model.as_str().into_bound_py_any(py),
    },
    OptionField {
        name: "adjust_labels",
        set: |o, n, v| flag(n, v).map(|x| o.adjust_labels = x),
        get: |py, o| o.adjust_labels.into_bound_py_any(py),
    },
];

/// The localizer options, in the order `localizer_defaults()` lists them (the solvers check
/// the values when the localizer is created).
const LOCALIZER: [OptionField<LocalizerOptions>; 6] = [
    OptionField {
        name: "pixel_sigma",
        set: |o, n, v| real(n, v).map(|x| *o = o.with_pixel_noise(x, o.max_residual_px())),
        get: |py, o| o.pixel_sigma().into_bound_py_any(py),
    },
    OptionField {
        name: "max_residual",
        set: |o, n, v| real(n, v).map(|x| *o = o.with_pixel_noise(o.pixel_sigma(), x)),
        get: |py, o| o.max_residual_px().into_bound_py_any(py),
    },
    OptionField {
        name: "gate_sigma",
        set: |o, n, v| real(n, v).map(|x| o.gate_sigma = x),
        get: |py, o| o.gate_sigma.into_bound_py_any(py),
    },
    OptionField {
        name: "history",
        set: |o, n, v| count_usize(n, v).map(|x| o.history = x),
        get: |py, o| o.history.into_bound_py_any(py),
    },
    OptionField {
        name: "locator",
        set: |o, n, v| text(n, v)?.parse::<Locator>().map_err(to_py_err).map(|x| o.locator = x),
        get: |py, o| o.locator.as_str().into_bound_py_any(py),
    },
    OptionField {
        name: "top_k",
        set: |o, n, v| count_usize(n, v).map(|x| o.top_k = x),
        get: |py, o| o.top_k.into_bound_py_any(py),
    },
];

fn flag(name: &str, value: &Bound<'_, PyAny>) -> PyResult<bool> {
    value.extract::<bool>().map_err(|_| invalid(name, "expected True or False"))
}

fn real(name: &str, value: &Bound<'_, PyAny>) -> PyResult<f64> {
    if value.is_instance_of::<pyo3::types::PyBool>() {
        return Err(invalid(name, "expected a real number, got a bool"));
    }
    value.extract::<f64>().map_err(|_| invalid(name, "expected a real number"))
}

fn text(name: &str, value: &Bound<'_, PyAny>) -> PyResult<String> {
    value.extract::<String>().map_err(|_| invalid(name, "expected a string"))
}

/// `T`'s defaults with the options in `given` applied (keys must be strings naming one of
/// `fields`; each value checked, errors naming it).
fn apply<T: Default>(fields: &[OptionField<T>], given: Option<&Bound<'_, PyDict>>) -> PyResult<T> {
    let mut o = T::default();
    let Some(given) = given else { return Ok(o) };
    for (key, value) in given.iter() {
        let name = text("options", &key)?;
        let field = fields.iter().find(|f| f.name == name).ok_or_else(|| {
            let known: Vec<&str> = fields.iter().map(|f| f.name).collect();
            invalid(&name, format!("not an option; expected one of {}", known.join(", ")))
        })?;
        (field.set)(&mut o, &name, &value)?;
    }
    Ok(o)
}

/// `o` as the dict of its user-facing values, in the order of `fields`.
fn to_dict<'py, T>(py: Python<'py>, fields: &[OptionField<T>], o: &T) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for f in fields {
        d.set_item(f.name, (f.get)(py, o)?)?;
    }
    Ok(d)
}

/// The core's defaults with the build options in `given` applied.
pub fn build_options(given: Option<&Bound<'_, PyDict>>) -> PyResult<BuildOptions> {
    apply(&BUILD, given)
}

/// The core's localizer defaults with the options in `given` applied.
pub fn localizer_options(given: Option<&Bound<'_, PyDict>>) -> PyResult<LocalizerOptions> {
    apply(&LOCALIZER, given)
}

/// `options` as the dict of its user-facing values (the keys [`build_options`] reads).
pub fn build_dict<'py>(py: Python<'py>, o: &BuildOptions) -> PyResult<Bound<'py, PyDict>> {
    to_dict(py, &BUILD, o)
}

/// `options` as the dict of its user-facing values (the keys [`localizer_options`] reads).
pub fn localizer_dict<'py>(py: Python<'py>, o: &LocalizerOptions) -> PyResult<Bound<'py, PyDict>> {
    to_dict(py, &LOCALIZER, o)
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
