//! Bindings of `geoloc_core::bow`: the vocabulary and the image database as Python classes.

use geoloc_core::bow::{BowDatabase as CoreDatabase, Vocabulary as CoreVocabulary};
use numpy::{IntoPyArray, PyArray1};
use pyo3::prelude::*;

use crate::convert::BorrowedDescriptors;
use crate::errors::to_py_err;

/// A hierarchical visual vocabulary; see `geoloc.retrieval.Vocabulary`.
#[pyclass(module = "geoloc._core", frozen)]
pub struct Vocabulary {
    inner: CoreVocabulary,
}

#[pymethods]
impl Vocabulary {
    #[staticmethod]
    fn train(
        py: Python<'_>,
        descriptors: &Bound<'_, PyAny>,
        branching: usize,
        depth: usize,
        seed: u64,
    ) -> PyResult<Self> {
        let d = BorrowedDescriptors::extract(descriptors, "descriptors")?;
        let view = d.view("descriptors")?;
        let inner = py.detach(|| CoreVocabulary::train(&view, branching, depth, seed)).map_err(to_py_err)?;
        Ok(Self { inner })
    }

    fn words<'py>(&self, py: Python<'py>, descriptors: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        let d = BorrowedDescriptors::extract(descriptors, "descriptors")?;
        let view = d.view("descriptors")?;
        let words = py.detach(|| self.inner.words_of(&view)).map_err(to_py_err)?;
        Ok(words.into_pyarray(py))
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

/// A TF-IDF image database; see `geoloc.retrieval.BowDatabase`.
#[pyclass(module = "geoloc._core", frozen)]
pub struct BowDatabase {
    inner: CoreDatabase,
}

#[pymethods]
impl BowDatabase {
    #[new]
    fn new(vocabulary_len: usize, images: Vec<Vec<u32>>) -> PyResult<Self> {
        Ok(Self { inner: CoreDatabase::new(vocabulary_len, &images).map_err(to_py_err)? })
    }

    /// [(image, score)] best first.
    fn query(&self, words: Vec<u32>, k: usize) -> Vec<(usize, f32)> {
        self.inner.query(&words, k)
    }
}

/// Registers the classes on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Vocabulary>()?;
    m.add_class::<BowDatabase>()
}
