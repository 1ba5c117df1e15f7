//! Bindings of `geoloc_core::{triangulate, pnp}`: arrays and keyword options in, frozen
//! result classes with numpy getters out. Documentation and the numpy-level conversions
//! (dtype, leading axes) live in `python/geoloc/geometry.py`; every check of values, option
//! strings and counts is geoloc-core's.

use geoloc_core::camera::Camera;
use geoloc_core::optim::RobustLoss;
use geoloc_core::pnp::{
    CovarianceModel, PnpOptions, PnpResult, PointUncertainty, RansacOptions, SharedPoseUncertainty,
    pose_partials_from_dense, solve_pnp_with_pixel_sigmas,
};
use geoloc_core::triangulate::{TrackStatus, Triangulation, TriangulationOptions, triangulate as core_triangulate};
use nalgebra::{Matrix3, Matrix3x6, Matrix6, Vector2, Vector3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use crate::convert::{
    contiguous, count, count_usize, indices, matrices, matrices_to_array3, matrix_to_array, one_pose, poses, rows,
};
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

/// (code, name, reason) of every triangulation status, from the core.
#[pyfunction]
pub fn track_statuses() -> Vec<(u8, &'static str, &'static str)> {
    TrackStatus::ALL.iter().map(|s| (s.code(), s.as_str(), s.reason())).collect()
}

/// The triangulation of many tracks (see `geoloc.geometry.TriangulationResult`).
#[pyclass(module = "geoloc._core", frozen)]
pub struct Triangulated {
    inner: Triangulation,
    n_cams: usize,
    with_pose_covariances: bool,
}

#[pymethods]
impl Triangulated {
    /// (P,) the distinct track ids, increasing; row i is track `track_ids[i]`.
    #[getter]
    fn track_ids<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<u64>> {
        self.inner.track_ids.iter().map(|&t| t as u64).collect::<Vec<_>>().into_pyarray(py)
    }
    /// (P, 3) points.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let flat: Vec<f64> =
            self.inner.points.iter().flat_map(|p| p.point.iter().copied().collect::<Vec<_>>()).collect();
        numpy::ndarray::Array2::from_shape_vec((self.inner.points.len(), 3), flat)
            .expect("invariant: three values per point")
            .into_pyarray(py)
    }
    /// (P,) status codes.
    #[getter]
    fn status<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<u8>> {
        self.inner.points.iter().map(|p| p.status.code()).collect::<Vec<_>>().into_pyarray(py)
    }
    /// Per track, the core's reason text.
    fn reasons(&self) -> Vec<&'static str> {
        self.inner.points.iter().map(|p| p.status.reason()).collect()
    }
    /// (P,) mean inlier residual (px).
    #[getter]
    fn mean_residual<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.points.iter().map(|p| p.mean_residual_px).collect::<Vec<_>>().into_pyarray(py)
    }
    /// (P,) widest ray angle (rad).
    #[getter]
    fn max_angle<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.points.iter().map(|p| p.max_angle_rad).collect::<Vec<_>>().into_pyarray(py)
    }
    /// (P, 3, 3) marginal covariances.
    #[getter]
    fn covariances<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.points.iter().map(|p| p.covariance).collect::<Vec<Matrix3<f64>>>())
    }
    /// (P, 3, 3) pixel-noise part of the covariances.
    #[getter]
    fn pixel_covariances<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.points.iter().map(|p| p.pixel_covariance).collect::<Vec<Matrix3<f64>>>())
    }
    /// (P·C, 3, 6) D_jk row-major over (track, camera), or None without pose covariances.
    #[getter]
    fn pose_jacobians<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray3<f64>>> {
        let n_cams = self.n_cams;
        self.with_pose_covariances.then(|| {
            let mut jacobians = vec![Matrix3x6::<f64>::zeros(); self.inner.points.len() * n_cams];
            for (j, p) in self.inner.points.iter().enumerate() {
                for (k, d) in &p.pose_jacobians {
                    jacobians[j * n_cams + k] = *d;
                }
            }
            matrices_to_array3(py, &jacobians)
        })
    }
    /// (O,) per observation: inlier of its valid track.
    #[getter]
    fn observation_inliers<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        self.inner.observation_inliers.clone().into_pyarray(py)
    }
}

