//! Bindings of `geoloc_core::retrieval`: the index as a Python class.

use geoloc_core::retrieval::{Backend, DescriptorIndex as CoreIndex};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::convert::count_arg;
use crate::errors::{invalid, to_py_err};

/// (distances (Q, k), indices (Q, k)).
type Neighbours<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<i64>>);

/// Exact k-NN index over (N, D) float32 descriptors; see `geoloc.retrieval`.
#[pyclass(module = "geoloc._core", frozen)]
pub struct DescriptorIndex {
    inner: CoreIndex,
}

/// The rows of a C-contiguous (N, D) float32 array and D.
fn rows_f32<'a>(name: &str, array: &'a PyReadonlyArray2<'_, f32>) -> PyResult<(&'a [f32], usize)> {
    let dim = array.shape()[1];
    let values = array.as_slice().map_err(|_| invalid(name, "array must be C-contiguous"))?;
    Ok((values, dim))
}

#[pymethods]
impl DescriptorIndex {
    #[new]
    #[pyo3(signature = (descriptors, *, backend=None))]
    fn new(py: Python<'_>, descriptors: PyReadonlyArray2<'_, f32>, backend: Option<&str>) -> PyResult<Self> {
        let (values, dim) = rows_f32("descriptors", &descriptors)?;
        let backend = backend.map(str::parse::<Backend>).transpose().map_err(to_py_err)?;
        let data = values.to_vec();
        let inner = py.detach(|| CoreIndex::with_backend(data, dim, backend)).map_err(to_py_err)?;
        Ok(Self { inner })
    }

    /// (distances, indices), each (Q, k).
    #[pyo3(signature = (queries, k=None))]
    fn query<'py>(
        &self,
        py: Python<'py>,
        queries: PyReadonlyArray2<'py, f32>,
        k: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Neighbours<'py>> {
        let k = count_arg(k, "k", 1)?;
        let (values, dim) = rows_f32("queries", &queries)?;
        if dim != self.inner.dim() {
            return Err(invalid("queries", format!("expected shape (Q, {}), got (…, {dim})", self.inner.dim())));
        }
        let q = queries.shape()[0];
        let (d, i) = py.detach(|| self.inner.query(values, k)).map_err(to_py_err)?;
        let d = Array2::from_shape_vec((q, k), d).map_err(|e| invalid("queries", e))?;
        let i = Array2::from_shape_vec((q, k), i.into_iter().map(|v| v as i64).collect())
            .map_err(|e| invalid("queries", e))?;
        Ok((d.into_pyarray(py), i.into_pyarray(py)))
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    /// D.
    #[getter]
    fn dim(&self) -> usize {
        self.inner.dim()
    }

    /// "kdtree" or "flat".
    #[getter]
    fn backend(&self) -> &'static str {
        self.inner.backend().as_str()
    }
}

/// Registers the class on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<DescriptorIndex>()
}
