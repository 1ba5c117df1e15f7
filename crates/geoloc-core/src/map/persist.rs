//! The map as a `.geoloc` file: which arrays and header fields hold what, and the checks that
//! make loading all-or-nothing.
//!
//! Arrays (row-major, see [`super::file`] for the container):
//!
//! | name | dtype, shape | content |
//! |---|---|---|
//! | `keyframes.world_from_cam` | f64 (K, 4, 4) | pose labels, camera-to-world |
//! | `keyframes.keypoint_offsets` | i64 (K + 1) | keyframe k's keypoints are rows `offsets[k]..offsets[k+1]` |
//! | `keypoints` | f64 (N, 2) | undistorted pixels (corrected by the self-calibration, if any) |
//! | `descriptors` | u8 (N, W) or f32 (N, W) | local descriptors (binary or float) |
//! | `keyframes.global_descriptors` | f32 (K, D) | only for global-descriptor or fused retrieval |
//! | `keyframes.pose_covariances` | f64 (K, 6, 6) | optional; right perturbation, translation first; adjusted: relative to the labels' frame |
//! | `vocabulary.node_offsets` | i64 (nodes + 1) | BoW or fused only: see [`crate::bow::VocabularyArrays`] |
//! | `vocabulary.centres` | u8 or f32 (R, W) | BoW or fused only: the tree's cluster centres |
//! | `vocabulary.children` | i64 (R) | BoW or fused only: child node index, or −word − 1 |
//! | `keyframes.labels` | f64 (K, 4, 4) | with `labels` in the header: the pose labels as given (world_from_label); `keyframes.world_from_cam` then holds the adjusted camera poses |
//! | `keyframes.label_corrections` | f64 (K, 7) | with `labels`: per keyframe log(L⁻¹B) (6, translation first) and its significance |
//! | `model.points` | f64 (P, 3) | optional 3D model ([`super::SceneModel`]): world points |
//! | `model.point_covariances` | f64 (P, 3, 3) | model: Σ_X per point |
//! | `model.descriptors` | u8 or f32 (P, W) | model: representative descriptor per point |
//! | `model.keypoint_points` | i64 (N) | model: point id of each keypoint, −1 for none |
//!
//! Maps written before the model existed have no `model` header field and no `model.*`
//! arrays: they load with `model` None (the model locator then builds it when it starts).
//!
//! The header ([`MapHeader`], JSON) holds the camera, the descriptor kind and width, the
//! retrieval method and its parameters, and `frontend`: a JSON object the caller owns (the
//! Python package records its feature extractor and descriptor model there; `geoloc-rs info`
//! prints it). The BoW database is rebuilt from the stored vocabulary and the keyframes'
//! descriptors on load (deterministic, and cheaper than storing the inverted file); the
//! vocabulary itself is stored, never retrained.

use std::path::Path;

use nalgebra::{Matrix3, Matrix4, Matrix6, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::file::{self, MapFile, Tensor, TensorData};
use super::{GroupMatches, Keyframe, LabelAdjustment, Map, MapNoise, Retrieval, SceneModel};
use crate::bow::{BowDatabase, Vocabulary, VocabularyArrays};
use crate::camera::{Camera, Distortion};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::matching::DescriptorSet;
use crate::motion::VelocityPrior;
use crate::optim::covariance::{check_covariance, check_covariances};
use crate::retrieval::DescriptorIndex;
use crate::selfcal::{IntrinsicsCorrection, SelfCalibration};

/// The intrinsics as stored.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraHeader {
    /// Focal length x (px).
    pub fx: f64,
    /// Focal length y (px).
    pub fy: f64,
    /// Principal point x (px).
    pub cx: f64,
    /// Principal point y (px).
    pub cy: f64,
}

impl CameraHeader {
    /// The stored form of `camera`.
    pub fn from_camera(camera: &Camera) -> Self {
        Self { fx: camera.fx, fy: camera.fy, cx: camera.cx, cy: camera.cy }
    }

    /// The camera, checked; a `Format` error prefixed with `what` otherwise.
    fn to_camera(self, what: &str) -> Result<Camera> {
        Camera::new(self.fx, self.fy, self.cx, self.cy).map_err(|e| format_error(format!("{what}: {e}")))
    }
}

/// How the map retrieves keyframes, as stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum RetrievalHeader {
    /// Bag of words with a stored vocabulary.
    Bow {
        /// Number of words.
        words: usize,
    },
    /// Nearest global descriptor.
    Global {
        /// Descriptor length.
        dim: usize,
    },
    /// Both, combined by verification ([`super::fused_retrieval`]).
    Fused {
        /// Number of words.
        words: usize,
        /// Descriptor length.
        dim: usize,
    },
}

/// The JSON header of a map file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapHeader {
    /// The intrinsics shared by keyframes and queries.
    pub camera: CameraHeader,
    /// Number of keyframes.
    pub keyframes: usize,
    /// Total number of keypoints.
    pub keypoints: usize,
    /// `"binary"` (u8, Hamming) or `"float"` (f32, L2).
    pub descriptor_kind: String,
    /// Bytes (binary) or values (float) per descriptor.
    pub descriptor_width: usize,
    /// The retrieval method and its size.
    pub retrieval: RetrievalHeader,
    /// Whether pose-label covariances are stored.
    pub pose_covariances: bool,
    /// The caller's own settings (a JSON object), e.g. the feature extractor.
    pub frontend: serde_json::Value,
    /// What was estimated about the map's noise at build time; absent in maps written
    /// before it existed (read as zero: no map-frame noise, no process noise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map_noise: Option<NoiseHeader>,
    /// The 3D model's size, when the map stores one (absent in maps without a model).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<ModelHeader>,
    /// The camera estimated from the keyframes, when it was tried (absent otherwise and in
    /// maps written before it existed). With a correction, `keypoints` are stored corrected.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub self_calibration: Option<SelfCalibrationHeader>,
    /// The labels' adjustment, when the map corrected its labels (absent otherwise and in
    /// maps written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<LabelsHeader>,
    /// The paper locator's prepared keyframe-pair matches ([`GroupMatches`]), when the map
    /// holds them (absent otherwise and in maps written before them: the localizer matches).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group_matches: Option<GroupMatchesHeader>,
}

/// [`GroupMatches`] in the header: the options they were made with (the groups and rows
/// are arrays).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupMatchesHeader {
    /// [`super::group_matches::fingerprint`] of the options.
    pub options: String,
}

/// [`LabelAdjustment`] in the header (the per-keyframe parts are arrays).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LabelsHeader {
    /// X = label_from_cam, row-major 4×4 (16 values).
    pub label_from_cam: Vec<f64>,
    /// Covariance of X, row-major (36 values).
    pub label_from_cam_covariance: Vec<f64>,
    /// The labels' σ used: translation (m), rotation (rad).
    pub label_sigma: [f64; 2],
    /// RMS reprojection error with the labels and after the adjustment (px).
    pub rms_px: [f64; 2],
    /// Observations used and rejected.
    pub observations: [usize; 2],
    /// τ of the label corrections (translation, rotation; keyframes).
    #[serde(default = "no_correlation")]
    pub correlation_keyframes: [f64; 2],
    /// Whether the map uses the adjustment (false: the images agreed with the labels).
    #[serde(default = "applied")]
    pub applied: bool,
    /// [`LabelAdjustment::pose_variance`] (6 values; absent in files saved before it: zero).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pose_variance: Vec<f64>,
    /// [`LabelAdjustment::breaks`] (absent in files saved before them, or when none).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub breaks: Vec<super::label_breaks::LabelBreak>,
    /// [`LabelAdjustment::replaced`] (absent likewise).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub replaced: Vec<super::label_breaks::LabelSegment>,
    /// [`LabelAdjustment::loops`] (absent likewise).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub loops: Vec<super::label_loops::LabelLoop>,
}

fn applied() -> bool {
    true
}

fn no_correlation() -> [f64; 2] {
    [1.0, 1.0]
}

impl LabelsHeader {
    fn from_labels(l: &LabelAdjustment) -> Self {
        Self {
            label_from_cam: row_major(&l.offset.matrix()),
            label_from_cam_covariance: l.offset_covariance.transpose().iter().copied().collect(),
            label_sigma: [l.label_sigma.translation_m, l.label_sigma.rotation_rad],
            rms_px: [l.rms_px.0, l.rms_px.1],
            observations: [l.observations.0, l.observations.1],
            correlation_keyframes: [l.correlation_keyframes.0, l.correlation_keyframes.1],
            applied: l.applied,
            pose_variance: l.pose_variance.iter().copied().collect(),
            breaks: l.breaks.clone(),
            replaced: l.replaced.clone(),
            loops: l.loops.clone(),
        }
    }

