//! Bindings of `geoloc_core::{map, localizer}` at the level of features (keypoints and
//! descriptors); images and feature extraction live in Python.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use geoloc_core::camera::Camera;
use geoloc_core::localizer::{Frame, Localization as CoreLocalization, Localizer as CoreLocalizer, LocalizerOptions};
use geoloc_core::map::{Keyframe, Map as CoreMap, RetrievalMethod, RetrievalQuery, SelfCalibrationHeader};
use nalgebra::Vector2;
use numpy::{PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

use crate::convert::{BorrowedDescriptors, matrices, matrices_to_array, matrices_to_array3, poses, rows};
use crate::errors::{invalid, to_py_err};
use crate::options::{build_options, localizer_dict, localizer_options};

fn keypoints(name: &str, a: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Vector2<f64>>> {
    Ok(rows::<2>(name, a)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect())
}

/// One global descriptor per keyframe, from an (N, D) float32 array.
fn globals(g: Option<&PyReadonlyArray2<'_, f32>>, n: usize) -> PyResult<Vec<Option<Vec<f32>>>> {
    let Some(g) = g else { return Ok(vec![None; n]) };
    let dim = g.shape()[1];
    if g.shape()[0] != n {
        return Err(invalid("global_descriptors", format!("expected shape ({n}, D), got {:?}", g.shape())));
    }
    let values = g.as_slice().map_err(|_| invalid("global_descriptors", "must be C-contiguous"))?;
    Ok(values.chunks_exact(dim.max(1)).map(|r| Some(r.to_vec())).chain(std::iter::repeat(None)).take(n).collect())
}

/// The keyframes: one pose, keypoint array and descriptor array each.
fn keyframes(
    poses_wc: &PyReadonlyArray2<'_, f64>,
    keypoints_list: &[PyReadonlyArray2<'_, f64>],
    descriptors_list: &[Bound<'_, PyAny>],
    global_descriptors: Option<&PyReadonlyArray2<'_, f32>>,
) -> PyResult<Vec<Keyframe>> {
    let poses = poses("poses", poses_wc)?;
    for (name, len) in [("keypoints", keypoints_list.len()), ("descriptors", descriptors_list.len())] {
        if len != poses.len() {
            return Err(invalid(name, format!("expected one array per pose ({}), got {len}", poses.len())));
        }
    }
    let globals = globals(global_descriptors, poses.len())?;
    (0..poses.len())
        .map(|i| {
            let name = format!("descriptors[{i}]");
            Ok(Keyframe {
                world_from_cam: poses[i],
                keypoints: keypoints(&format!("keypoints[{i}]"), &keypoints_list[i])?,
                descriptors: BorrowedDescriptors::extract(&descriptors_list[i], &name)?.to_owned_set(&name)?,
                global: globals[i].clone(),
            })
        })
        .collect()
}

/// An optional 1-D array argument of element type `T` (`dtype` and length `len` name it in
/// the error).
fn optional_vector<'py, T: numpy::Element>(
    value: Option<&Bound<'py, PyAny>>,
    name: &str,
    dtype: &str,
    len: &str,
) -> PyResult<Option<PyReadonlyArray1<'py, T>>> {
    value
        .map(|v| v.extract().map_err(|_| invalid(name, format!("expected a 1-D {dtype} array of shape ({len},)"))))
        .transpose()
}

/// The contiguous values of an optional 1-D array.
fn slice_of<'a, T: numpy::Element>(
    array: Option<&'a PyReadonlyArray1<'_, T>>,
    name: &str,
) -> PyResult<Option<&'a [T]>> {
    array.map(|a| a.as_slice().map_err(|_| invalid(name, "must be contiguous"))).transpose()
}

/// A map of keyframes (features level).
#[pyclass(module = "geoloc._core", frozen)]
pub struct FeatureMap {
    inner: Arc<CoreMap>,
}