/// Forward intersection of tracks; see `geoloc.geometry.triangulate`.
#[pyfunction]
#[pyo3(signature = (poses_wc, intrinsics, cam_ids, track_ids, pixels, *, pose_covariances=None, loss="huber", huber=1.0, pixel_sigma=1.0, max_residual=5.0, min_angle=1f64.to_radians()))]
#[allow(clippy::too_many_arguments)]
pub fn triangulate(
    py: Python<'_>,
    poses_wc: PyReadonlyArray2<'_, f64>,
    intrinsics: (f64, f64, f64, f64),
    cam_ids: PyReadonlyArray1<'_, i64>,
    track_ids: PyReadonlyArray1<'_, i64>,
    pixels: PyReadonlyArray2<'_, f64>,
    pose_covariances: Option<PyReadonlyArray2<'_, f64>>,
    loss: &str,
    huber: f64,
    pixel_sigma: f64,
    max_residual: f64,
    min_angle: f64,
) -> PyResult<Triangulated> {
    let cam = camera(intrinsics)?;
    let poses = poses("poses", &poses_wc)?;
    let covs = pose_covariances.as_ref().map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
    let (cam_ids, track_ids) = (indices("cam_ids", &cam_ids)?, indices("track_ids", &track_ids)?);
    let pixels = vectors2("pixels", &pixels)?;
    let loss = RobustLoss::from_name(loss, huber, "huber").map_err(to_py_err)?;
    let options = TriangulationOptions {
        loss,
        pixel_sigma,
        max_residual_px: max_residual,
        min_angle_rad: min_angle,
        ..Default::default()
    };
    let inner = py
        .detach(|| core_triangulate(&cam, &poses, covs.as_deref(), &cam_ids, &track_ids, &pixels, &options))
        .map_err(to_py_err)?;
    Ok(Triangulated { inner, n_cams: poses.len(), with_pose_covariances: covs.is_some() })
}

/// The pose of a camera from 2D–3D correspondences (see `geoloc.geometry.solve_pnp`).
#[pyclass(module = "geoloc._core", name = "PnPResult", frozen)]
pub struct PnPResult {
    inner: PnpResult,
}

#[pymethods]
impl PnPResult {
    /// Whether a pose was found.
    #[getter]
    fn success(&self) -> bool {
        self.inner.success
    }
    /// "ok" or why not.
    #[getter]
    fn reason(&self) -> &str {
        &self.inner.reason
    }
    /// (4, 4) world_from_cam.
    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix_to_array(py, &self.inner.world_from_cam.matrix())
    }
    /// (6, 6) right-perturbation covariance, translation first.
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix_to_array::<6, 6>(py, &self.inner.covariance)
    }
    /// (N,) used in the final solve.
    #[getter]
    fn inliers<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        self.inner.inliers.clone().into_pyarray(py)
    }
    /// RMS reprojection error of the inliers (px).
    #[getter]
    fn rms(&self) -> f64 {
        self.inner.rms_px
    }
    /// Isometric position σ (m).
    #[getter]
    fn sigma_p(&self) -> f64 {
        self.inner.sigma_p
    }
    /// Isometric rotation σ (rad).
    #[getter]
    fn sigma_r(&self) -> f64 {
        self.inner.sigma_r
    }
    /// RANSAC samples drawn.
    #[getter]
    fn ransac_iterations(&self) -> usize {
        self.inner.ransac_iterations
    }
    /// Iterations of the last LM run.
    #[getter]
    fn lm_iterations(&self) -> usize {
        self.inner.lm.map_or(0, |r| r.iterations)
    }
    /// Whether the last LM run converged.
    #[getter]
    fn lm_converged(&self) -> bool {
        self.inner.lm.is_some_and(|r| r.converged())
    }
    /// Why the last LM run stopped (None if none ran).
    #[getter]
    fn lm_termination(&self) -> Option<&'static str> {
        self.inner.lm.map(|r| r.termination.as_str())
    }
    fn __repr__(&self) -> String {
        let r = &self.inner;
        let n = r.inliers.iter().filter(|&&i| i).count();
        format!(
            "PnPResult(success={}, reason={:?}, inliers={n}/{}, rms={:.3})",
            r.success,
            r.reason,
            r.inliers.len(),
            r.rms_px
        )
    }
}

