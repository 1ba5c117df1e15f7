//! Bindings of `geoloc_core::adjust`: the bundle adjustment of keyframe poses given as labels
//! (robust priors), points and one label-to-camera offset. Documentation and the numpy-level
//! conversions live in `python/geoloc/adjustment.py`; every check of values is geoloc-core's.

use geoloc_core::adjust::{Adjustment, AdjustmentOptions, LabelSigma, Observation, bundle_adjust_from};
use geoloc_core::camera::Camera;
use geoloc_core::lie::SE3;
use nalgebra::{Vector2, Vector3};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use crate::convert::{indices, matrices_to_array, matrices_to_array3, matrix_to_array, one_pose, poses, rows};
use crate::errors::{invalid, to_py_err};

/// The adjusted problem (see `geoloc.adjustment.bundle_adjust`).
#[pyclass(module = "geoloc._core", name = "Adjustment", frozen)]
pub struct Adjusted {
    inner: Adjustment,
}

#[pymethods]
impl Adjusted {
    /// B_k, the adjusted world_from_label poses (K, 4, 4).
    #[getter]
    fn label_poses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.label_poses.iter().map(SE3::matrix).collect::<Vec<_>>())
    }

    /// The camera poses T_k = B_k X (K, 4, 4) world_from_cam.
    #[getter]
    fn camera_poses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.camera_poses().iter().map(SE3::matrix).collect::<Vec<_>>())
    }

    /// X = label_from_cam (4, 4).
    #[getter]
    fn offset<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix_to_array(py, &self.inner.offset.matrix())
    }

    /// The adjusted points (N, 3), world.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrices_to_array(py, &self.inner.points)
    }

    /// Marginal covariances of the B_k (K, 6, 6), right perturbation, translation first.
    #[getter]
    fn label_pose_covariances<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.label_pose_covariances)
    }

    /// Covariance of X (6, 6).
    #[getter]
    fn offset_covariance<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix_to_array(py, &self.inner.offset_covariance)
    }

    /// Marginal covariances of the points (N, 3, 3), m².
    #[getter]
    fn point_covariances<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.point_covariances)
    }

    /// Per observation, whether the last round used it (M,).
    #[getter]
    fn inliers<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        self.inner.inliers.clone().into_pyarray(py)
    }

    /// (σ_t m, σ_r rad) of the label priors the last round used.
    #[getter]
    fn label_sigma(&self) -> (f64, f64) {
        (self.inner.label_sigma.translation_m, self.inner.label_sigma.rotation_rad)
    }

    /// (start, final) robust cost Σ ρ.
    #[getter]
    fn cost(&self) -> (f64, f64) {
        self.inner.cost
    }

    /// (start, final) RMS reprojection error of the inlier observations, px.
    #[getter]
    fn rms_px(&self) -> (f64, f64) {
        self.inner.rms_px
    }

    /// Levenberg–Marquardt iterations over all rounds.
    #[getter]
    fn iterations(&self) -> usize {
        self.inner.iterations
    }
}

/// `geoloc_core::adjust::bundle_adjust_from` (see `geoloc.adjustment.bundle_adjust`).
#[pyfunction]
#[pyo3(signature = (intrinsics, labels, points, obs_keyframes, obs_points, obs_pixels, *, obs_sigmas=None, start=None, offset=None, label_sigma=None, estimate_offset=true, max_iterations=40, outlier_px=4.0, pixel_sigma=1.0))]
#[allow(clippy::too_many_arguments)]
pub fn bundle_adjust(
    py: Python<'_>,
    intrinsics: (f64, f64, f64, f64),
    labels: PyReadonlyArray2<'_, f64>,
    points: PyReadonlyArray2<'_, f64>,
    obs_keyframes: PyReadonlyArray1<'_, i64>,
    obs_points: PyReadonlyArray1<'_, i64>,
    obs_pixels: PyReadonlyArray2<'_, f64>,
    obs_sigmas: Option<PyReadonlyArray1<'_, f64>>,
    start: Option<PyReadonlyArray2<'_, f64>>,
    offset: Option<PyReadonlyArray2<'_, f64>>,
    label_sigma: Option<(f64, f64)>,
    estimate_offset: bool,
    max_iterations: usize,
    outlier_px: f64,
    pixel_sigma: f64,
) -> PyResult<Adjusted> {
    let (fx, fy, cx, cy) = intrinsics;
    let camera = Camera::new(fx, fy, cx, cy).map_err(to_py_err)?;
    let labels = poses("labels", &labels)?;
    let start = start.as_ref().map(|s| poses("start", s)).transpose()?;
    let offset = offset.as_ref().map(|x| one_pose("offset", x)).transpose()?.unwrap_or_else(SE3::identity);
    let points: Vec<Vector3<f64>> =
        rows::<3>("points", &points)?.chunks_exact(3).map(|c| Vector3::new(c[0], c[1], c[2])).collect();
    let (keyframes, point_ids) = (indices("obs_keyframes", &obs_keyframes)?, indices("obs_points", &obs_points)?);
    let pixels = rows::<2>("obs_pixels", &obs_pixels)?;
    if keyframes.len() != point_ids.len() || 2 * keyframes.len() != pixels.len() {
        return Err(invalid(
            "obs_pixels",
            format!(
                "{} obs_keyframes, {} obs_points and {} obs_pixels must be as many",
                keyframes.len(),
                point_ids.len(),
                pixels.len() / 2
            ),
        ));
    }
    let sigmas = match &obs_sigmas {
        Some(s) => s.as_slice().map_err(|_| invalid("obs_sigmas", "array must be contiguous"))?.to_vec(),
        None => vec![1.0; keyframes.len()],
    };
    if sigmas.len() != keyframes.len() {
        return Err(invalid("obs_sigmas", format!("{} obs_sigmas for {} observations", sigmas.len(), keyframes.len())));
    }
    let observations: Vec<Observation> = keyframes
        .iter()
        .zip(&point_ids)
        .zip(pixels.chunks_exact(2))
        .zip(&sigmas)
        .map(|(((&keyframe, &point), p), &sigma)| Observation {
            keyframe,
            point,
            pixel: Vector2::new(p[0], p[1]),
            sigma,
        })
        .collect();
    let options = AdjustmentOptions {
        pixel_sigma_px: pixel_sigma,
        label_sigma: label_sigma.map(|(t, r)| LabelSigma { translation_m: t, rotation_rad: r }),
        estimate_offset,
        max_iterations,
        outlier_px,
        ..AdjustmentOptions::default()
    };
    let start = start.as_deref().unwrap_or(&labels);
    let inner = py
        .detach(|| bundle_adjust_from(&camera, &labels, (start, &offset), &points, &observations, &options))
        .map_err(to_py_err)?;
    Ok(Adjusted { inner })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("ADJUSTMENT_SIGMA_RANGE", geoloc_core::adjust::SIGMA_RANGE)?;
    m.add_function(wrap_pyfunction!(bundle_adjust, m)?)?;
    m.add_class::<Adjusted>()?;
    Ok(())
}