#[pymethods]
impl FeatureMap {
    /// Builds a map from keyframes (poses (K, 4, 4) flattened to (K, 16), keypoints and
    /// descriptors per keyframe); `options` holds the build options the caller set (see
    /// `build_defaults()`), everything else is the core's default.
    #[new]
    #[pyo3(signature = (intrinsics, poses_wc, keypoints_list, descriptors_list, *, global_descriptors=None, pose_covariances=None, timestamps=None, options=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        intrinsics: (f64, f64, f64, f64),
        poses_wc: PyReadonlyArray2<'_, f64>,
        keypoints_list: Vec<PyReadonlyArray2<'_, f64>>,
        descriptors_list: Vec<Bound<'_, PyAny>>,
        global_descriptors: Option<PyReadonlyArray2<'_, f32>>,
        pose_covariances: Option<PyReadonlyArray2<'_, f64>>,
        timestamps: Option<PyReadonlyArray1<'_, f64>>,
        options: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let options = build_options(options)?;
        let (fx, fy, cx, cy) = intrinsics;
        let camera = Camera::new(fx, fy, cx, cy).map_err(to_py_err)?;
        let kfs = keyframes(&poses_wc, &keypoints_list, &descriptors_list, global_descriptors.as_ref())?;
        let covs = pose_covariances.as_ref().map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
        let ts = timestamps
            .as_ref()
            .map(|t| t.as_slice().map_err(|_| invalid("timestamps", "must be contiguous")))
            .transpose()?;
        let map = py.detach(|| CoreMap::build_with_options(camera, kfs, covs, ts, &options)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(map) })
    }

    fn __len__(&self) -> usize {
        self.inner.keyframes.len()
    }

    /// (fx, fy, cx, cy) of the map's camera.
    #[getter]
    fn intrinsics(&self) -> (f64, f64, f64, f64) {
        let c = self.inner.camera;
        (c.fx, c.fy, c.cx, c.cy)
    }

    /// How the map retrieves keyframes: "bow", "global" or "fused".
    #[getter]
    fn retrieval(&self) -> &'static str {
        match self.inner.retrieval {
            geoloc_core::map::Retrieval::Global(_) => RetrievalMethod::Global.as_str(),
            geoloc_core::map::Retrieval::Bow { .. } => RetrievalMethod::Bow.as_str(),
            geoloc_core::map::Retrieval::Fused { .. } => RetrievalMethod::Fused.as_str(),
        }
    }

    /// The `k` keyframes most similar to a query, best first: the localizers' retrieval
    /// (keypoints (N, 2) in the caller's undistorted pixels, descriptors (N, W), the global
    /// descriptor (D,) for maps that retrieve by one).
    #[pyo3(signature = (keypoints, descriptors, global_descriptor=None, k=5))]
    fn retrieve(
        &self,
        py: Python<'_>,
        keypoints: PyReadonlyArray2<'_, f64>,
        descriptors: Bound<'_, PyAny>,
        global_descriptor: Option<Bound<'_, PyAny>>,
        k: usize,
    ) -> PyResult<Vec<usize>> {
        let kps = self::keypoints("keypoints", &keypoints)?;
        let borrowed = BorrowedDescriptors::extract(&descriptors, "descriptors")?;
        let global = optional_vector::<f32>(global_descriptor.as_ref(), "global_descriptor", "float32", "D")?;
        let global = slice_of(global.as_ref(), "global_descriptor")?;
        let query = RetrievalQuery { keypoints: &kps, descriptors: borrowed.view("descriptors")?, global };
        py.detach(|| self.inner.retrieve_frame(&query, k)).map_err(to_py_err)
    }

    /// The camera the map estimated from its keyframes (JSON text of the map header's
    /// `self_calibration` object), or None when it was not tried.
    #[getter]
    fn self_calibration_json(&self) -> PyResult<Option<String>> {
        self.inner
            .self_calibration
            .as_ref()
            .map(|s| serde_json::to_string(&SelfCalibrationHeader::from_self_calibration(s)))
            .transpose()
            .map_err(|e| invalid("self_calibration", e.to_string()))
    }

    /// The labels' adjustment report (JSON text), or None when the labels were not adjusted.
    #[getter]
    fn labels_json(&self) -> Option<String> {
        self.inner.labels.as_ref().map(|l| l.report_json().to_string())
    }

    /// Per keyframe the labels' correction e_k = log(L_k⁻¹ B_k)^∨ (K, 6: translation m then
    /// rotation rad, right perturbation), or None when the labels were not adjusted.
    #[getter]
    fn label_corrections<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        let l = self.inner.labels.as_ref()?;
        Some(matrices_to_array(py, &l.corrections))
    }

    /// Per keyframe the significance e_kᵀ Σ_k⁻¹ e_k of its correction (K,), or None when the
    /// labels were not adjusted.
    #[getter]
    fn label_significance<'py>(&self, py: Python<'py>) -> Option<Bound<'py, numpy::PyArray1<f64>>> {
        let l = self.inner.labels.as_ref()?;
        Some(numpy::IntoPyArray::into_pyarray(l.significance.clone(), py))
    }

    /// The pose labels as given (K, 4, 4), or None when the labels were not adjusted.
    #[getter]
    fn label_poses<'py>(&self, py: Python<'py>) -> Option<Bound<'py, numpy::PyArray3<f64>>> {
        let l = self.inner.labels.as_ref()?;
        Some(matrices_to_array3(py, &l.labels.iter().map(|p| p.matrix()).collect::<Vec<_>>()))
    }

    /// The keyframe poses in the labels' convention (K, 4, 4): adjusted when the labels were
    /// adjusted, else the labels.
    #[getter]
    fn keyframe_poses<'py>(&self, py: Python<'py>) -> Bound<'py, numpy::PyArray3<f64>> {
        let poses = self.inner.keyframe_label_poses();
        matrices_to_array3(py, &poses.iter().map(|p| p.matrix()).collect::<Vec<_>>())
    }

    /// The keyframes' camera poses (K, 4, 4) world_from_cam (adjusted when the labels were).
    #[getter]
    fn camera_poses<'py>(&self, py: Python<'py>) -> Bound<'py, numpy::PyArray3<f64>> {
        matrices_to_array3(py, &self.inner.poses().iter().map(|p| p.matrix()).collect::<Vec<_>>())
    }

    /// The labels' adjustment problem of this map (`Map::label_adjustment_problem`):
    /// (keyframes (S,) int64, labels (S, 4, 4), points (N, 3), observation keyframes (M,)
    /// int64 into the S, observation points (M,) int64, observation pixels (M, 2)).
    #[allow(clippy::type_complexity)]
    fn label_adjustment_problem<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(
        Bound<'py, numpy::PyArray1<i64>>,
        Bound<'py, numpy::PyArray3<f64>>,
        Bound<'py, numpy::PyArray2<f64>>,
        Bound<'py, numpy::PyArray1<i64>>,
        Bound<'py, numpy::PyArray1<i64>>,
        Bound<'py, numpy::PyArray2<f64>>,
    )> {
        let inner = Arc::clone(&self.inner);
        let p = py.detach(move || inner.label_adjustment_problem()).map_err(to_py_err)?;
        let as_i64 = |v: Vec<usize>| v.into_iter().map(|i| i as i64).collect::<Vec<i64>>();
        let pixels: Vec<_> = p.observations.iter().map(|o| o.pixel).collect();
        Ok((
            numpy::IntoPyArray::into_pyarray(as_i64(p.keyframes), py),
            matrices_to_array3(py, &p.labels.iter().map(|x| x.matrix()).collect::<Vec<_>>()),
            matrices_to_array(py, &p.points),
            numpy::IntoPyArray::into_pyarray(as_i64(p.observations.iter().map(|o| o.keyframe).collect()), py),
            numpy::IntoPyArray::into_pyarray(as_i64(p.observations.iter().map(|o| o.point).collect()), py),
            matrices_to_array(py, &pixels),
        ))
    }

    /// Points of the map-level 3D model, or None when the map has no model.
    #[getter]
    fn model_points(&self) -> Option<usize> {
        self.inner.model.as_ref().map(|m| m.len())
    }

    /// The noise estimated at build time: (C_map (6, 6), acceleration PSD (6,), velocity
    /// prior mean (6,) and variance (6,), held-out samples, their median inliers n̄).
    #[getter]
    #[allow(clippy::type_complexity)]
    fn map_noise<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Vec<f64>, Vec<f64>, Vec<f64>, usize, f64)> {
        let n = &self.inner.noise;
        let list = |v: &nalgebra::Vector6<f64>| v.iter().copied().collect();
        let (mean, variance) = (list(&n.velocity_prior.mean), list(&n.velocity_prior.variance));
        let c = square(py, &n.pose_covariance)?;
        Ok((c, list(&n.acceleration_psd), mean, variance, n.holdout_samples, n.holdout_inliers))
    }

    /// The map noise at a pose's support and distance from the keyframes:
    /// (1 − w) C_near + w C_map·max(1, n̄/inliers) (the core's `MapNoise::covariance_at`).
    #[pyo3(signature = (inliers, novelty=None))]
    fn map_noise_at<'py>(
        &self,
        py: Python<'py>,
        inliers: Option<usize>,
        novelty: Option<f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        if novelty.is_some_and(|v| !(v.is_finite() && v >= 0.0)) {
            return Err(invalid("novelty", "must be finite and ≥ 0"));
        }
        square(py, &self.inner.noise.covariance_at(inliers, novelty))
    }

    /// The near regime of the map noise: (C_near (6, 6), ν₀ spacing, ν₁ held-out distance), or None.
    #[getter]
    #[allow(clippy::type_complexity)]
    fn map_noise_near<'py>(&self, py: Python<'py>) -> PyResult<Option<(Bound<'py, PyArray2<f64>>, f64, f64)>> {
        self.inner.noise.near.map(|n| Ok((square(py, &n.covariance)?, n.spacing, n.holdout_distance))).transpose()
    }

    /// The build's held-out re-localizations: (keyframes, δ (n, 6), C_G (n, 6, 6), inliers, used).
    #[getter]
    #[allow(clippy::type_complexity)]
    fn map_noise_holdout<'py>(
        &self,
        py: Python<'py>,
    ) -> (Vec<usize>, Bound<'py, PyArray2<f64>>, Bound<'py, numpy::PyArray3<f64>>, Vec<usize>, Vec<bool>, Vec<f64>)
    {
        let h = &self.inner.noise.holdout;
        let deltas: Vec<_> = h.iter().map(|s| s.delta.transpose()).collect();
        let covs: Vec<_> = h.iter().map(|s| s.covariance).collect();
        let keyframes = h.iter().map(|s| s.keyframe).collect();
        let inliers = h.iter().map(|s| s.inliers).collect();
        let used = h.iter().map(|s| s.used).collect();
        let novelty = h.iter().map(|s| s.novelty).collect();
        (keyframes, matrices_to_array(py, &deltas), matrices_to_array3(py, &covs), inliers, used, novelty)
    }

    /// Where C_map came from and the support it was measured at, in words (the core's wording).
    #[getter]
    fn map_noise_description(&self) -> String {
        self.inner.noise.description()
    }

    /// Per axis, whether the build's held-out samples resolve C_map (None: too few, or a loaded map).
    #[getter]
    fn map_noise_resolved(&self) -> Option<Vec<bool>> {
        self.inner.noise.resolved_axes().map(|r| r.to_vec())
    }

    /// Writes the map to `path` atomically; `frontend` is the caller's settings (JSON object text).
    fn save(&self, py: Python<'_>, path: PathBuf, frontend: &str) -> PyResult<()> {
        py.detach(|| self.inner.save(&path, frontend)).map_err(to_py_err)
    }

    /// The bytes `save` writes, in memory; `frontend` as for `save`.
    fn to_bytes<'py>(&self, py: Python<'py>, frontend: &str) -> PyResult<Bound<'py, PyBytes>> {
        let bytes = py.detach(|| self.inner.to_bytes(frontend)).map_err(to_py_err)?;
        Ok(PyBytes::new(py, &bytes))
    }

    /// Reads a map from the bytes of a saved one: the map and its frontend settings (JSON text).
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<(Self, String)> {
        let (map, header) = py.detach(|| CoreMap::from_bytes(data)).map_err(to_py_err)?;
        Ok((Self { inner: Arc::new(map) }, header.frontend.to_string()))
    }

    /// Reads a map written by `save`: the map and its frontend settings (JSON text).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<(Self, String)> {
        let (map, header) = py.detach(|| CoreMap::load(&path)).map_err(to_py_err)?;
        Ok((Self { inner: Arc::new(map) }, header.frontend.to_string()))
    }
}