    fn to_labels(&self, file: &MapFile, k: usize) -> Result<LabelAdjustment> {
        if self.label_from_cam.len() != 16 || self.label_from_cam_covariance.len() != 36 {
            return Err(format_error("labels: expected 16 label_from_cam and 36 covariance values"));
        }
        let offset = SE3::from_matrix(&Matrix4::from_row_slice(&self.label_from_cam))
            .map_err(|e| format_error(format!("labels.label_from_cam is not a rigid transform: {e}")))?;
        let offset_covariance = Matrix6::from_row_slice(&self.label_from_cam_covariance);
        check_covariance("labels.label_from_cam_covariance", &offset_covariance).map_err(as_format)?;
        let [t, r] = self.label_sigma;
        if !(t.is_finite() && t > 0.0 && r.is_finite() && r > 0.0) {
            return Err(format_error("labels.label_sigma: must be finite and > 0"));
        }
        let pose_variance = match self.pose_variance.len() {
            0 => Vector6::zeros(),
            6 => Vector6::from_column_slice(&self.pose_variance),
            n => return Err(format_error(format!("labels.pose_variance: expected 6 values, got {n}"))),
        };
        if pose_variance.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(format_error("labels.pose_variance: must be finite and ≥ 0"));
        }
        let labels = read_pose_array(file, "keyframes.labels", k)?;
        let values = f64_array(file, "keyframes.label_corrections", &[k, 7])?;
        if values.iter().any(|v| !v.is_finite()) {
            return Err(format_error("keyframes.label_corrections: holds a non-finite value"));
        }
        let corrections = values.chunks_exact(7).map(|c| Vector6::from_column_slice(&c[..6])).collect();
        let significance = values.chunks_exact(7).map(|c| c[6]).collect();
        Ok(LabelAdjustment {
            labels,
            offset,
            offset_covariance,
            corrections,
            significance,
            pose_variance,
            label_sigma: crate::adjust::LabelSigma { translation_m: t, rotation_rad: r },
            correlation_keyframes: (self.correlation_keyframes[0], self.correlation_keyframes[1]),
            rms_px: (self.rms_px[0], self.rms_px[1]),
            observations: (self.observations[0], self.observations[1]),
            applied: self.applied,
            breaks: self.breaks.clone(),
            replaced: self.replaced.clone(),
            loops: self.loops.clone(),
        })
    }
}

fn label_tensors(l: &LabelAdjustment) -> Result<Vec<(String, Tensor)>> {
    let k = l.labels.len();
    let poses = l.labels.iter().flat_map(|p| row_major(&p.matrix())).collect();
    let corrections = l
        .corrections
        .iter()
        .zip(&l.significance)
        .flat_map(|(e, m)| e.iter().copied().chain(std::iter::once(if m.is_finite() { *m } else { f64::MAX })))
        .collect();
    Ok(vec![
        tensor("keyframes.labels", vec![k, 4, 4], TensorData::F64(poses))?,
        tensor("keyframes.label_corrections", vec![k, 7], TensorData::F64(corrections))?,
    ])
}

/// [`SelfCalibration`] in the header: the estimated camera (absent when there is no
/// correction), why, and the residuals before and after.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelfCalibrationHeader {
    /// K′ = (f_x′, f_y′, c_x′, c_y′) and the distortion (k1, k2, p1, p2, k3), if estimated.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraHeader>,
    /// OpenCV's order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<Vec<f64>>,
    /// "ok", or why there is no correction.
    pub reason: String,
    /// RMS pixel residual of the tracks under the nominal camera (null without tracks).
    pub rms_before_px: Option<f64>,
    /// ... under the estimated one (null without one).
    pub rms_after_px: Option<f64>,
    /// Median pixel residual before (null without tracks).
    pub median_before_px: Option<f64>,
    /// ... after (null without one).
    pub median_after_px: Option<f64>,
    /// Track observations used.
    pub observations: usize,
    /// Points they observe.
    pub points: usize,
    /// RMS of the correction's 1σ over the tracks' pixels (px; null when not computed).
    pub correction_sigma_px: Option<f64>,
}

impl SelfCalibrationHeader {
    /// The header object of a self-calibration.
    pub fn from_self_calibration(s: &SelfCalibration) -> Self {
        let finite = |v: f64| v.is_finite().then_some(v);
        Self {
            camera: s.correction.map(|c| CameraHeader::from_camera(&c.camera)),
            distortion: s.correction.map(|c| c.distortion.to_opencv().to_vec()),
            reason: s.reason.clone(),
            rms_before_px: finite(s.rms_before_px),
            rms_after_px: finite(s.rms_after_px),
            median_before_px: finite(s.median_before_px),
            median_after_px: finite(s.median_after_px),
            observations: s.observations,
            points: s.points,
            correction_sigma_px: finite(s.correction_sigma_px),
        }
    }

    /// Checks and converts: camera and distortion both or neither, a valid camera, five
    /// finite coefficients.
    fn to_self_calibration(&self) -> Result<SelfCalibration> {
        let correction = match (&self.camera, &self.distortion) {
            (None, None) => None,
            (Some(c), Some(d)) => {
                let camera = c.to_camera("self_calibration.camera")?;
                if d.len() != 5 {
                    return Err(format_error("self_calibration.distortion: expected 5 coefficients"));
                }
                let distortion = Distortion::from_opencv(d)
                    .map_err(|e| format_error(format!("self_calibration.distortion: {e}")))?;
                Some(IntrinsicsCorrection { camera, distortion })
            }
            _ => return Err(format_error("self_calibration: camera and distortion go together")),
        };
        Ok(SelfCalibration {
            correction,
            reason: self.reason.clone(),
            rms_before_px: self.rms_before_px.unwrap_or(f64::NAN),
            rms_after_px: self.rms_after_px.unwrap_or(f64::NAN),
            median_before_px: self.median_before_px.unwrap_or(f64::NAN),
            median_after_px: self.median_after_px.unwrap_or(f64::NAN),
            observations: self.observations,
            points: self.points,
            correction_sigma_px: self.correction_sigma_px.unwrap_or(f64::NAN),
            report: None,
        })
    }
}

/// The stored 3D model ([`SceneModel`]): its number of points.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelHeader {
    /// Number of points.
    pub points: usize,
}

/// [`MapNoise`] in the header: C_map row-major (36 values), q (6 values), the samples.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseHeader {
    /// C_map, row-major, translation first (m², rad²).
    pub pose_covariance: Vec<f64>,
    /// Acceleration power spectral density per twist axis.
    pub acceleration_psd: Vec<f64>,
    /// Mean body velocity per twist axis, the velocity prior's (6 values; absent in files
    /// saved before it, and when there is no prior).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub velocity_mean: Vec<f64>,
    /// Variance of the body velocity per twist axis (6 values; absent as `velocity_mean`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub velocity_variance: Vec<f64>,
    /// Held-out keyframes C_map was estimated from.
    pub holdout_samples: usize,
    /// n̄, their median PnP inliers ([`MapNoise::holdout_inliers`]; absent in files saved
    /// before it, and when C_map is the default: C_map then applies unscaled).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub holdout_inliers: f64,
    /// Per axis, whether the held-out samples resolve C_map (6 values; absent when they could
    /// not estimate it, and in files saved before it).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub resolved: Vec<bool>,
    /// The near regime ([`crate::map::NearNoise`]): C_near row-major (36 values), ν₀ and ν₁;
    /// absent without one (and in files saved before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub near: Option<NearHeader>,
}

/// [`crate::map::NearNoise`] in the header.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NearHeader {
    /// C_near, row-major (36 values).
    pub covariance: Vec<f64>,
    /// ν₀, the keyframes' median spacing.
    pub spacing: f64,
    /// ν₁, the held-out keyframes' least distance (> ν₀).
    pub holdout_distance: f64,
}

