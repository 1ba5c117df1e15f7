//! Bindings of `geoloc_core::matching`.

use geoloc_core::camera::Camera;
use geoloc_core::lie::SE3;
use geoloc_core::matching::{Match, MatchOptions, epipolar_filter as core_epipolar, match_descriptors as core_match};
use nalgebra::Vector2;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::prelude::*;

use crate::convert::{BorrowedDescriptors, poses, rows};
use crate::errors::{invalid, to_py_err};

/// (pairs (M, 2) int64, distances (M,) float32).
type Matches<'py> = (Bound<'py, PyArray2<i64>>, Bound<'py, PyArray1<f32>>);

fn to_arrays(py: Python<'_>, matches: Vec<Match>) -> PyResult<Matches<'_>> {
    let pairs: Vec<i64> = matches.iter().flat_map(|m| [m.a as i64, m.b as i64]).collect();
    let pairs = Array2::from_shape_vec((matches.len(), 2), pairs).map_err(|e| invalid("pairs", e))?;
    Ok((pairs.into_pyarray(py), matches.iter().map(|m| m.distance).collect::<Vec<_>>().into_pyarray(py)))
}

/// Matches two descriptor arrays (both uint8: Hamming; both float32: Euclidean) without the GIL.
#[pyfunction]
#[pyo3(signature = (descriptors_a, descriptors_b, *, ratio=Some(0.8), mutual=true, max_distance=None))]
pub fn match_descriptors<'py>(
    py: Python<'py>,
    descriptors_a: Bound<'py, PyAny>,
    descriptors_b: Bound<'py, PyAny>,
    ratio: Option<f32>,
    mutual: bool,
    max_distance: Option<f32>,
) -> PyResult<Matches<'py>> {
    let ba = BorrowedDescriptors::extract(&descriptors_a, "descriptors_a")?;
    let bb = BorrowedDescriptors::extract(&descriptors_b, "descriptors_b")?;
    let (va, vb) = (ba.view("descriptors_a")?, bb.view("descriptors_b")?);
    let options = MatchOptions { ratio, mutual, max_distance };
    let m = py.detach(|| core_match(&va, &vb, &options)).map_err(to_py_err)?;
    to_arrays(py, m)
}

/// Keypoints of an (N, 2) float64 array.
fn keypoints(name: &str, a: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Vector2<f64>>> {
    Ok(rows::<2>(name, a)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect())
}

/// Index pairs of an (M, 2) int64 array (refusing negative indices).
fn pairs_of(pairs: &PyReadonlyArray2<'_, i64>) -> PyResult<Vec<Match>> {
    let values = pairs.as_slice().map_err(|_| invalid("pairs", "array must be C-contiguous"))?;
    values
        .chunks_exact(2)
        .enumerate()
        .map(|(i, c)| match (usize::try_from(c[0]), usize::try_from(c[1])) {
            (Ok(a), Ok(b)) => Ok(Match { a, b, distance: 0.0 }),
            _ => Err(invalid("pairs", format!("pairs[{i}] = ({}, {}) holds a negative index", c[0], c[1]))),
        })
        .collect()
}

/// The mask of `pairs` (M, 2) consistent with the epipolar geometry of two known poses.
#[pyfunction]
#[pyo3(signature = (intrinsics, pose_a, pose_b, keypoints_a, keypoints_b, pairs, *, max_px=2.0))]
#[allow(clippy::too_many_arguments)]
pub fn epipolar_filter<'py>(
    py: Python<'py>,
    intrinsics: (f64, f64, f64, f64),
    pose_a: PyReadonlyArray2<'py, f64>,
    pose_b: PyReadonlyArray2<'py, f64>,
    keypoints_a: PyReadonlyArray2<'py, f64>,
    keypoints_b: PyReadonlyArray2<'py, f64>,
    pairs: PyReadonlyArray2<'py, i64>,
    max_px: f64,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    let (fx, fy, cx, cy) = intrinsics;
    let cam = Camera::new(fx, fy, cx, cy).map_err(to_py_err)?;
    let first = |name: &str, p: &PyReadonlyArray2<'py, f64>| -> PyResult<SE3> {
        poses(name, p)?.first().copied().ok_or_else(|| invalid(name, "expected one pose"))
    };
    let (pa, pb) = (first("pose_a", &pose_a)?, first("pose_b", &pose_b)?);
    let (ka, kb) = (keypoints("keypoints_a", &keypoints_a)?, keypoints("keypoints_b", &keypoints_b)?);
    let pairs = pairs_of(&pairs)?;
    let mask = core_epipolar(&cam, &pa, &pb, &ka, &kb, &pairs, max_px).map_err(to_py_err)?;
    Ok(mask.into_pyarray(py))
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(match_descriptors, m)?)?;
    m.add_function(wrap_pyfunction!(epipolar_filter, m)?)?;
    Ok(())
}