/// The localization of one frame; see `geoloc.localizer.LocalizationResult`.
#[pyclass(module = "geoloc._core", frozen, name = "Localization")]
pub struct Localization {
    inner: CoreLocalization,
    /// The camera pose (world_from_cam) and its covariance, when the map's labels sit on
    /// another frame.
    camera: Option<geoloc_core::localizer::Estimate>,
}

/// A square matrix as an (n, n) float64 array.
fn square<'py, const N: usize>(
    py: Python<'py>,
    m: &nalgebra::SMatrix<f64, N, N>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    matrices_to_array(py, &[*m]).reshape([N, N])
}

#[pymethods]
impl Localization {
    /// The camera's own pose world_from_cam (4, 4) — differs from `pose` when the map
    /// adjusted its labels and found a label-to-camera offset — or None when lost.
    #[getter]
    fn camera_pose<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        self.camera.or(self.inner.estimate).map(|e| square(py, &e.world_from_cam.matrix())).transpose()
    }

    /// The camera pose's 6×6 covariance (right perturbation, translation first):
    /// Ad_{X⁻¹} C Ad_{X⁻¹}ᵀ + Σ_X for the labels' `covariance` C and the label-to-camera
    /// offset X with its covariance Σ_X; `covariance` when the labels are the camera's; None
    /// when lost.
    #[getter]
    fn camera_covariance<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        self.camera.or(self.inner.estimate).map(|e| square::<6>(py, &e.covariance)).transpose()
    }

    /// The pose in the labels' convention (world_from_cam when the labels are the camera's)
    /// (4, 4), or None when lost.
    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        self.inner.estimate.map(|e| square(py, &e.world_from_cam.matrix())).transpose()
    }

    /// 6×6 covariance (right perturbation, translation first), or None when lost.
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<f64>>>> {
        self.inner.estimate.map(|e| square::<6>(py, &e.covariance)).transpose()
    }

    /// "geometric", "fused", "motion" or "lost".
    #[getter]
    fn source(&self) -> &'static str {
        self.inner.source.as_str()
    }

    /// Why (e.g. why the geometric pose was not used).
    #[getter]
    fn reason(&self) -> &str {
        &self.inner.reason
    }

    /// The keyframe whose group gave the geometric pose (the retrieved one, or the last
    /// frame's when the paper's locator tracked).
    #[getter]
    fn keyframe(&self) -> usize {
        self.inner.keyframe
    }

    /// PnP inliers (0 without a geometric pose).
    #[getter]
    fn inliers(&self) -> usize {
        self.inner.inliers
    }

    /// The factor on the map's C_map inside `covariance`: w·max(1, n̄/n) (1 when lost).
    #[getter]
    fn map_noise_scale(&self) -> f64 {
        self.inner.map_noise_scale
    }

    /// ν: the pose's distance from the nearest keyframe (10 cm or 5° = 1), None when lost.
    #[getter]
    fn novelty(&self) -> Option<f64> {
        self.inner.novelty
    }

    /// Milliseconds per stage: retrieval, keyframes, map_points, matching, pnp, motion_fusion, total.
    #[getter]
    fn timings_ms<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let out = PyDict::new(py);
        for (stage, ms) in self.inner.timings.stages() {
            out.set_item(stage, ms)?;
        }
        Ok(out)
    }

    fn __repr__(&self) -> String {
        format!(
            "Localization(source={:?}, reason={:?}, keyframe={})",
            self.source(),
            self.inner.reason,
            self.inner.keyframe
        )
    }
}

