//! Bindings of `geoloc_core::{camera, triangulate, pnp}`: arrays in, dicts of arrays out.
//! Shapes and defaults are handled by `python/geoloc/geometry.py`.

use geoloc_core::camera::Camera;
use geoloc_core::optim::RobustLoss;
use geoloc_core::pnp::{
    CovarianceModel, PnpOptions, PointUncertainty, RansacOptions, SharedPoseUncertainty, solve_pnp as core_solve_pnp,
};
use geoloc_core::triangulate::{TriangulationOptions, triangulate as core_triangulate};
use nalgebra::{Matrix3x6, Vector2, Vector3};
use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{indices, matrices, matrices_to_array, poses, rows};
use crate::errors::{invalid, to_py_err};

fn camera(intrinsics: (f64, f64, f64, f64)) -> PyResult<Camera> {
    let (fx, fy, cx, cy) = intrinsics;
    Camera::new(fx, fy, cx, cy).map_err(to_py_err)
}

fn vectors2(name: &str, array: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Vector2<f64>>> {
    Ok(rows::<2>(name, array)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect())
}

fn vectors3(name: &str, array: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Vector3<f64>>> {
    Ok(rows::<3>(name, array)?.chunks_exact(3).map(|c| Vector3::new(c[0], c[1], c[2])).collect())
}

/// Forward intersection of tracks; see `geoloc.geometry.triangulate`.
#[pyfunction]
#[pyo3(signature = (poses_wc, intrinsics, cam_ids, track_ids, pixels, pose_covariances, loss, loss_width, pixel_sigma, max_residual, min_angle))]
#[allow(clippy::too_many_arguments)]
pub fn triangulate<'py>(
    py: Python<'py>,
    poses_wc: PyReadonlyArray2<'py, f64>,
    intrinsics: (f64, f64, f64, f64),
    cam_ids: PyReadonlyArray1<'py, i64>,
    track_ids: PyReadonlyArray1<'py, i64>,
    pixels: PyReadonlyArray2<'py, f64>,
    pose_covariances: Option<PyReadonlyArray2<'py, f64>>,
    loss: &str,
    loss_width: f64,
    pixel_sigma: f64,
    max_residual: f64,
    min_angle: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let cam = camera(intrinsics)?;
    let poses = poses("poses", &poses_wc)?;
    let covs = pose_covariances.as_ref().map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
    let cam_ids = indices("cam_ids", &cam_ids)?;
    let track_ids = indices("track_ids", &track_ids)?;
    let pixels = vectors2("pixels", &pixels)?;
    let options = TriangulationOptions {
        loss: RobustLoss::from_name(loss, loss_width, "huber").map_err(to_py_err)?,
        pixel_sigma,
        max_residual_px: max_residual,
        min_angle_rad: min_angle,
        ..TriangulationOptions::default()
    };
    let tri = py
        .detach(|| core_triangulate(&cam, &poses, covs.as_deref(), &cam_ids, &track_ids, &pixels, &options))
        .map_err(to_py_err)?;
    let out = PyDict::new(py);
    if covs.is_some() {
        let (n_cams, n) = (poses.len(), tri.points.len());
        let mut jacobians = vec![Matrix3x6::<f64>::zeros(); n * n_cams];
        for (j, p) in tri.points.iter().enumerate() {
            for (k, d) in &p.pose_jacobians {
                jacobians[j * n_cams + k] = *d;
            }
        }
        out.set_item("pose_jacobians", matrices_to_array(py, &jacobians))?;
    }
    out.set_item("points", matrices_to_array(py, &tri.points.iter().map(|p| p.point).collect::<Vec<_>>()))?;
    out.set_item("status", tri.points.iter().map(|p| p.status as u8).collect::<Vec<_>>().into_pyarray(py))?;
    out.set_item("mean_residual", tri.points.iter().map(|p| p.mean_residual_px).collect::<Vec<_>>().into_pyarray(py))?;
    out.set_item("max_angle", tri.points.iter().map(|p| p.max_angle_rad).collect::<Vec<_>>().into_pyarray(py))?;
    out.set_item("covariances", matrices_to_array(py, &tri.points.iter().map(|p| p.covariance).collect::<Vec<_>>()))?;
    out.set_item(
        "pixel_covariances",
        matrices_to_array(py, &tri.points.iter().map(|p| p.pixel_covariance).collect::<Vec<_>>()),
    )?;
    out.set_item("observation_inliers", tri.observation_inliers.into_pyarray(py))?;
    Ok(out)
}

/// Backward intersection; see `geoloc.geometry.solve_pnp`.
#[pyfunction]
#[pyo3(signature = (points3d, pixels, intrinsics, init_pose, point_covariances, point_pose_jacobians, pose_covariances, loss, loss_width, pixel_sigma, max_residual, covariance, min_iterations, max_iterations, confidence, seed))]
#[allow(clippy::too_many_arguments)]
pub fn solve_pnp<'py>(
    py: Python<'py>,
    points3d: PyReadonlyArray2<'py, f64>,
    pixels: PyReadonlyArray2<'py, f64>,
    intrinsics: (f64, f64, f64, f64),
    init_pose: Option<PyReadonlyArray2<'py, f64>>,
    point_covariances: Option<PyReadonlyArray2<'py, f64>>,
    point_pose_jacobians: Option<PyReadonlyArray2<'py, f64>>,
    pose_covariances: Option<PyReadonlyArray2<'py, f64>>,
    loss: &str,
    loss_width: f64,
    pixel_sigma: f64,
    max_residual: f64,
    covariance: &str,
    min_iterations: usize,
    max_iterations: usize,
    confidence: f64,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let cam = camera(intrinsics)?;
    let points = vectors3("points3d", &points3d)?;
    let pixels = vectors2("pixels", &pixels)?;
    let init = match &init_pose {
        Some(p) => poses("init_pose", p)?.first().copied(),
        None => None,
    };
    let covs = point_covariances.as_ref().map(|c| matrices::<3, 3, 9>("point_covariances", c)).transpose()?;
    let jacs = point_pose_jacobians.as_ref().map(|c| matrices::<3, 6, 18>("point_pose_jacobians", c)).transpose()?;
    let pose_covs = pose_covariances.as_ref().map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
    if covs.is_none() && (jacs.is_some() || pose_covs.is_some()) {
        return Err(invalid("point_covariances", "required when point_pose_jacobians / pose_covariances are given"));
    }
    if jacs.is_some() != pose_covs.is_some() {
        return Err(invalid("pose_covariances", "point_pose_jacobians and pose_covariances go together"));
    }
    let covariance = match covariance {
        "propagated" => CovarianceModel::Propagated,
        "paper" => CovarianceModel::Paper,
        other => return Err(invalid("covariance", format!("expected \"propagated\" or \"paper\", got {other:?}"))),
    };
    let options = PnpOptions {
        loss: RobustLoss::from_name(loss, loss_width, "huber").map_err(to_py_err)?,
        pixel_sigma,
        max_residual_px: max_residual,
        covariance,
        ransac: RansacOptions { min_iterations, max_iterations, confidence, seed },
        ..PnpOptions::default()
    };
    let result = py
        .detach(|| {
            let shared = match (&jacs, &pose_covs) {
                (Some(j), Some(c)) => Some(SharedPoseUncertainty { jacobians: j, pose_covariances: c }),
                _ => None,
            };
            let uncertainty = covs.as_ref().map(|c| PointUncertainty { covariances: c, shared });
            core_solve_pnp(&cam, &points, &pixels, init.as_ref(), uncertainty.as_ref(), &options)
        })
        .map_err(to_py_err)?;
    let out = PyDict::new(py);
    out.set_item("success", result.success)?;
    out.set_item("reason", result.reason)?;
    out.set_item("pose", matrices_to_array(py, &[result.world_from_cam.matrix()]))?;
    out.set_item("covariance", matrices_to_array(py, &[result.covariance]))?;
    out.set_item("inliers", result.inliers.into_pyarray(py))?;
    out.set_item("rms", result.rms_px)?;
    out.set_item("sigma_p", result.sigma_p)?;
    out.set_item("sigma_r", result.sigma_r)?;
    out.set_item("ransac_iterations", result.ransac_iterations)?;
    out.set_item("lm_iterations", result.lm.map_or(0, |r| r.iterations))?;
    out.set_item("lm_converged", result.lm.is_some_and(|r| r.converged()))?;
    Ok(out)
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(triangulate, m)?)?;
    m.add_function(wrap_pyfunction!(solve_pnp, m)?)?;
    Ok(())
}