/// Whether n̄ is 0 (then not written).
fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl NoiseHeader {
    fn from_noise(n: &MapNoise) -> Option<Self> {
        (*n != MapNoise::default()).then(|| Self {
            pose_covariance: n.pose_covariance.transpose().iter().copied().collect(),
            acceleration_psd: n.acceleration_psd.iter().copied().collect(),
            velocity_mean: six_or_none(&n.velocity_prior, &n.velocity_prior.mean),
            velocity_variance: six_or_none(&n.velocity_prior, &n.velocity_prior.variance),
            holdout_samples: n.holdout_samples,
            holdout_inliers: n.holdout_inliers,
            resolved: n.resolved.map(|r| r.to_vec()).unwrap_or_default(),
            near: n.near.map(|near| NearHeader {
                covariance: near.covariance.transpose().iter().copied().collect(),
                spacing: near.spacing,
                holdout_distance: near.holdout_distance,
            }),
        })
    }

    /// Checks and converts: 36 + 6 finite values, C_map symmetric PSD, q ≥ 0, n̄ finite ≥ 0, a
    /// near regime within C_map and not all zero.
    fn to_noise(&self) -> Result<MapNoise> {
        if self.pose_covariance.len() != 36 || self.acceleration_psd.len() != 6 {
            return Err(format_error("map_noise: expected 36 pose_covariance and 6 acceleration_psd values"));
        }
        let c = Matrix6::from_row_slice(&self.pose_covariance);
        check_covariance("map_noise.pose_covariance", &c).map_err(as_format)?;
        let q = Vector6::from_column_slice(&self.acceleration_psd);
        if q.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(format_error("map_noise.acceleration_psd: must be finite and ≥ 0"));
        }
        let velocity_prior = match (self.velocity_mean.len(), self.velocity_variance.len()) {
            (0, 0) => VelocityPrior::default(),
            (6, 6) => VelocityPrior {
                mean: Vector6::from_column_slice(&self.velocity_mean),
                variance: Vector6::from_column_slice(&self.velocity_variance),
            },
            (m, v) => {
                return Err(format_error(format!(
                    "map_noise: expected 6 velocity_mean and 6 velocity_variance values, got {m} and {v}"
                )));
            }
        };
        velocity_prior.check().map_err(|e| format_error(format!("map_noise.{e}")))?;
        if !(self.holdout_inliers.is_finite() && self.holdout_inliers >= 0.0) {
            return Err(format_error("map_noise.holdout_inliers: must be finite and ≥ 0"));
        }
        let resolved = match self.resolved.len() {
            0 => None,
            6 => Some(std::array::from_fn(|a| self.resolved[a])),
            n => return Err(format_error(format!("map_noise.resolved: expected 6 values, got {n}"))),
        };
        let near = self.near.as_ref().map(NearHeader::to_near).transpose()?;
        if let Some(n) = &near {
            // C_near is the keyframe poses' variance capped at C_map per axis, and a map whose
            // poses have none has no near regime
            if (0..6).any(|a| n.covariance[(a, a)] > c[(a, a)]) {
                return Err(format_error(
                    "map_noise.near.covariance: exceeds pose_covariance on an axis (C_near is capped at C_map)",
                ));
            }
            if (0..6).all(|a| n.covariance[(a, a)] <= 0.0) {
                return Err(format_error(
                    "map_noise.near.covariance: all zero (a map without pose variances has none)",
                ));
            }
        }
        Ok(MapNoise {
            pose_covariance: c,
            acceleration_psd: q,
            velocity_prior,
            holdout_samples: self.holdout_samples,
            holdout_inliers: self.holdout_inliers,
            holdout: vec![],
            resolved,
            near,
        })
    }
}

impl NearHeader {
    /// Checks and converts: 36 finite values of a symmetric PSD C_near, 0 ≤ ν₀ < ν₁ finite.
    fn to_near(&self) -> Result<crate::map::NearNoise> {
        if self.covariance.len() != 36 {
            return Err(format_error(format!(
                "map_noise.near.covariance: expected 36 values, got {}",
                self.covariance.len()
            )));
        }
        let covariance = Matrix6::from_row_slice(&self.covariance);
        check_covariance("map_noise.near.covariance", &covariance).map_err(as_format)?;
        let (spacing, far) = (self.spacing, self.holdout_distance);
        if !(spacing.is_finite() && far.is_finite() && 0.0 <= spacing && spacing < far) {
            return Err(format_error("map_noise.near: needs finite 0 ≤ spacing < holdout_distance"));
        }
        Ok(crate::map::NearNoise { covariance, spacing, holdout_distance: far })
    }
}

/// The values of a prior's `part`, or none when there is no prior.
fn six_or_none(prior: &VelocityPrior, part: &Vector6<f64>) -> Vec<f64> {
    if prior.is_none() { Vec::new() } else { part.iter().copied().collect() }
}

fn format_error(reason: impl Into<String>) -> GeolocError {
    GeolocError::Format { reason: reason.into() }
}

fn tensor(name: &str, shape: Vec<usize>, data: TensorData) -> Result<(String, Tensor)> {
    Ok((name.to_owned(), Tensor::new(name, shape, data)?))
}

impl Map {
    /// The map as a [`MapFile`]; `frontend` must be a JSON object (the caller's settings).
    ///
    /// # Errors
    /// `InvalidInput` naming `frontend` when it is not a JSON object.
    pub fn to_map_file(&self, frontend: &str) -> Result<MapFile> {
        let frontend: serde_json::Value = serde_json::from_str(frontend)
            .map_err(|e| GeolocError::invalid("frontend", format!("not valid JSON: {e}")))?;
        if !frontend.is_object() {
            return Err(GeolocError::invalid("frontend", "must be a JSON object"));
        }
        let k = self.keyframes.len();
        let (binary, width) = kind_and_width(&self.keyframes[0].descriptors);
        let mut tensors = vec![
            tensor(
                "keyframes.world_from_cam",
                vec![k, 4, 4],
                TensorData::F64(self.keyframes.iter().flat_map(|kf| row_major(&kf.world_from_cam.matrix())).collect()),
            )?,
            tensor("keyframes.keypoint_offsets", vec![k + 1], TensorData::I64(self.keypoint_offsets()))?,
            tensor(
                "keypoints",
                vec![self.keypoint_count(), 2],
                TensorData::F64(
                    self.keyframes.iter().flat_map(|kf| kf.keypoints.iter().flat_map(|p| [p.x, p.y])).collect(),
                ),
            )?,
            descriptor_tensor("descriptors", &DescriptorSet::stack(self.keyframes.iter().map(|kf| &kf.descriptors)))?,
        ];
        if let Some(covs) = &self.pose_covariances {
            let data = covs.iter().flat_map(|c| c.transpose().iter().copied().collect::<Vec<_>>()).collect();
            tensors.push(tensor("keyframes.pose_covariances", vec![k, 6, 6], TensorData::F64(data))?);
        }
        let retrieval = match &self.retrieval {
            Retrieval::Global(index) => {
                let data = self.keyframes.iter().flat_map(|kf| kf.global.clone().unwrap_or_default()).collect();
                tensors.push(tensor("keyframes.global_descriptors", vec![k, index.dim()], TensorData::F32(data))?);
                RetrievalHeader::Global { dim: index.dim() }
            }
            Retrieval::Bow { vocabulary, .. } => {
                tensors.extend(vocabulary_tensors(&vocabulary.to_arrays())?);
                RetrievalHeader::Bow { words: vocabulary.len() }
            }
            Retrieval::Fused { vocabulary, index, .. } => {
                let data = self.keyframes.iter().flat_map(|kf| kf.global.clone().unwrap_or_default()).collect();
                tensors.push(tensor("keyframes.global_descriptors", vec![k, index.dim()], TensorData::F32(data))?);
                tensors.extend(vocabulary_tensors(&vocabulary.to_arrays())?);
                RetrievalHeader::Fused { words: vocabulary.len(), dim: index.dim() }
            }
        };
        let header = MapHeader {
            camera: CameraHeader::from_camera(&self.camera),
            keyframes: k,
            keypoints: self.keypoint_count(),
            descriptor_kind: if binary { "binary" } else { "float" }.to_owned(),
            descriptor_width: width,
            retrieval,
            pose_covariances: self.pose_covariances.is_some(),
            frontend,
            map_noise: NoiseHeader::from_noise(&self.noise),
            model: self.model.as_ref().map(|m| ModelHeader { points: m.len() }),
            self_calibration: self.self_calibration.as_ref().map(SelfCalibrationHeader::from_self_calibration),
            labels: self.labels.as_ref().map(LabelsHeader::from_labels),
            group_matches: self.group_matches.as_ref().map(|m| GroupMatchesHeader { options: m.options.clone() }),
        };
        if let Some(model) = &self.model {
            tensors.extend(model_tensors(model)?);
        }
        if let Some(labels) = &self.labels {
            tensors.extend(label_tensors(labels)?);
        }
        if let Some(matches) = &self.group_matches {
            tensors.extend(group_match_tensors(matches)?);
        }
        let header = serde_json::to_string(&header).map_err(|e| format_error(e.to_string()))?;
        Ok(MapFile { header, tensors: tensors.into_iter().collect() })
    }