/// The keyword options of `solve_pnp`, turned into core options in one place: the
/// robust loss and the noise model, and RANSAC's (`ransac`, `min_iterations`,
/// `max_iterations`, `confidence`, `seed`).
struct PnpKeywords<'a, 'py> {
    loss: &'a str,
    huber: f64,
    pixel_sigma: f64,
    max_residual: f64,
    covariance: &'a str,
    ransac: RansacKeywords<'a, 'py>,
}

/// The RANSAC keywords of `solve_pnp`.
struct RansacKeywords<'a, 'py> {
    ransac: Option<bool>,
    min_iterations: Option<&'a Bound<'py, PyAny>>,
    max_iterations: Option<&'a Bound<'py, PyAny>>,
    confidence: f64,
    seed: Option<&'a Bound<'py, PyAny>>,
}

impl RansacKeywords<'_, '_> {
    /// `ransac=False` needs an initial pose.
    fn check(&self, has_init: bool) -> PyResult<()> {
        if self.ransac == Some(false) && !has_init {
            return Err(invalid("init_pose", "required when ransac=False"));
        }
        Ok(())
    }
}

impl PnpKeywords<'_, '_> {
    /// The core options; `has_init`: whether an initial pose was given (`ransac=True` with
    /// one runs RANSAC too).
    fn options(&self, has_init: bool) -> PyResult<PnpOptions> {
        let (d, r) = (RansacOptions::default(), &self.ransac);
        let or = |name, v: Option<&Bound<'_, PyAny>>, default| v.map_or(Ok(default), |v| count_usize(name, v));
        Ok(PnpOptions {
            loss: RobustLoss::from_name(self.loss, self.huber, "huber").map_err(to_py_err)?,
            pixel_sigma: self.pixel_sigma,
            max_residual_px: self.max_residual,
            covariance: self.covariance.parse::<CovarianceModel>().map_err(to_py_err)?,
            ransac_with_init: r.ransac == Some(true) && has_init,
            ransac: RansacOptions {
                min_iterations: or("min_iterations", r.min_iterations, d.min_iterations)?,
                max_iterations: or("max_iterations", r.max_iterations, d.max_iterations)?,
                confidence: r.confidence,
                seed: r.seed.map_or(Ok(d.seed), |v| count("seed", v))?,
            },
            ..PnpOptions::default()
        })
    }
}

/// Point and pose uncertainty arrays, borrowed and checked for shape.
type Uncertainty = (Vec<Matrix3<f64>>, Option<(Vec<Matrix3x6<f64>>, Vec<Matrix6<f64>>)>);

fn uncertainty_arrays(
    point_covariances: Option<&PyReadonlyArray2<'_, f64>>,
    point_pose_jacobians: Option<&PyReadonlyArray2<'_, f64>>,
    pose_covariances: Option<&PyReadonlyArray2<'_, f64>>,
) -> PyResult<Option<Uncertainty>> {
    let covs = point_covariances.map(|c| matrices::<3, 3, 9>("point_covariances", c)).transpose()?;
    let jacs = point_pose_jacobians.map(|c| matrices::<3, 6, 18>("point_pose_jacobians", c)).transpose()?;
    let pose_covs = pose_covariances.map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
    match (covs, jacs, pose_covs) {
        (None, None, None) => Ok(None),
        (Some(c), None, None) => Ok(Some((c, None))),
        (Some(c), Some(j), Some(p)) => Ok(Some((c, Some((j, p))))),
        (None, _, _) => Err(invalid("point_covariances", "required when pose_jacobians / pose_covariances are given")),
        _ => Err(invalid("pose_covariances", "pose_jacobians and pose_covariances go together")),
    }
}

