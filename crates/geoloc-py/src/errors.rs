//! The one mapping from [`GeolocError`] onto the Python exception hierarchy of
//! `geoloc.exceptions` (every class there also derives from the builtin it refines, e.g.
//! `InvalidInputError(GeolocError, ValueError)`).

use geoloc_core::GeolocError;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyType;

/// The name of the `geoloc.exceptions` class that `err` is raised as.
fn exception_class_name(err: &GeolocError) -> &'static str {
    match err {
        GeolocError::InvalidInput { .. } | GeolocError::NonFinite { .. } => "InvalidInputError",
        GeolocError::NotARotation { .. } => "NotARotationError",
        GeolocError::Format { .. } => "FileFormatError",
        GeolocError::Io { .. } => "FileAccessError",
        _ => "GeolocError",
    }
}

/// Converts a core error into the matching `geoloc.exceptions` exception.
///
/// Falls back to `ValueError`/`RuntimeError` if `geoloc.exceptions` cannot be imported (only
/// when `geoloc._core` is used without its package).
pub fn to_py_err(err: GeolocError) -> PyErr {
    let message = err.to_string();
    let class_name = exception_class_name(&err);
    Python::attach(|py| {
        let class = py
            .import("geoloc.exceptions")
            .and_then(|module| module.getattr(class_name))
            .and_then(|class| class.cast_into::<PyType>().map_err(PyErr::from));
        match class {
            Ok(class) => PyErr::from_type(class, message),
            Err(_) if class_name == "GeolocError" => PyRuntimeError::new_err(message),
            Err(_) => PyValueError::new_err(message),
        }
    })
}

/// `ValueError` naming the argument, for shape and layout problems found while borrowing.
pub fn invalid(name: &str, reason: impl std::fmt::Display) -> PyErr {
    to_py_err(GeolocError::invalid(name, reason.to_string()))
}
