//! Bindings of `geoloc_core::{map, localizer}` at the level of features (keypoints and
//! descriptors); images and feature extraction live in Python.

use std::sync::{Arc, Mutex};

use geoloc_core::camera::Camera;
use geoloc_core::localizer::{Frame, Localizer as CoreLocalizer, LocalizerOptions, Source};
use geoloc_core::map::{Keyframe, Map as CoreMap, RetrievalKind};
use nalgebra::Vector2;
use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{BorrowedDescriptors, matrices, matrices_to_array, poses, rows};
use crate::errors::{invalid, to_py_err};

fn keypoints(name: &str, a: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Vector2<f64>>> {
    Ok(rows::<2>(name, a)?.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect())
}

/// A map of keyframes (features level).
#[pyclass(module = "geoloc._core", frozen)]
pub struct FeatureMap {
    inner: Arc<CoreMap>,
}

#[pymethods]
impl FeatureMap {
    #[new]
    #[pyo3(signature = (intrinsics, poses_wc, keypoints_list, descriptors_list, global_descriptors, pose_covariances, retrieval, branching, depth, seed))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        intrinsics: (f64, f64, f64, f64),
        poses_wc: PyReadonlyArray2<'_, f64>,
        keypoints_list: Vec<PyReadonlyArray2<'_, f64>>,
        descriptors_list: Vec<Bound<'_, PyAny>>,
        global_descriptors: Option<PyReadonlyArray2<'_, f32>>,
        pose_covariances: Option<PyReadonlyArray2<'_, f64>>,
        retrieval: &str,
        branching: usize,
        depth: usize,
        seed: u64,
    ) -> PyResult<Self> {
        let (fx, fy, cx, cy) = intrinsics;
        let camera = Camera::new(fx, fy, cx, cy).map_err(to_py_err)?;
        let poses = poses("poses", &poses_wc)?;
        if keypoints_list.len() != poses.len() || descriptors_list.len() != poses.len() {
            return Err(invalid(
                "keypoints",
                format!("need one keypoint and one descriptor array per pose ({})", poses.len()),
            ));
        }
        let globals: Option<(Vec<f32>, usize)> = global_descriptors
            .as_ref()
            .map(|g| {
                Ok::<_, PyErr>((
                    g.as_slice().map_err(|_| invalid("global_descriptors", "must be C-contiguous"))?.to_vec(),
                    g.shape()[1],
                ))
            })
            .transpose()?;
        let mut keyframes = Vec::with_capacity(poses.len());
        for (i, pose) in poses.iter().enumerate() {
            keyframes.push(Keyframe {
                world_from_cam: *pose,
                keypoints: keypoints(&format!("keypoints[{i}]"), &keypoints_list[i])?,
                descriptors: {
                    let name = format!("descriptors[{i}]");
                    BorrowedDescriptors::extract(&descriptors_list[i], &name)?.to_owned_set(&name)?
                },
                global: globals.as_ref().map(|(g, d)| g[i * d..(i + 1) * d].to_vec()),
            });
        }
        let covs = pose_covariances.as_ref().map(|c| matrices::<6, 6, 36>("pose_covariances", c)).transpose()?;
        let kind = match retrieval {
            "bow" => RetrievalKind::Bow { branching, depth },
            "global" => RetrievalKind::Global,
            other => return Err(invalid("retrieval", format!("expected \"bow\" or \"global\", got {other:?}"))),
        };
        let map = py.detach(|| CoreMap::build(camera, keyframes, covs, kind, seed)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(map) })
    }

    fn __len__(&self) -> usize {
        self.inner.keyframes.len()
    }
}

/// The per-frame localizer with its motion history.
#[pyclass(module = "geoloc._core", frozen)]
pub struct FeatureLocalizer {
    inner: Mutex<CoreLocalizer>,
}

#[pymethods]
impl FeatureLocalizer {
    #[new]
    fn new(map: &FeatureMap, pixel_sigma: f64, max_residual: f64, gate_sigma: f64, history: usize) -> PyResult<Self> {
        let mut options = LocalizerOptions { gate_sigma, history, ..LocalizerOptions::default() };
        options.pnp.pixel_sigma = pixel_sigma;
        options.pnp.max_residual_px = max_residual;
        options.triangulation.pixel_sigma = pixel_sigma;
        options.triangulation.max_residual_px = max_residual;
        Ok(Self { inner: Mutex::new(CoreLocalizer::new(Arc::clone(&map.inner), options)) })
    }

    /// dict(pose (1, 16) | None, covariance (1, 36) | None, source, reason, keyframe, inliers, timings)
    fn localize<'py>(
        &self,
        py: Python<'py>,
        timestamp: f64,
        keypoints_px: PyReadonlyArray2<'py, f64>,
        descriptors: Bound<'py, PyAny>,
        global_descriptor: Option<PyReadonlyArray1<'py, f32>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let kps = keypoints("keypoints", &keypoints_px)?;
        let borrowed = BorrowedDescriptors::extract(&descriptors, "descriptors")?;
        let global = global_descriptor
            .as_ref()
            .map(|g| g.as_slice().map_err(|_| invalid("global", "must be contiguous")))
            .transpose()?;
        let view = borrowed.view("descriptors")?;
        let frame = Frame { timestamp, keypoints: &kps, descriptors: view, global };
        let result = py
            .detach(|| self.inner.lock().ok().map(|mut loc| loc.localize(&frame)))
            .ok_or_else(|| invalid("localizer", "a previous call panicked; create a new localizer"))?
            .map_err(to_py_err)?;
        let out = PyDict::new(py);
        out.set_item("pose", result.world_from_cam.map(|p| matrices_to_array(py, &[p.matrix()])))?;
        out.set_item("covariance", result.covariance.map(|c| matrices_to_array(py, &[c])))?;
        out.set_item(
            "source",
            match result.source {
                Source::Geometric => "geometric",
                Source::Fused => "fused",
                Source::Motion => "motion",
                Source::Lost => "lost",
            },
        )?;
        out.set_item("reason", result.reason)?;
        out.set_item("keyframe", result.keyframe)?;
        out.set_item("inliers", result.inliers)?;
        let t = result.timings;
        let timings = PyDict::new(py);
        for (k, v) in [
            ("retrieval", t.retrieval_ms),
            ("keyframes", t.keyframes_ms),
            ("map_points", t.map_points_ms),
            ("matching", t.matching_ms),
            ("pnp", t.pnp_ms),
            ("motion_fusion", t.motion_fusion_ms),
            ("total", t.total_ms),
        ] {
            timings.set_item(k, v)?;
        }
        out.set_item("timings_ms", timings)?;
        Ok(out)
    }

    fn reset(&self) -> PyResult<()> {
        self.inner.lock().map_err(|_| invalid("localizer", "a previous call panicked"))?.reset();
        Ok(())
    }
}

/// Registers the classes on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<FeatureMap>()?;
    m.add_class::<FeatureLocalizer>()
}