    /// Rebuilds a map from a [`MapFile`]; returns it with its header.
    ///
    /// # Errors
    /// `Format` naming the array or field that is missing, of the wrong shape or dtype, or
    /// holds values a map cannot have (non-finite numbers, non-rigid poses, offsets that do
    /// not partition the keypoints, a malformed vocabulary).
    pub fn from_map_file(file: &MapFile) -> Result<(Self, MapHeader)> {
        let header: MapHeader =
            serde_json::from_str(&file.header).map_err(|e| format_error(format!("map header: {e}")))?;
        let camera = header.camera.to_camera("map header camera")?;
        let k = header.keyframes;
        if k == 0 {
            return Err(format_error("the map has no keyframes"));
        }
        let poses = read_poses(file, k)?;
        let offsets = read_offsets(file, k, header.keypoints)?;
        let keypoints = f64_array(file, "keypoints", &[header.keypoints, 2])?;
        let descriptors = read_descriptors(file, &header)?;
        let globals = match header.retrieval {
            RetrievalHeader::Global { dim } | RetrievalHeader::Fused { dim, .. } if dim > 0 => {
                Some((f32_array(file, "keyframes.global_descriptors", &[k, dim])?, dim))
            }
            RetrievalHeader::Global { .. } | RetrievalHeader::Fused { .. } => {
                return Err(format_error("global descriptor length 0"));
            }
            RetrievalHeader::Bow { .. } => None,
        };
        let mut keyframes = Vec::with_capacity(k);
        for (i, pose) in poses.into_iter().enumerate() {
            let (a, b) = (offsets[i], offsets[i + 1]);
            keyframes.push(Keyframe {
                world_from_cam: pose,
                keypoints: keypoints[2 * a..2 * b].chunks_exact(2).map(|p| Vector2::new(p[0], p[1])).collect(),
                descriptors: descriptors.select(&(a..b).collect::<Vec<_>>()),
                global: globals.as_ref().map(|(g, dim)| g[i * dim..(i + 1) * dim].to_vec()),
            });
        }
        super::check_keyframes(&keyframes).map_err(as_format)?;
        let pose_covariances = if header.pose_covariances { Some(read_pose_covariances(file, k)?) } else { None };
        if let Some(c) = &pose_covariances {
            super::check_pose_covariances(c, k).map_err(as_format)?;
        }
        let retrieval = match header.retrieval {
            RetrievalHeader::Global { dim } => {
                let data = globals.map(|(g, _)| g).unwrap_or_default();
                Retrieval::Global(DescriptorIndex::new(data, dim).map_err(as_format)?)
            }
            RetrievalHeader::Bow { words } => {
                let (vocabulary, database) = read_bow(file, words, &keyframes)?;
                Retrieval::Bow { vocabulary, database }
            }
            RetrievalHeader::Fused { words, dim } => {
                let (vocabulary, database) = read_bow(file, words, &keyframes)?;
                let data = globals.map(|(g, _)| g).unwrap_or_default();
                Retrieval::Fused { vocabulary, database, index: DescriptorIndex::new(data, dim).map_err(as_format)? }
            }
        };
        let noise = header.map_noise.as_ref().map(NoiseHeader::to_noise).transpose()?.unwrap_or_default();
        let model = header.model.map(|h| read_model(file, h.points, &keyframes)).transpose()?;
        let self_calibration =
            header.self_calibration.as_ref().map(SelfCalibrationHeader::to_self_calibration).transpose()?;
        let labels = header.labels.as_ref().map(|h| h.to_labels(file, k)).transpose()?;
        let group_matches =
            header.group_matches.as_ref().map(|h| read_group_matches(file, h, &keyframes)).transpose()?;
        let map = Self {
            camera,
            keyframes,
            pose_covariances,
            retrieval,
            noise,
            model,
            self_calibration,
            labels,
            group_matches,
        };
        Ok((map, header))
    }

    /// The bytes [`Map::save`] writes, in memory: a map sent to another process or kept in a
    /// database; [`Map::from_bytes`] reads them back.
    ///
    /// # Errors
    /// As [`Map::to_map_file`] and [`MapFile::to_bytes`].
    pub fn to_bytes(&self, frontend: &str) -> Result<Vec<u8>> {
        self.to_map_file(frontend)?.to_bytes()
    }

    /// Reads a map from the bytes of a saved map ([`Map::to_bytes`], or a map file read
    /// whole), checking everything first as [`Map::load`] does.
    ///
    /// # Errors
    /// `Format` as [`MapFile::from_bytes`] and [`Map::from_map_file`] (truncated, corrupt,
    /// another version, a checksum mismatch).
    pub fn from_bytes(bytes: &[u8]) -> Result<(Self, MapHeader)> {
        Self::from_map_file(&MapFile::from_bytes(bytes)?)
    }

    /// Saves the map to `path` atomically (see [`file::write`]).
    ///
    /// # Errors
    /// As [`Map::to_map_file`] and [`file::write`].
    pub fn save(&self, path: &Path, frontend: &str) -> Result<()> {
        file::write(path, &self.to_map_file(frontend)?)
    }

    /// Loads a map saved by [`Map::save`], checking everything first.
    ///
    /// # Errors
    /// As [`file::read`] and [`Map::from_map_file`].
    pub fn load(path: &Path) -> Result<(Self, MapHeader)> {
        let file = file::read(path)?;
        Self::from_map_file(&file).map_err(|e| match e {
            GeolocError::Format { reason } => format_error(format!("{}: {reason}", path.display())),
            other => other,
        })
    }

    fn keypoint_count(&self) -> usize {
        self.keyframes.iter().map(|kf| kf.keypoints.len()).sum()
    }

    fn keypoint_offsets(&self) -> Vec<i64> {
        let mut offsets = vec![0i64];
        let mut total = 0i64;
        for kf in &self.keyframes {
            total += kf.keypoints.len() as i64;
            offsets.push(total);
        }
        offsets
    }
}

/// The stored vocabulary (`words` of them, as the header says) and the database rebuilt from
/// the keyframes' descriptors.
fn read_bow(file: &MapFile, words: usize, keyframes: &[Keyframe]) -> Result<(Vocabulary, BowDatabase)> {
    let vocabulary = Vocabulary::from_arrays(read_vocabulary(file)?).map_err(as_format)?;
    if vocabulary.len() != words {
        return Err(format_error(format!("vocabulary has {} words, header says {words}", vocabulary.len())));
    }
    let database = bow_database(&vocabulary, keyframes)?;
    Ok((vocabulary, database))
}

/// Errors of the core constructors, reported as a corrupt file.
fn as_format(e: GeolocError) -> GeolocError {
    format_error(format!("invalid map content: {e}"))
}

fn row_major(m: &Matrix4<f64>) -> Vec<f64> {
    m.transpose().iter().copied().collect()
}

fn expect_shape(name: &str, t: &Tensor, shape: &[usize]) -> Result<()> {
    if t.shape != shape {
        return Err(format_error(format!("array {name:?} has shape {:?}, expected {shape:?}", t.shape)));
    }
    Ok(())
}

fn f64_array<'a>(file: &'a MapFile, name: &str, shape: &[usize]) -> Result<&'a [f64]> {
    let t = file.tensor(name)?;
    expect_shape(name, t, shape)?;
    match &t.data {
        TensorData::F64(v) if v.iter().all(|x| x.is_finite()) => Ok(v),
        TensorData::F64(_) => Err(format_error(format!("array {name:?} holds non-finite values"))),
        _ => Err(format_error(format!("array {name:?} must be float64"))),
    }
}

fn f32_array(file: &MapFile, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
    let t = file.tensor(name)?;
    expect_shape(name, t, shape)?;
    match &t.data {
        TensorData::F32(v) if v.iter().all(|x| x.is_finite()) => Ok(v.clone()),
        TensorData::F32(_) => Err(format_error(format!("array {name:?} holds non-finite values"))),
        _ => Err(format_error(format!("array {name:?} must be float32"))),
    }
}

fn read_poses(file: &MapFile, k: usize) -> Result<Vec<SE3>> {
    read_pose_array(file, "keyframes.world_from_cam", k)
}

fn read_pose_array(file: &MapFile, name: &str, k: usize) -> Result<Vec<SE3>> {
    let values = f64_array(file, name, &[k, 4, 4])?;
    values
        .chunks_exact(16)
        .enumerate()
        .map(|(i, m)| {
            SE3::from_matrix(&Matrix4::from_row_slice(m))
                .map_err(|e| format_error(format!("{name}[{i}] is not a rigid transform: {e}")))
        })
        .collect()
}