/// The arrays of one `solve_pnp` call, converted and checked for shape (in the order the
/// arguments are named: intrinsics, points3d, pixels, init_pose).
struct PnpInputs {
    camera: Camera,
    points: Vec<Vector3<f64>>,
    pixels: Vec<Vector2<f64>>,
    init: Option<geoloc_core::lie::SE3>,
}

impl PnpInputs {
    fn read(
        intrinsics: (f64, f64, f64, f64),
        points3d: &PyReadonlyArray2<'_, f64>,
        pixels: &PyReadonlyArray2<'_, f64>,
        init_pose: Option<&PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<Self> {
        let (camera, points, pixels) =
            (camera(intrinsics)?, vectors3("points3d", points3d)?, vectors2("pixels", pixels)?);
        let init = init_pose.map(|p| one_pose("init_pose", p)).transpose()?;
        Ok(Self { camera, points, pixels, init })
    }

    /// The core solve with the uncertainty arrays and per-correspondence σ scales, if given.
    fn solve(
        &self,
        unc: Option<&Uncertainty>,
        sigmas: Option<&[f64]>,
        options: &PnpOptions,
    ) -> geoloc_core::Result<PnpResult> {
        let dense = unc.and_then(|(_, s)| s.as_ref());
        let partials = dense.map(|(j, c)| pose_partials_from_dense(j, self.points.len(), c.len())).transpose()?;
        let shared = dense
            .zip(partials.as_deref())
            .map(|((_, c), j)| SharedPoseUncertainty { jacobians: j, pose_covariances: c });
        let uncertainty = unc.map(|(c, _)| PointUncertainty { covariances: c, shared });
        let (cam, init) = (&self.camera, self.init.as_ref());
        solve_pnp_with_pixel_sigmas(cam, &self.points, &self.pixels, sigmas, init, uncertainty.as_ref(), options)
    }
}

/// Backward intersection; see `geoloc.geometry.solve_pnp`.
#[pyfunction]
#[pyo3(signature = (points3d, pixels, intrinsics, *, init_pose=None, point_covariances=None, point_pose_jacobians=None, pose_covariances=None, pixel_sigmas=None, loss="huber", huber=1.0, pixel_sigma=1.0, max_residual=5.0, covariance="propagated", ransac=None, min_iterations=None, max_iterations=None, confidence=0.9999, seed=None))]
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
    pixel_sigmas: Option<PyReadonlyArray1<'py, f64>>,
    loss: &str,
    huber: f64,
    pixel_sigma: f64,
    max_residual: f64,
    covariance: &str,
    ransac: Option<bool>,
    min_iterations: Option<Bound<'py, PyAny>>,
    max_iterations: Option<Bound<'py, PyAny>>,
    confidence: f64,
    seed: Option<Bound<'py, PyAny>>,
) -> PyResult<PnPResult> {
    let inputs = PnpInputs::read(intrinsics, &points3d, &pixels, init_pose.as_ref())?;
    let ransac = RansacKeywords {
        ransac,
        min_iterations: min_iterations.as_ref(),
        max_iterations: max_iterations.as_ref(),
        confidence,
        seed: seed.as_ref(),
    };
    ransac.check(inputs.init.is_some())?;
    let unc = uncertainty_arrays(point_covariances.as_ref(), point_pose_jacobians.as_ref(), pose_covariances.as_ref())?;
    let sigmas = contiguous("pixel_sigmas", pixel_sigmas.as_ref())?;
    let keywords = PnpKeywords { loss, huber, pixel_sigma, max_residual, covariance, ransac };
    let options = keywords.options(inputs.init.is_some())?;
    let inner = py.detach(|| inputs.solve(unc.as_ref(), sigmas, &options)).map_err(to_py_err)?;
    Ok(PnPResult { inner })
}

/// Registers the functions and classes of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(triangulate, m)?)?;
    m.add_function(wrap_pyfunction!(solve_pnp, m)?)?;
    m.add_function(wrap_pyfunction!(track_statuses, m)?)?;
    m.add_class::<Triangulated>()?;
    m.add_class::<PnPResult>()?;
    Ok(())
}