/// The per-frame localizer with its motion history.
#[pyclass(module = "geoloc._core", frozen)]
pub struct FeatureLocalizer {
    inner: Mutex<CoreLocalizer>,
    /// The map (results are returned in its labels' convention).
    map: Arc<CoreMap>,
    /// The options it was created with.
    options: LocalizerOptions,
}

#[pymethods]
impl FeatureLocalizer {
    /// A localizer on `map`; `options` holds the localizer options the caller set (see
    /// `localizer_defaults()`), everything else is the core's default.
    #[new]
    #[pyo3(signature = (map, *, options=None))]
    fn new(py: Python<'_>, map: &FeatureMap, options: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        let options = localizer_options(options)?;
        let inner = py.detach(|| CoreLocalizer::new(Arc::clone(&map.inner), options)).map_err(to_py_err)?;
        Ok(Self { inner: Mutex::new(inner), map: Arc::clone(&map.inner), options })
    }

    /// The localizer's user-facing options (the keys of `localizer_defaults()`).
    #[getter]
    fn options<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        localizer_dict(py, &self.options)
    }

    /// Localizes one frame (keypoints (N, 2) undistorted pixels, descriptors (N, W), optional
    /// per-keypoint pixel σ (N,)).
    #[pyo3(signature = (timestamp, keypoints, descriptors, global_descriptor=None, pixel_sigmas=None))]
    fn localize(
        &self,
        py: Python<'_>,
        timestamp: f64,
        keypoints: PyReadonlyArray2<'_, f64>,
        descriptors: Bound<'_, PyAny>,
        global_descriptor: Option<Bound<'_, PyAny>>,
        pixel_sigmas: Option<Bound<'_, PyAny>>,
    ) -> PyResult<Localization> {
        let kps = self::keypoints("keypoints", &keypoints)?;
        let borrowed = BorrowedDescriptors::extract(&descriptors, "descriptors")?;
        let global = optional_vector::<f32>(global_descriptor.as_ref(), "global_descriptor", "float32", "D")?;
        let sigmas = optional_vector::<f64>(pixel_sigmas.as_ref(), "pixel_sigmas", "float64", "N")?;
        let (global, sigmas) =
            (slice_of(global.as_ref(), "global_descriptor")?, slice_of(sigmas.as_ref(), "pixel_sigmas")?);
        let frame = Frame {
            timestamp,
            keypoints: &kps,
            descriptors: borrowed.view("descriptors")?,
            global,
            pixel_sigmas: sigmas,
        };
        let inner = py
            .detach(|| self.inner.lock().ok().map(|mut loc| loc.localize(&frame)))
            .ok_or_else(|| invalid("localizer", "a previous call panicked; create a new localizer"))?
            .map_err(to_py_err)?;
        let camera = self.map.to_camera_convention(inner.clone()).estimate;
        let inner = self.map.to_label_convention(inner);
        Ok(Localization { camera: self.map.labels.as_ref().and(camera), inner })
    }

    fn reset(&self, py: Python<'_>) -> PyResult<()> {
        // waits for a localize of another thread without the GIL, as localize itself does:
        // holding it here stalled every Python thread for the length of that frame
        py.detach(|| self.inner.lock().ok().map(|mut loc| loc.reset()))
            .ok_or_else(|| invalid("localizer", "a previous call panicked; create a new localizer"))
    }
}

/// Registers the classes on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<FeatureMap>()?;
    m.add_class::<Localization>()?;
    m.add_class::<FeatureLocalizer>()
}
