//! Bindings of `geoloc_core::bow`: the vocabulary and the image database as Python classes.

use geoloc_core::bow::{BowDatabase as CoreDatabase, Vocabulary as CoreVocabulary};
use numpy::{IntoPyArray, PyArray1};
use pyo3::prelude::*;

use crate::convert::{BorrowedDescriptors, count_arg, u64_arg};
use crate::errors::to_py_err;

/// (scores (k,) float32, image indices (k,) int64).
type Ranked<'py> = (Bound<'py, PyArray1<f32>>, Bound<'py, PyArray1<i64>>);

/// A hierarchical visual vocabulary; see `geoloc.retrieval.Vocabulary`.
#[pyclass(module = "geoloc._core", frozen)]
pub struct Vocabulary {
    inner: CoreVocabulary,
}

impl Vocabulary {
    /// The word of each row of a descriptor array, without the GIL.
    fn words_of(&self, py: Python<'_>, descriptors: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<u32>> {
        let d = BorrowedDescriptors::extract(descriptors, name)?;
        let view = d.view(name)?;
        py.detach(|| self.inner.words_of(&view)).map_err(to_py_err)
    }
}

#[pymethods]
impl Vocabulary {
    #[staticmethod]
    #[pyo3(signature = (descriptors, *, branching=None, depth=None, seed=None))]
    fn train(
        py: Python<'_>,
        descriptors: &Bound<'_, PyAny>,
        branching: Option<&Bound<'_, PyAny>>,
        depth: Option<&Bound<'_, PyAny>>,
        seed: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let (branching, depth) = (count_arg(branching, "branching", 10)?, count_arg(depth, "depth", 3)?);
        let seed = u64_arg(seed, "seed", 0)?;
        let d = BorrowedDescriptors::extract(descriptors, "descriptors")?;
        let view = d.view("descriptors")?;
        let inner = py.detach(|| CoreVocabulary::train(&view, branching, depth, seed)).map_err(to_py_err)?;
        Ok(Self { inner })
    }

    fn words<'py>(&self, py: Python<'py>, descriptors: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyArray1<u32>>> {
        Ok(self.words_of(py, descriptors, "descriptors")?.into_pyarray(py))
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

/// A TF-IDF image database over a vocabulary; see `geoloc.retrieval.BowDatabase`.
#[pyclass(module = "geoloc._core", frozen)]
pub struct BowDatabase {
    vocabulary: Py<Vocabulary>,
    inner: CoreDatabase,
}

#[pymethods]
impl BowDatabase {
    #[new]
    fn new(py: Python<'_>, vocabulary: Bound<'_, Vocabulary>, images: Vec<Bound<'_, PyAny>>) -> PyResult<Self> {
        let words: Vec<Vec<u32>> = images
            .iter()
            .enumerate()
            .map(|(i, d)| vocabulary.get().words_of(py, d, &format!("images[{i}]")))
            .collect::<PyResult<_>>()?;
        let v = &vocabulary.get().inner;
        let inner = CoreDatabase::with_weighting(v.len(), &words, v.term_weighting()).map_err(to_py_err)?;
        Ok(Self { vocabulary: vocabulary.unbind(), inner })
    }

    /// (scores in [0, 1], image indices) of the `k` best images, best first.
    #[pyo3(signature = (descriptors, k=None))]
    fn query<'py>(
        &self,
        py: Python<'py>,
        descriptors: &Bound<'py, PyAny>,
        k: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Ranked<'py>> {
        let k = count_arg(k, "k", 1)?;
        if k == 0 {
            return Err(crate::errors::invalid("k", "must be ≥ 1"));
        }
        let words = self.vocabulary.get().words_of(py, descriptors, "descriptors")?;
        let ranked = py.detach(|| self.inner.query(&words, k));
        let scores: Vec<f32> = ranked.iter().map(|r| r.1).collect();
        let ids: Vec<i64> = ranked.iter().map(|r| r.0 as i64).collect();
        Ok((scores.into_pyarray(py), ids.into_pyarray(py)))
    }

    /// The vocabulary.
    #[getter]
    fn vocabulary(&self, py: Python<'_>) -> Py<Vocabulary> {
        self.vocabulary.clone_ref(py)
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

/// Registers the classes on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Vocabulary>()?;
    m.add_class::<BowDatabase>()
}
