//! Bindings of `geoloc_core::{keyframes, motion, fusion}`.

use geoloc_core::fusion::{Gate, fuse as core_fuse};
use geoloc_core::keyframes::{KeyframeOptions, keyframe_score as core_score, select_keyframes as core_select};
use geoloc_core::motion::{VelocityPrior, motion_predict_with_prior as core_motion_predict};
use nalgebra::Vector6;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use crate::convert::{count_usize, matrices, matrix_to_array, one_matrix, one_pose, poses};
use crate::errors::{invalid, to_py_err};

/// The keyframe options from keyword arguments (defaults: the paper's), checked by the core.
#[allow(clippy::too_many_arguments)]
fn options(
    n: Option<&Bound<'_, PyAny>>,
    window: Option<&Bound<'_, PyAny>>,
    d_m: Option<f64>,
    ell: Option<f64>,
    alpha_m: Option<f64>,
    min_score: Option<f64>,
) -> PyResult<KeyframeOptions> {
    let d = KeyframeOptions::default();
    let options = KeyframeOptions {
        n: n.map_or(Ok(d.n), |v| count_usize("n", v))?,
        window: window.map_or(Ok(d.window), |v| count_usize("window", v))?,
        d_m: d_m.unwrap_or(d.d_m),
        ell: ell.unwrap_or(d.ell),
        alpha_m_rad: alpha_m.unwrap_or(d.alpha_m_rad),
        min_score: min_score.unwrap_or(d.min_score),
    };
    options.check().map_err(to_py_err)?;
    Ok(options)
}

/// s(T₁, T₂) for each pair of rows (N, 16) × (N, 16) → (N,).
#[pyfunction]
#[pyo3(signature = (pose1, pose2, *, d_m=None, ell=None, alpha_m=None))]
pub fn keyframe_score<'py>(
    py: Python<'py>,
    pose1: PyReadonlyArray2<'py, f64>,
    pose2: PyReadonlyArray2<'py, f64>,
    d_m: Option<f64>,
    ell: Option<f64>,
    alpha_m: Option<f64>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let o = options(None, None, d_m, ell, alpha_m, None)?;
    let (a, b) = (poses("T1", &pose1)?, poses("T2", &pose2)?);
    if a.len() != b.len() {
        return Err(invalid("T2", format!("has {} poses but T1 has {}", b.len(), a.len())));
    }
    let scores: Vec<f64> = a.iter().zip(&b).map(|(x, y)| core_score(x, y, o.d_m, o.ell, o.alpha_m_rad)).collect();
    Ok(scores.into_pyarray(py))
}

/// The keyframe group around `k`.
#[pyfunction]
#[pyo3(signature = (poses_wc, k, *, n=None, window=None, d_m=None, ell=None, alpha_m=None, min_score=None))]
#[allow(clippy::too_many_arguments)]
pub fn select_keyframes<'py>(
    py: Python<'py>,
    poses_wc: PyReadonlyArray2<'py, f64>,
    k: &Bound<'py, PyAny>,
    n: Option<Bound<'py, PyAny>>,
    window: Option<Bound<'py, PyAny>>,
    d_m: Option<f64>,
    ell: Option<f64>,
    alpha_m: Option<f64>,
    min_score: Option<f64>,
) -> PyResult<Bound<'py, PyArray1<u64>>> {
    let options = options(n.as_ref(), window.as_ref(), d_m, ell, alpha_m, min_score)?;
    let p = poses("poses", &poses_wc)?;
    let group = core_select(&p, count_usize("k", k)?, &options).map_err(to_py_err)?;
    Ok(group.into_iter().map(|i| i as u64).collect::<Vec<_>>().into_pyarray(py))
}

/// Getters shared by the two pose estimates (pose, covariance and the solve's report).
macro_rules! pose_estimate_methods {
    ($class:ident { $($extra:tt)* }) => {
        #[pymethods]
        impl $class {
            $($extra)*

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
            /// Gauss–Newton iterations (0 when no solve ran).
            #[getter]
            fn iterations(&self) -> usize {
                self.inner.report.map_or(0, |r| r.iterations)
            }
            /// Why the solve stopped (None when no solve ran).
            #[getter]
            fn termination(&self) -> Option<&'static str> {
                self.inner.report.map(|r| r.termination.as_str())
            }
        }
    };
}

