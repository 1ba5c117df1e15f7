//! Borrowing numpy arrays as flat row-major slices and filling new ones, with the checks
//! that make every binding raise a named error instead of panicking.

use geoloc_core::GeolocError;
use geoloc_core::parallel::try_fill_items;
use nalgebra::{SMatrix, SVector};
use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::{invalid, to_py_err};

/// The rows of an (N, WIDTH) float64 array as one C-contiguous slice, after checking the
/// width, the layout and that every value is finite.
pub fn rows<'a, const WIDTH: usize>(name: &str, array: &'a PyReadonlyArray2<'_, f64>) -> PyResult<&'a [f64]> {
    let shape = array.shape();
    if shape[1] != WIDTH {
        return Err(invalid(name, format!("expected shape (N, {WIDTH}), got {shape:?}")));
    }
    let values =
        array.as_slice().map_err(|_| invalid(name, "array must be C-contiguous (use numpy.ascontiguousarray)"))?;
    if let Some(flat) = values.iter().position(|v| !v.is_finite()) {
        return Err(to_py_err(GeolocError::NonFinite { name: name.into(), index: flat / WIDTH }));
    }
    Ok(values)
}

/// Row `i` of a flat row-major slice as a fixed-size array.
#[inline]
pub fn row<const WIDTH: usize>(values: &[f64], i: usize) -> &[f64; WIDTH] {
    values[i * WIDTH..(i + 1) * WIDTH].try_into().expect("invariant: callers index rows of a slice checked by `rows`")
}

/// A row-major R×C matrix from a row of R·C values.
#[inline]
pub fn matrix_from_row<const R: usize, const C: usize>(values: &[f64]) -> SMatrix<f64, R, C> {
    SMatrix::<f64, R, C>::from_row_slice(values)
}

/// A vector from a row of values.
#[inline]
pub fn vector_from_row<const N: usize>(values: &[f64; N]) -> SVector<f64, N> {
    SVector::<f64, N>::from_column_slice(values)
}

/// Writes an R×C matrix row-major into `out` (length R·C).
#[inline]
pub fn write_matrix<const R: usize, const C: usize>(m: &SMatrix<f64, R, C>, out: &mut [f64]) {
    for r in 0..R {
        for c in 0..C {
            out[r * C + c] = m[(r, c)];
        }
    }
}

/// A new (n, WIDTH) array whose row i is written by `fill(i, row)`, computed without the
/// GIL (in parallel for large n). A failing row's error names `name[i]`.
///
/// The array is allocated by numpy (which backs large arrays with huge pages, so the first
/// touch of a 25 MB result costs a few page faults instead of thousands) and filled in place.
pub fn fill_rows<'py, const WIDTH: usize, F>(py: Python<'py>, n: usize, fill: F) -> PyResult<Bound<'py, PyArray2<f64>>>
where
    F: Fn(usize, &mut [f64]) -> geoloc_core::Result<()> + Sync + Send,
{
    let array = PyArray2::<f64>::zeros(py, [n, WIDTH], false);
    {
        let mut guard = array.readwrite();
        let out = guard.as_slice_mut().map_err(|e| invalid("output", format!("internal layout error: {e}")))?;
        py.detach(|| try_fill_items(out, WIDTH, fill)).map_err(to_py_err)?;
    }
    Ok(array)
}

/// The common batch length of several (N, ·) arrays.
pub fn batch_len(names_and_lengths: &[(&str, usize)]) -> PyResult<usize> {
    let (first_name, n) = names_and_lengths[0];
    for &(name, len) in &names_and_lengths[1..] {
        if len != n {
            return Err(invalid(name, format!("has {len} items but {first_name} has {n}")));
        }
    }
    Ok(n)
}

/// Each row of an (N, R·C) array as an R×C matrix (rows of the array are row-major).
pub fn matrices<const R: usize, const C: usize, const W: usize>(
    name: &str,
    array: &PyReadonlyArray2<'_, f64>,
) -> PyResult<Vec<SMatrix<f64, R, C>>> {
    let values = rows::<W>(name, array)?;
    Ok(values.chunks_exact(W).map(matrix_from_row::<R, C>).collect())
}

