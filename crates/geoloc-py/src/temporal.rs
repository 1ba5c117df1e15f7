//! Bindings of `geoloc_core::{keyframes, motion, fusion}`.

use geoloc_core::fusion::{FusionSource, Gate, fuse as core_fuse};
use geoloc_core::keyframes::{KeyframeOptions, keyframe_score as core_score, select_keyframes as core_select};
use geoloc_core::motion::motion_predict as core_motion_predict;
use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{matrices, matrices_to_array, poses};
use crate::errors::{invalid, to_py_err};

fn options(n: usize, window: usize, d_m: f64, ell: f64, alpha_m: f64, min_score: f64) -> KeyframeOptions {
    KeyframeOptions { n, window, d_m, ell, alpha_m_rad: alpha_m, min_score }
}

/// s(T₁, T₂) for each pair of rows (N, 16) × (N, 16) → (N,).
#[pyfunction]
pub fn keyframe_score<'py>(
    py: Python<'py>,
    pose1: PyReadonlyArray2<'py, f64>,
    pose2: PyReadonlyArray2<'py, f64>,
    d_m: f64,
    ell: f64,
    alpha_m: f64,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let (a, b) = (poses("T1", &pose1)?, poses("T2", &pose2)?);
    if a.len() != b.len() {
        return Err(invalid("T2", format!("has {} poses but T1 has {}", b.len(), a.len())));
    }
    Ok(a.iter().zip(&b).map(|(x, y)| core_score(x, y, d_m, ell, alpha_m)).collect::<Vec<_>>().into_pyarray(py))
}

/// The keyframe group around `k`.
#[pyfunction]
#[pyo3(signature = (poses_wc, k, n, window, d_m, ell, alpha_m, min_score))]
#[allow(clippy::too_many_arguments)]
pub fn select_keyframes<'py>(
    py: Python<'py>,
    poses_wc: PyReadonlyArray2<'py, f64>,
    k: usize,
    n: usize,
    window: usize,
    d_m: f64,
    ell: f64,
    alpha_m: f64,
    min_score: f64,
) -> PyResult<Bound<'py, PyArray1<u64>>> {
    let p = poses("poses", &poses_wc)?;
    let group = core_select(&p, k, &options(n, window, d_m, ell, alpha_m, min_score)).map_err(to_py_err)?;
    Ok(group.into_iter().map(|i| i as u64).collect::<Vec<_>>().into_pyarray(py))
}

/// Constant-velocity prediction: dict(pose (1, 16), covariance (1, 36), velocity (6,), rms_residual).
#[pyfunction]
pub fn motion_predict<'py>(
    py: Python<'py>,
    poses_wc: PyReadonlyArray2<'py, f64>,
    timestamps: PyReadonlyArray1<'py, f64>,
    t_query: f64,
    covariances: Option<PyReadonlyArray2<'py, f64>>,
) -> PyResult<Bound<'py, PyDict>> {
    let p = poses("poses", &poses_wc)?;
    let t = timestamps.as_slice().map_err(|_| invalid("timestamps", "must be contiguous"))?;
    let c = covariances.as_ref().map(|c| matrices::<6, 6, 36>("covariances", c)).transpose()?;
    let pred = core_motion_predict(&p, t, t_query, c.as_deref()).map_err(to_py_err)?;
    let out = PyDict::new(py);
    out.set_item("pose", matrices_to_array(py, &[pred.world_from_cam.matrix()]))?;
    out.set_item("covariance", matrices_to_array(py, &[pred.covariance]))?;
    out.set_item("velocity", pred.details.velocity.as_slice().to_vec().into_pyarray(py))?;
    out.set_item("rms_residual", pred.details.rms_residual)?;
    Ok(out)
}

/// Gate and fuse: dict(pose (1, 16), covariance (1, 36), source, iterations).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn fuse<'py>(
    py: Python<'py>,
    pose_m: PyReadonlyArray2<'py, f64>,
    cov_m: PyReadonlyArray2<'py, f64>,
    pose_g: PyReadonlyArray2<'py, f64>,
    cov_g: PyReadonlyArray2<'py, f64>,
    gate_sigma: f64,
    gate: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let pm = poses("pose_m", &pose_m)?;
    let pg = poses("pose_g", &pose_g)?;
    let cm = matrices::<6, 6, 36>("cov_m", &cov_m)?;
    let cg = matrices::<6, 6, 36>("cov_g", &cov_g)?;
    let (Some(pm), Some(pg), Some(cm), Some(cg)) = (pm.first(), pg.first(), cm.first(), cg.first()) else {
        return Err(invalid("pose_m", "expected one pose and one covariance each"));
    };
    let gate = match gate {
        "isometric" => Gate::Isometric,
        "chi2" => Gate::ChiSquared,
        other => return Err(invalid("gate", format!("expected \"isometric\" or \"chi2\", got {other:?}"))),
    };
    let f = core_fuse(pm, cm, pg, cg, gate_sigma, gate).map_err(to_py_err)?;
    let out = PyDict::new(py);
    out.set_item("pose", matrices_to_array(py, &[f.world_from_cam.matrix()]))?;
    out.set_item("covariance", matrices_to_array(py, &[f.covariance]))?;
    out.set_item(
        "source",
        match f.details {
            FusionSource::Fused => "fused",
            FusionSource::Motion => "motion",
        },
    )?;
    out.set_item("iterations", f.report.map_or(0, |r| r.iterations))?;
    Ok(out)
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(keyframe_score, m)?)?;
    m.add_function(wrap_pyfunction!(select_keyframes, m)?)?;
    m.add_function(wrap_pyfunction!(motion_predict, m)?)?;
    m.add_function(wrap_pyfunction!(fuse, m)?)?;
    Ok(())
}