/// A constant-velocity prediction (see `geoloc.motion.motion_predict`).
#[pyclass(module = "geoloc._core", frozen)]
pub struct MotionPrediction {
    inner: geoloc_core::motion::MotionPrediction,
}
pose_estimate_methods!(MotionPrediction {
    /// (6,) the fitted body velocity (v, ω) per second.
    #[getter]
    fn velocity<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.details.velocity.as_slice().to_vec().into_pyarray(py)
    }
    /// RMS of the fit residuals.
    #[getter]
    fn rms_residual(&self) -> f64 {
        self.inner.details.rms_residual
    }
});

/// A gated fusion (see `geoloc.fusion.fuse`).
#[pyclass(module = "geoloc._core", frozen)]
pub struct FusionResult {
    inner: geoloc_core::fusion::Fusion,
}
pose_estimate_methods!(FusionResult {
    /// "fused" or "motion" (the geometric pose failed the gate).
    #[getter]
    fn source(&self) -> &'static str {
        self.inner.details.as_str()
    }
});

/// Constant-velocity prediction at `t_query`, plus the process noise of white body
/// acceleration of PSD `acceleration_psd` (6,) (zero: none), with the velocity prior
/// N(`velocity_mean`, diag(`velocity_variance`)) (each (6,); variance zero: none).
#[pyfunction]
#[pyo3(signature = (poses_wc, timestamps, t_query, *, covariances=None, acceleration_psd=None, velocity_mean=None, velocity_variance=None))]
#[allow(clippy::too_many_arguments)]
pub fn motion_predict(
    py: Python<'_>,
    poses_wc: PyReadonlyArray2<'_, f64>,
    timestamps: PyReadonlyArray1<'_, f64>,
    t_query: f64,
    covariances: Option<PyReadonlyArray2<'_, f64>>,
    acceleration_psd: Option<PyReadonlyArray1<'_, f64>>,
    velocity_mean: Option<PyReadonlyArray1<'_, f64>>,
    velocity_variance: Option<PyReadonlyArray1<'_, f64>>,
) -> PyResult<MotionPrediction> {
    let p = poses("poses", &poses_wc)?;
    let t = timestamps.as_slice().map_err(|_| invalid("timestamps", "must be contiguous"))?;
    let c = covariances.as_ref().map(|c| matrices::<6, 6, 36>("covariances", c)).transpose()?;
    let six = |name: &str, v: &Option<PyReadonlyArray1<'_, f64>>| match v {
        Some(v) => match v.as_slice() {
            Ok(s) if s.len() == 6 => Ok(Vector6::from_column_slice(s)),
            _ => Err(invalid(name, "must be 6 contiguous values")),
        },
        None => Ok(Vector6::zeros()),
    };
    let q = six("acceleration_psd", &acceleration_psd)?;
    let prior = VelocityPrior {
        mean: six("velocity_mean", &velocity_mean)?,
        variance: six("velocity_variance", &velocity_variance)?,
    };
    let inner = py.detach(|| core_motion_predict(&p, t, t_query, c.as_deref(), &q, &prior)).map_err(to_py_err)?;
    Ok(MotionPrediction { inner })
}

/// Gate and fuse one motion prediction with one geometric pose.
#[pyfunction]
#[pyo3(signature = (pose_m, cov_m, pose_g, cov_g, *, gate_sigma=3.0, gate="isometric"))]
pub fn fuse(
    pose_m: PyReadonlyArray2<'_, f64>,
    cov_m: PyReadonlyArray2<'_, f64>,
    pose_g: PyReadonlyArray2<'_, f64>,
    cov_g: PyReadonlyArray2<'_, f64>,
    gate_sigma: f64,
    gate: &str,
) -> PyResult<FusionResult> {
    let (pm, pg) = (one_pose("pose_m", &pose_m)?, one_pose("pose_g", &pose_g)?);
    let (cm, cg) = (one_matrix::<6>("cov_m", &cov_m)?, one_matrix::<6>("cov_g", &cov_g)?);
    let gate = gate.parse::<Gate>().map_err(to_py_err)?;
    let inner = core_fuse(&pm, &cm, &pg, &cg, gate_sigma, gate).map_err(to_py_err)?;
    Ok(FusionResult { inner })
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(keyframe_score, m)?)?;
    m.add_function(wrap_pyfunction!(select_keyframes, m)?)?;
    m.add_function(wrap_pyfunction!(motion_predict, m)?)?;
    m.add_function(wrap_pyfunction!(fuse, m)?)?;
    m.add_class::<MotionPrediction>()?;
    m.add_class::<FusionResult>()?;
    Ok(())
}