/// Each row of an (N, 16) array as a rigid transform, strictly checked (errors name `name[i]`).
pub fn poses(name: &str, array: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<geoloc_core::lie::SE3>> {
    matrices::<4, 4, 16>(name, array)?
        .iter()
        .enumerate()
        .map(|(i, m)| geoloc_core::lie::SE3::from_matrix(m).map_err(|e| to_py_err(e.at(name, i))))
        .collect()
}

/// A 1-D integer array as indices (refusing negative values, naming the first).
pub fn indices(name: &str, array: &numpy::PyReadonlyArray1<'_, i64>) -> PyResult<Vec<usize>> {
    let values = array.as_slice().map_err(|_| invalid(name, "array must be contiguous"))?;
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| usize::try_from(v).map_err(|_| invalid(name, format!("{name}[{i}] = {v} is negative"))))
        .collect()
}

/// Matrices as an (N, R·C) array, each row-major.
pub fn matrices_to_array<'py, const R: usize, const C: usize>(
    py: Python<'py>,
    items: &[SMatrix<f64, R, C>],
) -> Bound<'py, PyArray2<f64>> {
    let mut flat = vec![0.0; items.len() * R * C];
    for (m, out) in items.iter().zip(flat.chunks_exact_mut(R * C)) {
        write_matrix(m, out);
    }
    let array = numpy::ndarray::Array2::from_shape_vec((items.len(), R * C), flat)
        .expect("invariant: the buffer has items × R·C values");
    numpy::IntoPyArray::into_pyarray(array, py)
}

/// Local descriptors borrowed from numpy: uint8 rows are binary (Hamming), float32 rows float.
pub enum BorrowedDescriptors<'py> {
    /// (N, W) uint8.
    Binary(numpy::PyReadonlyArray2<'py, u8>),
    /// (N, W) float32.
    Float(numpy::PyReadonlyArray2<'py, f32>),
}

impl<'py> BorrowedDescriptors<'py> {
    /// Borrows `obj` as either kind, or a `ValueError` naming `name`.
    pub fn extract(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Self> {
        if let Ok(a) = obj.extract::<numpy::PyReadonlyArray2<'py, u8>>() {
            return Ok(Self::Binary(a));
        }
        obj.extract::<numpy::PyReadonlyArray2<'py, f32>>()
            .map(Self::Float)
            .map_err(|_| invalid(name, "expected a 2-D uint8 (binary) or float32 array"))
    }

    /// The core view of the rows.
    pub fn view(&self, name: &str) -> PyResult<geoloc_core::matching::Descriptors<'_>> {
        use geoloc_core::matching::Descriptors;
        let contiguous = || invalid(name, "array must be C-contiguous");
        Ok(match self {
            Self::Binary(a) => {
                Descriptors::Binary { data: a.as_slice().map_err(|_| contiguous())?, width: a.shape()[1] }
            }
            Self::Float(a) => Descriptors::Float { data: a.as_slice().map_err(|_| contiguous())?, width: a.shape()[1] },
        })
    }

    /// An owned copy of the rows.
    pub fn to_owned_set(&self, name: &str) -> PyResult<geoloc_core::matching::DescriptorSet> {
        use geoloc_core::matching::{DescriptorSet, Descriptors};
        Ok(match self.view(name)? {
            Descriptors::Binary { data, width } => DescriptorSet::Binary { data: data.to_vec(), width },
            Descriptors::Float { data, width } => DescriptorSet::Float { data: data.to_vec(), width },
        })
    }
}

/// The integer argument `obj` unless absent or None; a bool is refused.
fn given_int<'a, 'py>(obj: Option<&'a Bound<'py, PyAny>>, name: &str) -> PyResult<Option<&'a Bound<'py, PyAny>>> {
    match obj.filter(|o| !o.is_none()) {
        Some(o) if o.is_instance_of::<pyo3::types::PyBool>() => Err(invalid(name, "expected an integer, got a bool")),
        given => Ok(given),
    }
}

/// An optional integer argument ([`count`]); `None` gives `default`; a bool is refused.
pub fn u64_arg(obj: Option<&Bound<'_, PyAny>>, name: &str, default: u64) -> PyResult<u64> {
    given_int(obj, name)?.map_or(Ok(default), |o| count(name, o))
}