fn read_offsets(file: &MapFile, k: usize, n: usize) -> Result<Vec<usize>> {
    let name = "keyframes.keypoint_offsets";
    let t = file.tensor(name)?;
    expect_shape(name, t, &[k + 1])?;
    let TensorData::I64(v) = &t.data else { return Err(format_error(format!("array {name:?} must be int64"))) };
    let offsets: Vec<usize> = v.iter().map(|&o| usize::try_from(o).unwrap_or(usize::MAX)).collect();
    let monotone = offsets.windows(2).all(|w| w[0] <= w[1]);
    if offsets[0] != 0 || offsets[k] != n || !monotone {
        return Err(format_error(format!("array {name:?} does not partition the {n} keypoints")));
    }
    Ok(offsets)
}

fn read_descriptors(file: &MapFile, header: &MapHeader) -> Result<DescriptorSet> {
    let t = file.tensor("descriptors")?;
    let width = header.descriptor_width;
    expect_shape("descriptors", t, &[header.keypoints, width])?;
    if width == 0 {
        return Err(format_error("descriptor width 0"));
    }
    match (header.descriptor_kind.as_str(), &t.data) {
        ("binary", TensorData::U8(data)) => Ok(DescriptorSet::Binary { data: data.clone(), width }),
        ("float", TensorData::F32(data)) if data.iter().all(|x| x.is_finite()) => {
            Ok(DescriptorSet::Float { data: data.clone(), width })
        }
        (kind, _) => Err(format_error(format!("array \"descriptors\" does not hold {kind:?} descriptors"))),
    }
}

fn read_pose_covariances(file: &MapFile, k: usize) -> Result<Vec<Matrix6<f64>>> {
    let values = f64_array(file, "keyframes.pose_covariances", &[k, 6, 6])?;
    Ok(values.chunks_exact(36).map(Matrix6::from_row_slice).collect())
}

fn bow_database(vocabulary: &Vocabulary, keyframes: &[Keyframe]) -> Result<BowDatabase> {
    let words: Vec<Vec<u32>> = keyframes
        .iter()
        .map(|kf| vocabulary.words_of(&kf.descriptors.view()))
        .collect::<Result<_>>()
        .map_err(as_format)?;
    BowDatabase::with_weighting(vocabulary.len(), &words, vocabulary.term_weighting()).map_err(as_format)
}

fn kind_and_width(d: &DescriptorSet) -> (bool, usize) {
    match d {
        DescriptorSet::Binary { width, .. } => (true, *width),
        DescriptorSet::Float { width, .. } => (false, *width),
    }
}

fn descriptor_tensor(name: &str, set: &DescriptorSet) -> Result<(String, Tensor)> {
    let (_, width) = kind_and_width(set);
    let data = match set {
        DescriptorSet::Binary { data, .. } => TensorData::U8(data.clone()),
        DescriptorSet::Float { data, .. } => TensorData::F32(data.clone()),
    };
    tensor(name, vec![set.len(), width], data)
}

fn vocabulary_tensors(v: &VocabularyArrays) -> Result<Vec<(String, Tensor)>> {
    Ok(vec![
        tensor("vocabulary.node_offsets", vec![v.node_offsets.len()], TensorData::I64(v.node_offsets.clone()))?,
        descriptor_tensor("vocabulary.centres", &v.centres)?,
        tensor("vocabulary.children", vec![v.children.len()], TensorData::I64(v.children.clone()))?,
    ])
}

fn model_tensors(model: &SceneModel) -> Result<Vec<(String, Tensor)>> {
    let p = model.len();
    let ids: Vec<i64> =
        model.point_ids.iter().flatten().map(|id| id.map_or(-1, |i| i64::try_from(i).unwrap_or(-1))).collect();
    Ok(vec![
        tensor(
            "model.points",
            vec![p, 3],
            TensorData::F64(model.points.iter().flat_map(|x| [x.x, x.y, x.z]).collect()),
        )?,
        tensor(
            "model.point_covariances",
            vec![p, 3, 3],
            TensorData::F64(
                model.covariances.iter().flat_map(|c| c.transpose().iter().copied().collect::<Vec<_>>()).collect(),
            ),
        )?,
        descriptor_tensor("model.descriptors", &model.descriptors)?,
        tensor("model.keypoint_points", vec![ids.len()], TensorData::I64(ids))?,
    ])
}

/// The stored model, checked: shapes, finite values, point covariances symmetric positive
/// semi-definite ([`check_covariances`]), descriptors of the keyframes' kind and width, point
/// ids in −1..P, every point observed.
fn read_model(file: &MapFile, p: usize, keyframes: &[Keyframe]) -> Result<SceneModel> {
    let points = f64_array(file, "model.points", &[p, 3])?;
    let covs = f64_array(file, "model.point_covariances", &[p, 3, 3])?;
    let name = "model.descriptors";
    let t = file.tensor(name)?;
    let width = kind_and_width(&keyframes[0].descriptors).1;
    expect_shape(name, t, &[p, width])?;
    let descriptors = match (&keyframes[0].descriptors, &t.data) {
        (DescriptorSet::Binary { .. }, TensorData::U8(data)) => DescriptorSet::Binary { data: data.clone(), width },
        (DescriptorSet::Float { .. }, TensorData::F32(data)) if data.iter().all(|x| x.is_finite()) => {
            DescriptorSet::Float { data: data.clone(), width }
        }
        _ => return Err(format_error(format!("array {name:?} does not hold the keyframes' kind of descriptors"))),
    };
    let n: usize = keyframes.iter().map(|k| k.keypoints.len()).sum();
    let ids = i64_vector(file, "model.keypoint_points")?;
    if ids.len() != n || ids.iter().any(|&i| i < -1 || i >= p as i64) {
        return Err(format_error(format!("array \"model.keypoint_points\" must hold {n} ids in -1..{p}")));
    }
    let mut rest = ids.as_slice();
    let mut point_ids = Vec::with_capacity(keyframes.len());
    for kf in keyframes {
        let (mine, tail) = rest.split_at(kf.keypoints.len());
        point_ids.push(mine.iter().map(|&i| usize::try_from(i).ok()).collect());
        rest = tail;
    }
    // checked here as PnP checks them, so a bad file is blamed at load, not at the first frame
    let covariances: Vec<Matrix3<f64>> = covs.chunks_exact(9).map(Matrix3::from_row_slice).collect();
    check_covariances("model.point_covariances", &covariances).map_err(as_format)?;
    SceneModel::from_parts(
        points.chunks_exact(3).map(Vector3::from_column_slice).collect(),
        covariances,
        descriptors,
        point_ids,
    )
    .map_err(as_format)
}

/// `group_matches.group_offsets` i64 (K + 1) and `group_matches.groups` u32 (G): seed s's
/// group is `groups[offsets[s]..offsets[s+1]]`; `group_matches.row_offsets` i64 (K + 1) and
/// `group_matches.rows` u32 (3M): seed s's rows (g, seed keypoint, g keypoint) are rows
/// `row_offsets[s]..row_offsets[s+1]` of `rows` viewed as (M, 3).
fn group_match_tensors(m: &GroupMatches) -> Result<Vec<(String, Tensor)>> {
    let offsets = |lens: Vec<usize>| -> Vec<i64> {
        std::iter::once(0)
            .chain(lens.into_iter().scan(0i64, |acc, n| {
                *acc += n as i64;
                Some(*acc)
            }))
            .collect()
    };
    let u32s = |v: &mut dyn Iterator<Item = usize>| -> Result<Vec<u32>> {
        v.map(|x| u32::try_from(x).map_err(|_| format_error("group_matches: an index does not fit in u32"))).collect()
    };
    let k = m.groups.len();
    let groups = u32s(&mut m.groups.iter().flatten().copied())?;
    let rows = u32s(&mut m.rows.iter().flatten().flatten().copied())?;
    Ok(vec![
        tensor(
            "group_matches.group_offsets",
            vec![k + 1],
            TensorData::I64(offsets(m.groups.iter().map(Vec::len).collect())),
        )?,
        tensor("group_matches.groups", vec![groups.len()], TensorData::U32(groups))?,
        tensor(
            "group_matches.row_offsets",
            vec![k + 1],
            TensorData::I64(offsets(m.rows.iter().map(Vec::len).collect())),
        )?,
        tensor("group_matches.rows", vec![rows.len()], TensorData::U32(rows))?,
    ])
}

