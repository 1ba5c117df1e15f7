//! Bindings of `geoloc_core::matching`.

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
    let pairs = Array2::from_shape_vec((matches.len(), 2), pairs).map_err(|e| invalid("matches", e.to_string()))?;
    Ok((pairs.into_pyarray(py), matches.iter().map(|m| m.distance).collect::<Vec<_>>().into_pyarray(py)))
}

fn options(ratio: Option<f32>, mutual: bool, max_distance: Option<f32>) -> MatchOptions {
    MatchOptions { ratio, mutual, max_distance }
}

/// Matches two descriptor arrays (both uint8: Hamming; both float32: Euclidean) without the GIL.
#[pyfunction]
pub fn match_descriptors<'py>(
    py: Python<'py>,
    a: Bound<'py, PyAny>,
    b: Bound<'py, PyAny>,
    ratio: Option<f32>,
    mutual: bool,
    max_distance: Option<f32>,
) -> PyResult<Matches<'py>> {
    let (ba, bb) =
        (BorrowedDescriptors::extract(&a, "descriptors_a")?, BorrowedDescriptors::extract(&b, "descriptors_b")?);
    let (va, vb) = (ba.view("descriptors_a")?, bb.view("descriptors_b")?);
    let options = options(ratio, mutual, max_distance);
    let m = py.detach(|| core_match(&va, &vb, &options)).map_err(to_py_err)?;
    to_arrays(py, m)
}

/// The matches (M, 2) consistent with the epipolar geometry of two known poses.
#[pyfunction]
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
    let cam = geoloc_core::camera::Camera::new(fx, fy, cx, cy).map_err(to_py_err)?;
    let first = |name: &str, p: &PyReadonlyArray2<'py, f64>| -> PyResult<SE3> {
        poses(name, p)?.first().copied().ok_or_else(|| invalid(name, "expected one pose"))
    };
    let (pa, pb) = (first("pose_a", &pose_a)?, first("pose_b", &pose_b)?);
    let ka: Vec<Vector2<f64>> =
        rows::<2>("keypoints_a", &keypoints_a)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect();
    let kb: Vec<Vector2<f64>> =
        rows::<2>("keypoints_b", &keypoints_b)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect();
    let pairs = pairs.as_slice().map_err(|_| invalid("matches", "array must be C-contiguous"))?;
    let matches: Vec<Match> = pairs
        .chunks_exact(2)
        .map(|c| {
            let (a, b) = (usize::try_from(c[0]), usize::try_from(c[1]));
            match (a, b) {
                (Ok(a), Ok(b)) => Ok(Match { a, b, distance: 0.0 }),
                _ => Err(invalid("matches", "indices must be non-negative")),
            }
        })
        .collect::<PyResult<_>>()?;
    let kept = core_epipolar(&cam, &pa, &pb, &ka, &kb, &matches, max_px).map_err(to_py_err)?;
    let mut mask = vec![false; matches.len()];
    let mut k = 0;
    for (i, m) in matches.iter().enumerate() {
        if k < kept.len() && kept[k].a == m.a && kept[k].b == m.b {
            mask[i] = true;
            k += 1;
        }
    }
    Ok(mask.into_pyarray(py))
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(match_descriptors, m)?)?;
    m.add_function(wrap_pyfunction!(epipolar_filter, m)?)?;
    Ok(())
}