/// [`u64_arg`] as a count (usize, [`count_usize`]).
pub fn count_arg(obj: Option<&Bound<'_, PyAny>>, name: &str, default: usize) -> PyResult<usize> {
    given_int(obj, name)?.map_or(Ok(default), |o| count_usize(name, o))
}

/// A Python integer (or anything with `__index__`, e.g. `np.int64`) as a non-negative
/// count; floats, negative values and values beyond `u64` raise `InvalidInputError` naming
/// `name` (never `OverflowError`).
pub fn count(name: &str, value: &Bound<'_, PyAny>) -> PyResult<u64> {
    if value.is_instance_of::<pyo3::types::PyBool>() {
        return Err(invalid(name, format!("expected a non-negative integer, got a bool ({})", describe(value))));
    }
    let index = value
        .call_method0("__index__")
        .map_err(|_| invalid(name, format!("expected a non-negative integer, got {}", describe(value))))?;
    if let Ok(v) = index.extract::<u64>() {
        return Ok(v);
    }
    let negative = index.lt(0).unwrap_or(false);
    Err(invalid(
        name,
        if negative {
            format!("expected a non-negative integer, got {index}")
        } else {
            format!("{index} is too large (at most {})", u64::MAX)
        },
    ))
}

/// [`count`] as a `usize`.
pub fn count_usize(name: &str, value: &Bound<'_, PyAny>) -> PyResult<usize> {
    let v = count(name, value)?;
    usize::try_from(v).map_err(|_| invalid(name, format!("{v} is too large")))
}

fn describe(value: &Bound<'_, PyAny>) -> String {
    value.repr().map_or_else(|_| "a non-integer".to_owned(), |r| r.to_string())
}

/// A fixed-size matrix as a new (R, C) numpy array.
pub fn matrix_to_array<'py, const R: usize, const C: usize>(
    py: Python<'py>,
    m: &SMatrix<f64, R, C>,
) -> Bound<'py, PyArray2<f64>> {
    numpy::IntoPyArray::into_pyarray(numpy::ndarray::Array2::from_shape_fn((R, C), |(r, c)| m[(r, c)]), py)
}

/// Matrices as a new (N, R, C) numpy array.
pub fn matrices_to_array3<'py, const R: usize, const C: usize>(
    py: Python<'py>,
    items: &[SMatrix<f64, R, C>],
) -> Bound<'py, numpy::PyArray3<f64>> {
    let array = numpy::ndarray::Array3::from_shape_fn((items.len(), R, C), |(i, r, c)| items[i][(r, c)]);
    numpy::IntoPyArray::into_pyarray(array, py)
}

/// One (4, 4) array as a rigid transform, strictly checked; errors name `name` (no index).
pub fn one_pose(name: &str, array: &PyReadonlyArray2<'_, f64>) -> PyResult<geoloc_core::lie::SE3> {
    if array.shape() != [4, 4] {
        return Err(invalid(name, format!("expected shape (4, 4), got {:?}", array.shape())));
    }
    let m = nalgebra::Matrix4::from_fn(|r, c| *array.get([r, c]).unwrap_or(&f64::NAN));
    geoloc_core::lie::SE3::from_matrix(&m).map_err(|e| to_py_err(e.named(name)))
}

/// One (D, D) array as a matrix; errors name `name` (finiteness is checked too).
pub fn one_matrix<const D: usize>(name: &str, array: &PyReadonlyArray2<'_, f64>) -> PyResult<SMatrix<f64, D, D>> {
    if array.shape() != [D, D] {
        return Err(invalid(name, format!("expected shape ({D}, {D}), got {:?}", array.shape())));
    }
    let m = SMatrix::<f64, D, D>::from_fn(|r, c| *array.get([r, c]).unwrap_or(&f64::NAN));
    if let Some(flat) = m.transpose().iter().position(|v| !v.is_finite()) {
        return Err(to_py_err(GeolocError::NonFinite { name: name.into(), index: flat }));
    }
    Ok(m)
}

/// The values of an optional 1-D array, which must be C-contiguous (`name` in the error).
pub fn contiguous<'a>(name: &str, array: Option<&'a numpy::PyReadonlyArray1<'_, f64>>) -> PyResult<Option<&'a [f64]>> {
    array.map(|a| a.as_slice().map_err(|_| crate::errors::invalid(name, "must be contiguous"))).transpose()
}