fn read_group_matches(file: &MapFile, header: &GroupMatchesHeader, keyframes: &[Keyframe]) -> Result<GroupMatches> {
    let k = keyframes.len();
    let u32_vector = |name: &str| -> Result<Vec<usize>> {
        let t = file.tensor(name)?;
        match (&t.data, t.shape.as_slice()) {
            (TensorData::U32(v), [_]) => Ok(v.iter().map(|&x| x as usize).collect()),
            _ => Err(format_error(format!("array {name:?} must be a 1-D uint32 array"))),
        }
    };
    // offsets that partition `len` values into k parts
    let parts = |name: &str, len: usize| -> Result<Vec<std::ops::Range<usize>>> {
        let o = i64_vector(file, name)?;
        let ok = o.len() == k + 1 && o[0] == 0 && o[k] == len as i64 && o.windows(2).all(|w| w[0] <= w[1]);
        if !ok {
            return Err(format_error(format!("array {name:?} must hold {} increasing offsets from 0 to {len}", k + 1)));
        }
        Ok(o.windows(2).map(|w| w[0] as usize..w[1] as usize).collect())
    };
    let groups_flat = u32_vector("group_matches.groups")?;
    let rows_flat = u32_vector("group_matches.rows")?;
    if rows_flat.len() % 3 != 0 {
        return Err(format_error("array \"group_matches.rows\" must hold whole rows of 3"));
    }
    let groups =
        parts("group_matches.group_offsets", groups_flat.len())?.into_iter().map(|r| groups_flat[r].to_vec()).collect();
    let rows = parts("group_matches.row_offsets", rows_flat.len() / 3)?
        .into_iter()
        .map(|r| rows_flat[3 * r.start..3 * r.end].chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
        .collect();
    let matches = GroupMatches { options: header.options.clone(), groups, rows };
    matches.check(keyframes).map_err(as_format)?;
    Ok(matches)
}

fn i64_vector(file: &MapFile, name: &str) -> Result<Vec<i64>> {
    let t = file.tensor(name)?;
    match (&t.data, t.shape.as_slice()) {
        (TensorData::I64(v), [_]) => Ok(v.clone()),
        _ => Err(format_error(format!("array {name:?} must be a 1-D int64 array"))),
    }
}

fn read_vocabulary(file: &MapFile) -> Result<VocabularyArrays> {
    let name = "vocabulary.centres";
    let t = file.tensor(name)?;
    let centres = match (&t.data, t.shape.as_slice()) {
        (TensorData::U8(data), &[_, width]) if width > 0 => DescriptorSet::Binary { data: data.clone(), width },
        (TensorData::F32(data), &[_, width]) if width > 0 => DescriptorSet::Float { data: data.clone(), width },
        _ => return Err(format_error(format!("array {name:?} must be a 2-D uint8 or float32 array"))),
    };
    Ok(VocabularyArrays {
        node_offsets: i64_vector(file, "vocabulary.node_offsets")?,
        centres,
        children: i64_vector(file, "vocabulary.children")?,
    })
}

/// `file` with its header's `section` (e.g. `"labels"`, `"map_noise"`) changed by `edit`,
/// read back: how the tests damage one field of a stored record.
#[cfg(test)]
pub(crate) fn read_with_edited_header(
    file: &MapFile,
    section: &str,
    edit: &dyn Fn(&mut serde_json::Value),
) -> Result<(Map, MapHeader)> {
    let mut header: serde_json::Value = serde_json::from_str(&file.header).expect("the header is JSON");
    edit(&mut header[section]);
    let mut edited = file.clone();
    edited.header = header.to_string();
    Map::from_map_file(&edited)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{RetrievalKind, RetrievalQuery};
    use crate::rng::SplitMix64;
    use crate::testing::isotropic_pose_covariance;

    fn keyframes(rng: &mut SplitMix64, binary: bool, global: bool) -> Vec<Keyframe> {
        (0..6)
            .map(|k| {
                let n = 40 + 3 * k;
                let descriptors = if binary {
                    DescriptorSet::Binary {
                        data: (0..n * 32).map(|_| (rng.next_u64() & 0xff) as u8).collect(),
                        width: 32,
                    }
                } else {
                    DescriptorSet::Float {
                        data: (0..n * 16).map(|_| rng.uniform_in(-1.0, 1.0) as f32).collect(),
                        width: 16,
                    }
                };
                Keyframe {
                    world_from_cam: rng.pose(3.0),
                    keypoints: (0..n)
                        .map(|_| Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0)))
                        .collect(),
                    descriptors,
                    global: global.then(|| (0..8).map(|_| rng.uniform_in(-1.0, 1.0) as f32).collect()),
                }
            })
            .collect()
    }

    fn map(binary: bool, kind: RetrievalKind, covariances: bool) -> Map {
        let mut rng = SplitMix64::new(21);
        let kfs = keyframes(&mut rng, binary, !matches!(kind, RetrievalKind::Bow { .. }));
        let covs = covariances.then(|| vec![isotropic_pose_covariance(0.01, 0.005); kfs.len()]);
        let camera = Camera::new(525.0, 526.0, 320.5, 239.5).expect("valid camera");
        Map::build(camera, kfs, covs, kind, 3).expect("valid map")
    }

    fn assert_same(a: &Map, b: &Map) {
        assert_eq!(a.camera, b.camera);
        assert_eq!(a.keyframes, b.keyframes);
        assert_eq!(a.pose_covariances, b.pose_covariances);
        for kf in &a.keyframes {
            let query = RetrievalQuery {
                keypoints: &kf.keypoints,
                descriptors: kf.descriptors.view(),
                global: kf.global.as_deref(),
            };
            let n = a.keyframes.len();
            assert_eq!(
                a.retrieve_top(&query, n, 0..0).expect("retrieves"),
                b.retrieve_top(&query, n, 0..0).expect("retrieves")
            );
        }
    }

    #[test]
    fn every_kind_of_map_round_trips_exactly() {
        let bow = RetrievalKind::Bow { branching: 4, depth: 2 };
        for (binary, kind, covariances) in [
            (true, bow, false),
            (false, bow, true),
            (true, RetrievalKind::Global, true),
            (false, RetrievalKind::Global, false),
            (true, RetrievalKind::Fused { branching: 4, depth: 2 }, false),
            (false, RetrievalKind::Fused { branching: 3, depth: 2 }, true),
        ] {
            let original = map(binary, kind, covariances);
            let file = original.to_map_file(r#"{"features":"orb"}"#).expect("serializes");
            let bytes = file.to_bytes().expect("bytes");
            let (back, header) = Map::from_map_file(&MapFile::from_bytes(&bytes).expect("reads")).expect("valid map");
            assert_same(&original, &back);
            assert_eq!(header.frontend["features"], "orb");
            assert_eq!(header.keyframes, 6);
            // The stored vocabulary is used as stored (same words), not retrained.
            match (&original.retrieval, &back.retrieval) {
                (Retrieval::Bow { vocabulary: a, .. }, Retrieval::Bow { vocabulary: b, .. })
                | (Retrieval::Fused { vocabulary: a, .. }, Retrieval::Fused { vocabulary: b, .. }) => assert_eq!(a, b),
                (Retrieval::Global(_), Retrieval::Global(_)) => {}
                _ => panic!("the retrieval method changed on the way"),
            }
            assert_eq!(
                back.to_map_file(r#"{"features":"orb"}"#).expect("serializes").to_bytes().expect("bytes"),
                bytes
            );
        }
    }

    #[test]
    fn bad_content_is_refused_with_the_array_named() {
        let original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        let good = original.to_map_file("{}").expect("serializes");
        let mut sheared = good.clone();
        if let Some(Tensor { data: TensorData::F64(v), .. }) = sheared.tensors.get_mut("keyframes.world_from_cam") {
            v[1] += 0.5; // R no longer a rotation
        }
        let err = Map::from_map_file(&sheared).expect_err("not rigid");
        assert!(err.to_string().contains("keyframes.world_from_cam[0] is not a rigid transform"), "{err}");
        let mut offsets = good.clone();
        if let Some(Tensor { data: TensorData::I64(v), .. }) = offsets.tensors.get_mut("keyframes.keypoint_offsets") {
            v[2] = v[1] - 1;
        }
        let err = Map::from_map_file(&offsets).expect_err("offsets");
        assert!(err.to_string().contains("keypoint_offsets"), "{err}");
        let mut missing = good.clone();
        missing.tensors.remove("vocabulary.children");
        let err = Map::from_map_file(&missing).expect_err("missing array");
        assert!(err.to_string().contains("vocabulary.children"), "{err}");
        let err = original.to_map_file("[1, 2]").expect_err("frontend must be an object");
        assert!(matches!(err, GeolocError::InvalidInput { ref name, .. } if name == "frontend"), "{err:?}");
    }

    #[test]
    fn self_calibration_round_trips_with_or_without_a_correction() {
        use crate::selfcal::{IntrinsicsCorrection, SelfCalibration};
        let with = SelfCalibration {
            correction: Some(IntrinsicsCorrection {
                camera: Camera::new(516.25, 529.5, 314.125, 243.0625).expect("valid"),
                distortion: Distortion { k1: -0.06, k2: 0.02, p1: 0.004, p2: -0.003, k3: 0.0 },
            }),
            reason: "ok".into(),
            rms_before_px: 2.5,
            rms_after_px: 0.75,
            median_before_px: 1.5,
            median_after_px: 0.5,
            observations: 1234,
            points: 321,
            correction_sigma_px: 0.125,
            report: None,
        };
        // no tracks at all: every statistic NaN, stored as null
        let without = SelfCalibration {
            correction: None,
            reason: "0 observations of 0 points (needs 200 of 50)".into(),
            rms_before_px: f64::NAN,
            rms_after_px: f64::NAN,
            median_before_px: f64::NAN,
            median_after_px: f64::NAN,
            observations: 0,
            points: 0,
            correction_sigma_px: f64::NAN,
            report: None,
        };
        for calibration in [with, without] {
            let mut original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
            original.self_calibration = Some(calibration.clone());
            let bytes = original.to_map_file("{}").expect("serializes").to_bytes().expect("bytes");
            let (back, header) = Map::from_map_file(&MapFile::from_bytes(&bytes).expect("reads")).expect("valid map");
            let got = back.self_calibration.expect("stored");
            assert_eq!(got.correction, calibration.correction);
            assert_eq!(got.reason, calibration.reason);
            assert_eq!((got.observations, got.points), (calibration.observations, calibration.points));
            for (a, b) in [
                (got.rms_before_px, calibration.rms_before_px),
                (got.median_after_px, calibration.median_after_px),
                (got.correction_sigma_px, calibration.correction_sigma_px),
            ] {
                assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()), "{a} vs {b}");
            }
            assert_eq!(header.self_calibration.is_some_and(|h| h.camera.is_some()), calibration.correction.is_some());
        }
        // a camera without its distortion is refused
        let mut original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        original.self_calibration = Some(with_camera_only());
        let file = original.to_map_file("{}").expect("serializes");
        let mut header: serde_json::Value = serde_json::from_str(&file.header).expect("json");
        header["self_calibration"]["distortion"] = serde_json::Value::Null;
        let broken = MapFile { header: header.to_string(), tensors: file.tensors.clone() };
        let err = Map::from_map_file(&broken).expect_err("half a correction");
        assert!(err.to_string().contains("self_calibration"), "{err}");
    }

    fn with_camera_only() -> crate::selfcal::SelfCalibration {
        crate::selfcal::SelfCalibration {
            correction: Some(crate::selfcal::IntrinsicsCorrection {
                camera: Camera::new(520.0, 520.0, 320.0, 240.0).expect("valid"),
                distortion: Distortion::default(),
            }),
            reason: "ok".into(),
            rms_before_px: 1.0,
            rms_after_px: 1.0,
            median_before_px: 1.0,
            median_after_px: 1.0,
            observations: 500,
            points: 100,
            correction_sigma_px: 0.1,
            report: None,
        }
    }

    #[test]
    #[allow(clippy::float_cmp)] // values are copied, not computed
    fn map_noise_round_trips_and_old_maps_read_it_as_zero() {
        let mut original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        let old = original.to_map_file("{}").expect("serializes");
        assert!(!old.header.contains("map_noise"), "a map without noise writes the old header");
        let (back, header) = Map::from_map_file(&old).expect("valid");
        assert_eq!(back.noise, MapNoise::default());
        assert!(header.map_noise.is_none());
        let a = Matrix6::from_fn(|r, c| 1e-4 * ((r + 1) * (c + 1)) as f64) + Matrix6::identity() * 1e-3;
        original.noise = MapNoise {
            pose_covariance: a,
            acceleration_psd: Vector6::repeat(0.25),
            velocity_prior: VelocityPrior {
                mean: Vector6::new(0.01, -0.02, 0.03, -0.04, 0.05, -0.06),
                variance: Vector6::new(0.04, 0.05, 0.06, 0.07, 0.08, 0.09),
            },
            holdout_samples: 57,
            holdout_inliers: 312.5,
            holdout: vec![],
            resolved: Some([true, false, true, true, false, true]),
            near: Some(crate::map::NearNoise {
                covariance: Matrix6::from_diagonal(&Vector6::new(4e-5, 3e-5, 2e-5, 1e-5, 2e-5, 3e-5)),
                spacing: 0.125,
                holdout_distance: 1.75,
            }),
        };
        let file = original.to_map_file("{}").expect("serializes");
        let (back, header) = Map::from_map_file(&file).expect("valid");
        assert_eq!(back.noise, original.noise);
        assert_eq!(header.map_noise.map(|n| n.holdout_samples), Some(57));
        let mut bad = file.clone();
        bad.header = bad.header.replace("312.5", "-312.5");
        assert!(Map::from_map_file(&bad).expect_err("negative n̄").to_string().contains("holdout_inliers"));
        // a file saved before the support: the key is absent, C_map applies unscaled
        let mut old_support = file.clone();
        old_support.header = old_support.header.replace(r#","holdout_inliers":312.5"#, "");
        assert!(!old_support.header.contains("holdout_inliers"), "{}", old_support.header);
        let (back, _) = Map::from_map_file(&old_support).expect("valid");
        assert_eq!(back.noise.holdout_inliers, 0.0);
        assert_eq!(back.noise.pose_covariance_at(Some(10)), a);
        // the resolved axes: read back as written (above), absent in an older file, 6 or refused
        assert!(file.header.contains(r#""resolved":[true,false,true,true,false,true]"#), "{}", file.header);
        let mut old_resolved = file.clone();
        old_resolved.header = old_resolved.header.replace(r#","resolved":[true,false,true,true,false,true]"#, "");
        let (back, _) = Map::from_map_file(&old_resolved).expect("valid");
        assert_eq!(back.noise.resolved_axes(), None);
        let mut bad = file.clone();
        bad.header = bad.header.replace(r#""resolved":[true,"#, r#""resolved":["#);
        assert!(Map::from_map_file(&bad).expect_err("5 values").to_string().contains("map_noise.resolved"));
        let mut bad = file.clone();
        bad.header = bad.header.replace("0.25", "-0.25");
        assert!(Map::from_map_file(&bad).expect_err("negative q").to_string().contains("acceleration_psd"));
        let mut bad = file.clone();
        bad.header = bad.header.replace("0.07", "-0.07");
        assert!(Map::from_map_file(&bad).expect_err("negative variance").to_string().contains("velocity_variance"));
        let mut bad = file.clone();
        bad.header = bad.header.replace(r#""velocity_mean":[0.01,"#, r#""velocity_mean":["#);
        assert!(Map::from_map_file(&bad).expect_err("5 values").to_string().contains("velocity_mean"));
        // a file saved before the velocity prior: the keys are absent, the prior is none
        let mut old_noise = file.clone();
        old_noise.header = old_noise
            .header
            .replace(r#""velocity_mean":[0.01,-0.02,0.03,-0.04,0.05,-0.06],"#, "")
            .replace(r#""velocity_variance":[0.04,0.05,0.06,0.07,0.08,0.09],"#, "");
        assert!(!old_noise.header.contains("velocity_"), "{}", old_noise.header);
        let (back, _) = Map::from_map_file(&old_noise).expect("valid");
        assert!(back.noise.velocity_prior.is_none());
        assert_eq!(back.noise.acceleration_psd, original.noise.acceleration_psd);
        // the near regime: absent in an older file (C_map at every distance), checked when present
        let with_near = |edit: &dyn Fn(&mut serde_json::Value)| read_with_edited_header(&file, "map_noise", edit);
        let back = with_near(&|n| {
            n.as_object_mut().expect("object").remove("near");
        })
        .expect("an older file")
        .0;
        assert_eq!(back.noise.near, None);
        assert_eq!(back.noise.covariance_at(Some(400), Some(0.0)), a);
        for (what, edit) in [
            (
                "near.covariance",
                &(|n: &mut serde_json::Value| n["near"]["covariance"][0] = (-1.0).into())
                    as &dyn Fn(&mut serde_json::Value),
            ),
            ("near.covariance", &|n| n["near"]["covariance"] = serde_json::json!([1.0])),
            ("near.covariance: exceeds", &|n| n["near"]["covariance"][0] = 1.0.into()),
            ("near.covariance: all zero", &|n| n["near"]["covariance"] = serde_json::Value::from(vec![0.0; 36])),
            ("map_noise.near", &|n| n["near"]["spacing"] = 2.0.into()),
            ("map_noise.near", &|n| n["near"]["spacing"] = (-0.1).into()),
        ] {
            let err = with_near(edit).expect_err(what).to_string();
            assert!(err.contains(what), "{what}: {err}");
        }
    }

    /// A stored model comes back exactly (re-saved bytes identical); a map without one
    /// writes the old header and loads with none; bad point ids are refused by array name.
    #[test]
    fn the_model_round_trips_and_maps_without_one_still_load() {
        let mut original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        let old = original.to_map_file("{}").expect("serializes");
        assert!(!old.header.contains("\"model\""), "{}", old.header);
        assert!(Map::from_map_file(&old).expect("valid").0.model.is_none());
        let point_ids: Vec<Vec<Option<usize>>> = original
            .keyframes
            .iter()
            .map(|kf| (0..kf.keypoints.len()).map(|i| (i < 3).then_some(i)).collect())
            .collect();
        let points = vec![Vector3::new(0.5, -1.0, 3.0), Vector3::new(1.0, 2.0, 4.0), Vector3::new(-0.25, 0.0, 5.5)];
        let covs: Vec<Matrix3<f64>> =
            (1..4).map(|i| Matrix3::from_fn(|r, c| 1e-4 * i as f64 * if r == c { 3.0 } else { 1.0 })).collect();
        let descriptors = original.keyframes[0].descriptors.select(&[0, 1, 2]);
        original.model = Some(SceneModel::from_parts(points, covs, descriptors, point_ids).expect("valid model"));
        let file = original.to_map_file("{}").expect("serializes");
        let bytes = file.to_bytes().expect("bytes");
        let (back, header) = Map::from_map_file(&MapFile::from_bytes(&bytes).expect("reads")).expect("valid");
        assert_eq!(back.model, original.model);
        assert_eq!(header.model, Some(ModelHeader { points: 3 }));
        assert_eq!(back.model.as_ref().map(|m| m.observers(1).len()), Some(6));
        assert_eq!(back.to_map_file("{}").expect("serializes").to_bytes().expect("bytes"), bytes);
        let mut bad = file.clone();
        if let Some(Tensor { data: TensorData::I64(v), .. }) = bad.tensors.get_mut("model.keypoint_points") {
            v[0] = 3;
        }
        let err = Map::from_map_file(&bad).expect_err("id out of range");
        assert!(err.to_string().contains("model.keypoint_points"), "{err}");
        let mut missing = file.clone();
        missing.tensors.remove("model.points");
        assert!(Map::from_map_file(&missing).expect_err("missing").to_string().contains("model.points"));
    }

    /// A point covariance that is not positive semi-definite is refused at load, naming the
    /// array and the point (before, it loaded and the first localization blamed the caller).
    #[test]
    fn a_non_psd_point_covariance_is_refused_at_load() {
        let mut original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        let point_ids: Vec<Vec<Option<usize>>> = original
            .keyframes
            .iter()
            .map(|kf| (0..kf.keypoints.len()).map(|i| (i < 3).then_some(i)).collect())
            .collect();
        let points = vec![Vector3::new(0.5, -1.0, 3.0), Vector3::new(1.0, 2.0, 4.0), Vector3::new(-0.25, 0.0, 5.5)];
        let descriptors = original.keyframes[0].descriptors.select(&[0, 1, 2]);
        original.model = Some(
            SceneModel::from_parts(points, vec![Matrix3::identity() * 1e-4; 3], descriptors, point_ids).expect("valid"),
        );
        let file = original.to_map_file("{}").expect("serializes");
        // point 2: eigenvalues 1e-4, 1e-4, −1e-4 (symmetric, finite, indefinite)
        let mut bad = file.clone();
        if let Some(Tensor { data: TensorData::F64(v), .. }) = bad.tensors.get_mut("model.point_covariances") {
            v[2 * 9 + 8] = -1e-4;
        }
        let err = Map::from_map_file(&bad).expect_err("indefinite covariance");
        assert!(matches!(err, GeolocError::Format { .. }), "{err:?}");
        assert!(err.to_string().contains("model.point_covariances[2]: is not positive semi-definite"), "{err}");
        let mut asymmetric = file.clone();
        if let Some(Tensor { data: TensorData::F64(v), .. }) = asymmetric.tensors.get_mut("model.point_covariances") {
            v[1] = 5e-5;
        }
        let err = Map::from_map_file(&asymmetric).expect_err("asymmetric covariance");
        assert!(err.to_string().contains("model.point_covariances[0]: is not symmetric"), "{err}");
    }

    /// Nodes of the crafted chain vocabulary (the adversarial probe's size: ~13 MB).
    const CHAIN_NODES: usize = 200_000;
    /// The crafted chain must be refused well within this (it took 27–36 s to load before).
    const CHAIN_REFUSED_WITHIN: std::time::Duration = std::time::Duration::from_secs(1);

    /// A chain vocabulary (node i: node i + 1 and word i; 200 000 levels), saved with a valid
    /// checksum by the map's own writer and a header whose word count matches: refused at
    /// load by the depth limit, at once, instead of a 200 000-distance descent per descriptor.
    #[test]
    fn a_crafted_chain_vocabulary_is_refused_at_load_at_once() {
        let original = map(true, RetrievalKind::Bow { branching: 4, depth: 2 }, false);
        let mut file = original.to_map_file("{}").expect("serializes");
        let (node_offsets, children) = crate::testing::chain_vocabulary(CHAIN_NODES);
        let words = CHAIN_NODES + 1;
        let centres = DescriptorSet::Binary { data: vec![0; children.len() * 32], width: 32 };
        let chain = VocabularyArrays { node_offsets, centres, children };
        for (name, t) in vocabulary_tensors(&chain).expect("tensors") {
            file.tensors.insert(name, t);
        }
        let mut header: MapHeader = serde_json::from_str(&file.header).expect("header");
        header.retrieval = RetrievalHeader::Bow { words };
        file.header = serde_json::to_string(&header).expect("header");
        let dir = std::env::temp_dir().join(format!("geoloc-persist-chain-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("chain.geoloc");
        file::write(&path, &file).expect("saves with a valid checksum");
        let start = std::time::Instant::now();
        let err = Map::load(&path).expect_err("the chain is refused");
        let took = start.elapsed();
        assert!(matches!(err, GeolocError::Format { .. }), "{err:?}");
        assert!(err.to_string().contains("deeper than the limit of 24 levels (MAX_DEPTH)"), "{err}");
        assert!(took < CHAIN_REFUSED_WITHIN, "refused after {took:?}");
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn save_and_load_through_a_file() {
        let dir = std::env::temp_dir().join(format!("geoloc-persist-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("scene.geoloc");
        let original = map(false, RetrievalKind::Bow { branching: 3, depth: 2 }, true);
        original.save(&path, "{}").expect("saves");
        let (back, _) = Map::load(&path).expect("loads");
        assert_same(&original, &back);
        let bytes = std::fs::read(&path).expect("read");
        std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("truncate");
        let err = Map::load(&path).expect_err("truncated");
        assert!(err.to_string().contains("scene.geoloc"), "{err}");
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    /// The bytes in memory are the saved file's, byte for byte, and read back to the same map
    /// with the same frontend record; a truncated or altered copy is refused as a file is.
    #[test]
    fn the_bytes_in_memory_are_the_saved_file() {
        let dir = std::env::temp_dir().join(format!("geoloc-persist-bytes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("scene.geoloc");
        let original = map(true, RetrievalKind::Bow { branching: 3, depth: 2 }, true);
        let frontend = r#"{"features":"orb"}"#;
        original.save(&path, frontend).expect("saves");
        let bytes = original.to_bytes(frontend).expect("serializes");
        assert_eq!(bytes, std::fs::read(&path).expect("read"));
        let (back, header) = Map::from_bytes(&bytes).expect("reads");
        assert_same(&original, &back);
        assert_eq!(header.frontend.to_string(), frontend);
        let err = Map::from_bytes(&bytes[..bytes.len() - 9]).expect_err("truncated");
        assert!(matches!(err, GeolocError::Format { .. }), "{err}");
        let mut altered = bytes.clone();
        let last = altered.len() - 1;
        altered[last] ^= 1;
        let err = Map::from_bytes(&altered).expect_err("altered");
        assert!(err.to_string().contains("checksum mismatch"), "{err}");
        assert!(matches!(Map::from_bytes(&[]), Err(GeolocError::Format { .. })));
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
