//! The map a camera is localized against: keyframes with known world_from_cam poses, their
//! keypoints (undistorted pixels) and local descriptors, optional global descriptors, the
//! camera, and the retrieval structure built from them (a descriptor index when a network
//! provides global descriptors, else a bag-of-words vocabulary and database).
//!
//! [`Map::with_refined_intrinsics`] estimates the camera from the keyframes themselves
//! ([`crate::selfcal`]); the keyframes' keypoints are then stored corrected, and the
//! localizer corrects every query's keypoints the same way before using them.

mod build;
pub mod file;
pub mod fused_retrieval;
pub mod group_matches;
pub mod label_breaks;
pub mod label_loops;
pub mod labels;
pub mod model;
pub mod noise;
mod persist;

pub use build::BuildOptions;
pub use group_matches::GroupMatches;
pub use labels::{LabelAdjustment, LabelRun};
pub use model::{ModelOptions, PairMatches, SceneModel};
pub use persist::{
    CameraHeader, LabelsHeader, MapHeader, ModelHeader, NoiseHeader, RetrievalHeader, SelfCalibrationHeader,
};

use std::borrow::Cow;

use nalgebra::{Matrix6, Vector2, Vector6};

use crate::adjust::{AdjustmentOptions, Observation, camera_frame_covariance};
use crate::bow::{BowDatabase, Vocabulary};
use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
pub use crate::matching::DescriptorSet;
use crate::matching::Descriptors;
use crate::motion::VelocityPrior;
use crate::optim::covariance::check_covariances;
use crate::retrieval::DescriptorIndex;
use crate::selfcal::{IntrinsicsCorrection, SelfCalibration, SelfCalibrationOptions, TrackObservation, self_calibrate};
use crate::triangulate::TriangulationOptions;

/// One keyframe of the map.
#[derive(Clone, Debug, PartialEq)]
pub struct Keyframe {
    /// Pose label (world_from_cam).
    pub world_from_cam: SE3,
    /// Keypoints, undistorted pixels.
    pub keypoints: Vec<Vector2<f64>>,
    /// One local descriptor per keypoint.
    pub descriptors: DescriptorSet,
    /// Global descriptor from a network, if any.
    pub global: Option<Vec<f32>>,
}

/// How the map retrieves the keyframe most similar to a query image.
pub enum Retrieval {
    /// Nearest global descriptor.
    Global(DescriptorIndex),
    /// Bag of words over the local descriptors.
    Bow {
        /// The vocabulary.
        vocabulary: Vocabulary,
        /// The keyframes' TF-IDF database.
        database: BowDatabase,
    },
    /// Bag of words and the nearest global descriptors each propose keyframes, and two-view
    /// verification orders them ([`fused_retrieval`]): a network can add candidates, never
    /// remove BoW's.
    Fused {
        /// The vocabulary.
        vocabulary: Vocabulary,
        /// The keyframes' TF-IDF database.
        database: BowDatabase,
        /// The keyframes' global descriptors.
        index: DescriptorIndex,
    },
}

/// The map.
pub struct Map {
    /// Intrinsics shared by keyframes and queries.
    pub camera: Camera,
    /// The keyframes, in capture order.
    pub keyframes: Vec<Keyframe>,
    /// Covariances of the keyframe poses (right perturbation), if known: those given with the
    /// labels, or after [`Map::with_adjusted_labels`] the adjusted poses' relative to the labels' frame.
    pub pose_covariances: Option<Vec<Matrix6<f64>>>,
    /// The retrieval structure.
    pub retrieval: Retrieval,
    /// What was estimated about the map's noise at build time (zero when not estimated).
    pub noise: MapNoise,
    /// The map-level 3D model of the model locator ([`Map::with_model`]), if built.
    pub model: Option<SceneModel>,
    /// The camera estimated from the keyframes ([`Map::with_refined_intrinsics`]), if tried;
    /// with a correction, the keyframes' keypoints are stored corrected and queries'
    /// keypoints are corrected by the localizer.
    pub self_calibration: Option<SelfCalibration>,
    /// The labels and their correction by bundle adjustment ([`Map::with_adjusted_labels`]),
    /// if adjusted: the keyframes' `world_from_cam` are then the adjusted camera poses.
    pub labels: Option<LabelAdjustment>,
    /// The paper locator's keyframe-pair matches prepared at build time
    /// ([`BuildSteps::group_matches`]), if prepared.
    pub group_matches: Option<GroupMatches>,
}

/// A labels' adjustment problem ([`Map::label_adjustment_problem`]): what
/// [`crate::adjust::bundle_adjust_from`] takes, on the skeleton keyframes `keyframes`.
#[derive(Clone, Debug, PartialEq)]
pub struct AdjustmentProblem {
    /// The map's keyframe index of each of the problem's keyframes (the skeleton, in order).
    pub keyframes: Vec<usize>,
    /// Their labels (world_from_label), the priors.
    pub labels: Vec<SE3>,
    /// Their start poses (label convention; the labels for a map not adjusted before).
    pub start: Vec<SE3>,
    /// The points (world), triangulated from the start poses.
    pub points: Vec<nalgebra::Vector3<f64>>,
    /// Keyframe `keyframe` (an index into `labels`) sees point `point` at `pixel`.
    pub observations: Vec<Observation>,
    /// The views of the points that the triangulation from the start poses rejected: the
    /// adjustment's candidates ([`crate::adjust::bundle_adjust_with_candidates`]), which join
    /// once the poses have moved to where they fit.
    pub candidates: Vec<Observation>,
}

/// Which build steps [`Map::with_build_steps`] runs, in this order: the labels' adjustment,
/// the camera estimate (with the adjusted camera poses), the 3D model (each None to skip it).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BuildSteps {
    /// Estimate the camera from the keyframes ([`Map::with_refined_intrinsics`]).
    pub calibration: Option<SelfCalibrationOptions>,
    /// Correct the labels by bundle adjustment ([`Map::with_adjusted_labels`]).
    pub adjustment: Option<AdjustmentOptions>,
    /// Build the 3D model of the model locator ([`Map::with_model`]).
    pub model: Option<ModelOptions>,
    /// Prepare the paper locator's keyframe-pair matches for the default localizer options
    /// ([`GroupMatches`]), last, from the final poses and keypoints.
    pub group_matches: bool,
}

/// The map's noise, estimated at build time from its own keyframes
/// ([`Map::with_estimated_noise`]); all zero when not estimated (old maps load so).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapNoise {
    /// C_map: 6×6 covariance (right perturbation of world_from_cam, translation first) of
    /// the pose-label error a query's pose shares with the map (label inconsistency between
    /// parts of the trajectory), beyond what the PnP covariance explains. Added to every
    /// returned covariance.
    pub pose_covariance: Matrix6<f64>,
    /// q: power spectral density of the white body acceleration per twist axis
    /// ((m/s²)²·s, (rad/s²)²·s), from the keyframes' timestamps and poses; 0 = none.
    pub acceleration_psd: Vector6<f64>,
    /// The motion model's velocity prior: mean and variance of the body velocity per twist
    /// axis, from the keyframes' timestamps and poses; none (all zero) in maps saved before it.
    pub velocity_prior: VelocityPrior,
    /// Held-out keyframes placed within the gross-failure bounds (C_map's samples; with fewer
    /// than 12 C_map is a conservative default, never zero).
    pub holdout_samples: usize,
    /// n̄: the median PnP inliers of C_map's held-out samples, the support C_map was measured
    /// at ([`MapNoise::pose_covariance_at`]); 0 when C_map is the default or the map was saved
    /// before it (C_map then applies unscaled).
    pub holdout_inliers: f64,
    /// The held-out re-localizations themselves (build-time diagnostics, not stored in the
    /// map file: a loaded map has none).
    pub holdout: Vec<HoldoutSample>,
    /// Per axis (translation first), whether the held-out samples resolve C_map
    /// ([`noise::resolved_axes`]), kept in the map file so that a loaded map says what the
    /// built one did; None when they could not estimate it (or a file saved before it).
    pub resolved: Option<[bool; 6]>,
    /// The near regime: the map noise of a pose as close to the keyframes as they are to each
    /// other ([`NearNoise`], [`MapNoise::covariance_at`]); None: C_map at every distance (no
    /// keyframe pose covariances, C_map the default, or a file saved before it).
    pub near: Option<NearNoise>,
}

/// The map noise near the keyframes ([`noise`], "the near regime"): a query the distance ν
/// ([`noise::pose_distance`]: 10 cm or 5° count 1) from its nearest keyframe gets
///
///   C(ν) = (1 − w) C_near + w C_map,  w = clamp((ν − ν₀) / (ν₁ − ν₀), 0, 1),
///
/// C_near the keyframe poses' own variance, ν₀ the keyframes' median spacing and ν₁ the least
/// distance of a held-out keyframe C_map was measured from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NearNoise {
    /// C_near: diagonal, per axis the median variance of the keyframe poses in the labels'
    /// frame ([`LabelAdjustment::pose_variance`], or the given pose covariances of a map that
    /// keeps its labels), at most C_map's.
    pub covariance: Matrix6<f64>,
    /// ν₀: the median distance of a keyframe from its nearest other keyframe.
    pub spacing: f64,
    /// ν₁: the least distance, among C_map's held-out keyframes, of a held-out keyframe from
    /// the keyframes its re-localization kept (> ν₀).
    pub holdout_distance: f64,
}

impl MapNoise {
    /// The map noise of a pose resting on `inliers` PnP inliers (None: support unknown):
    ///
    ///   C_map(n) = C_map · max(1, n̄ / n),
    ///
    /// n̄ = [`MapNoise::holdout_inliers`]. The map-frame error a pose shares is that of the map
    /// points it rests on; with n of them it averages over n (∝ 1/n for independent point
    /// errors), so a pose with less support than the typical held-out keyframe shares more
    /// of it than C_map, their average, says. Never below C_map: a pose with more support
    /// than the held-out keyframes is not shown to share less (the points' errors are
    /// correlated through the keyframe poses that triangulated them). Unscaled when n̄ is 0
    /// (default C_map, or a map saved without it) or the support is unknown.
    pub fn pose_covariance_at(&self, inliers: Option<usize>) -> Matrix6<f64> {
        self.pose_covariance * self.support_scale(inliers)
    }

    /// The factor max(1, n̄/n) of [`MapNoise::pose_covariance_at`] (1 when unscaled).
    pub fn support_scale(&self, inliers: Option<usize>) -> f64 {
        match inliers {
            Some(n) if n > 0 && self.holdout_inliers > n as f64 => self.holdout_inliers / n as f64,
            _ => 1.0,
        }
    }

    /// w(ν) of [`NearNoise`]: the weight of C_map in the map noise of a pose at distance
    /// `novelty` from its nearest keyframe (1 without a near regime or a distance).
    pub fn novelty_weight(&self, novelty: Option<f64>) -> f64 {
        match (self.near, novelty) {
            (Some(near), Some(v)) => ((v - near.spacing) / (near.holdout_distance - near.spacing)).clamp(0.0, 1.0),
            _ => 1.0,
        }
    }

    /// The map noise of a pose resting on `inliers` PnP inliers at distance `novelty`
    /// ([`noise::pose_distance`]) from its nearest keyframe: (1 − w) C_near + w C_map·max(1, n̄/n)
    /// (w = [`MapNoise::novelty_weight`], C_map's support scaling as
    /// [`MapNoise::pose_covariance_at`]); C_map at the support alone without a near regime or
    /// a distance.
    pub fn covariance_at(&self, inliers: Option<usize>, novelty: Option<f64>) -> Matrix6<f64> {
        let w = self.novelty_weight(novelty);
        let far = self.pose_covariance_at(inliers) * w;
        match self.near {
            Some(near) if w < 1.0 => far + near.covariance * (1.0 - w),
            _ => far,
        }
    }

    /// Per axis, whether the held-out samples resolve C_map ([`noise::resolved_axes`], as
    /// estimated at build and stored in the map file); None when they cannot estimate it, or
    /// for a map saved before it was stored.
    pub fn resolved_axes(&self) -> Option<[bool; 6]> {
        self.resolved
    }

    /// Where C_map came from and the support it was measured at, in words: the one wording
    /// of `geoloc build-map`, `Map.map_noise` and `geoloc-rs info` ([`noise::describe`]).
    pub fn description(&self) -> String {
        noise::describe(self)
    }
}

/// One held-out keyframe re-localized against the rest of the map ([`Map::with_estimated_noise`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HoldoutSample {
    /// The keyframe.
    pub keyframe: usize,
    /// δ = log(T_label⁻¹ T_est)^∨ (right perturbation, translation first).
    pub delta: Vector6<f64>,
    /// The geometric locator's covariance C_G of T_est.
    pub covariance: Matrix6<f64>,
    /// PnP inliers of T_est.
    pub inliers: usize,
    /// Whether the C_map estimate used it (all do, unless there were too few for one).
    pub used: bool,
    /// Its distance from the keyframes its re-localization kept ([`noise::pose_distance`]).
    pub novelty: f64,
}

/// How to build the retrieval structure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RetrievalKind {
    /// Use the keyframes' global descriptors (all must have one, of equal length).
    Global,
    /// Train a BoW vocabulary of `branching`^`depth` words on the keyframes' descriptors.
    Bow {
        /// Children per node.
        branching: usize,
        /// Levels.
        depth: usize,
    },
    /// Both: the BoW vocabulary and the keyframes' global descriptors, combined by
    /// verification ([`fused_retrieval`]).
    Fused {
        /// Children per node.
        branching: usize,
        /// Levels.
        depth: usize,
    },
}

/// The retrieval methods by name (`"bow"`, `"global"`, `"fused"`), without their parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RetrievalMethod {
    /// Bag of words ([`RetrievalKind::Bow`]).
    Bow,
    /// Global descriptors ([`RetrievalKind::Global`]).
    Global,
    /// Both, combined by verification ([`RetrievalKind::Fused`]).
    Fused,
}

impl RetrievalMethod {
    /// Every method, in declaration order.
    pub const ALL: [Self; 3] = [Self::Bow, Self::Global, Self::Fused];

    /// The name: `"bow"`, `"global"` or `"fused"` (the one place that spells it).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Bow => "bow",
            Self::Global => "global",
            Self::Fused => "fused",
        }
    }

    /// The retrieval to build (`branching`, `depth` are used by BoW only).
    pub fn with(self, branching: usize, depth: usize) -> RetrievalKind {
        match self {
            Self::Bow => RetrievalKind::Bow { branching, depth },
            Self::Global => RetrievalKind::Global,
            Self::Fused => RetrievalKind::Fused { branching, depth },
        }
    }
}

impl std::str::FromStr for RetrievalMethod {
    type Err = GeolocError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL.into_iter().find(|m| m.as_str() == s).ok_or_else(|| {
            GeolocError::invalid("retrieval", format!("expected \"bow\", \"global\" or \"fused\", got {s:?}"))
        })
    }
}

impl std::fmt::Debug for Map {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let retrieval = match &self.retrieval {
            Retrieval::Global(index) => format!("global ({}-D)", index.dim()),
            Retrieval::Bow { vocabulary, .. } => format!("bow ({} words)", vocabulary.len()),
            Retrieval::Fused { vocabulary, index, .. } => {
                format!("fused (bow {} words, global {}-D)", vocabulary.len(), index.dim())
            }
        };
        f.debug_struct("Map")
            .field("camera", &self.camera)
            .field("keyframes", &self.keyframes.len())
            .field("pose_covariances", &self.pose_covariances.is_some())
            .field("retrieval", &retrieval)
            .field("model_points", &self.model.as_ref().map(SceneModel::len))
            .finish()
    }
}

impl Map {
    /// Builds the map and its retrieval structure: checks every keyframe, then builds the
    /// global-descriptor index or trains the BoW vocabulary (seeded by `seed`) and indexes
    /// the keyframes' words.
    ///
    /// # Errors
    /// Named as the Python caller spells them: no keyframes (`keyframes`), keypoint and
    /// descriptor counts that disagree or non-finite keypoints (`keypoints[i]`), mixed
    /// descriptor kinds or widths or non-finite float descriptors (`descriptors[i]`), missing,
    /// unequal or non-finite global descriptors (`global_descriptors`), a wrong count or a
    /// covariance that is not symmetric positive semi-definite (`pose_covariances[i]`), and
    /// the vocabulary's own limits (`branching`, `depth`).
    pub fn build(
        camera: Camera,
        keyframes: Vec<Keyframe>,
        pose_covariances: Option<Vec<Matrix6<f64>>>,
        kind: RetrievalKind,
        seed: u64,
    ) -> Result<Self> {
        check_keyframes(&keyframes)?;
        if let Some(c) = &pose_covariances {
            check_pose_covariances(c, keyframes.len())?;
        }
        let retrieval = match kind {
            RetrievalKind::Global => Retrieval::Global(global_index(&keyframes)?),
            RetrievalKind::Bow { branching, depth } => {
                let (vocabulary, database) = bow_retrieval(&keyframes, branching, depth, seed)?;
                Retrieval::Bow { vocabulary, database }
            }
            RetrievalKind::Fused { branching, depth } => {
                let index = global_index(&keyframes)?;
                let (vocabulary, database) = bow_retrieval(&keyframes, branching, depth, seed)?;
                Retrieval::Fused { vocabulary, database, index }
            }
        };
        Ok(Self {
            camera,
            keyframes,
            pose_covariances,
            retrieval,
            noise: MapNoise::default(),
            model: None,
            self_calibration: None,
            labels: None,
            group_matches: None,
        })
    }

    /// The map with its camera estimated from its own keyframes ([`crate::selfcal`]): tracks
    /// built as for the 3D model ([`SceneModel::build`] with [`calibration_tracks`]'s looser
    /// thresholds), the camera fitted to them with the keyframe poses fixed, then every
    /// keyframe keypoint u replaced by the corrected u_c = K d⁻¹(K′⁻¹u). When the tracks give
    /// no correction (too few, or one that does not invert at some keypoint) the keypoints
    /// stay as they were and [`Map::self_calibration`] says why. A 3D model built before is
    /// dropped (its points belong to the uncorrected keypoints): build it after, or with
    /// [`Map::with_refined_intrinsics_and_model`].
    ///
    /// # Errors
    /// The map was refined already (`intrinsics`); as [`SceneModel::build`] and
    /// [`self_calibrate`].
    pub fn with_refined_intrinsics(self, options: &SelfCalibrationOptions) -> Result<Self> {
        self.with_build_steps(&BuildSteps { calibration: Some(*options), ..BuildSteps::default() })
    }

    /// [`Map::with_refined_intrinsics`] then [`Map::with_model`], the same maps bit for bit,
    /// with the keyframe pairs' descriptor matching done once for both ([`PairMatches`]:
    /// it does not depend on the keypoints the correction moves) when `model`'s pair and
    /// matching options are [`calibration_tracks`]'s.
    ///
    /// # Errors
    /// As [`Map::with_refined_intrinsics`] and [`Map::with_model`].
    pub fn with_refined_intrinsics_and_model(
        self,
        calibration: &SelfCalibrationOptions,
        model: &ModelOptions,
    ) -> Result<Self> {
        self.with_build_steps(&BuildSteps {
            calibration: Some(*calibration),
            model: Some(*model),
            ..BuildSteps::default()
        })
    }

    /// The map with its pose labels corrected by bundle adjustment ([`crate::adjust`]):
    /// tracks as for the camera estimate ([`adjustment_tracks`]: pairs proposed by the
    /// labels, the epipolar check widened so that it does not decide between labels and
    /// images), then keyframe poses, points and the label-to-camera offset adjusted with the
    /// labels as robust priors. The keyframes' `world_from_cam` become the adjusted camera
    /// poses, `pose_covariances` their marginal covariances relative to the labels' frame
    /// (the adjusted labels' seen from the camera, the offset held: Ad_{X⁻¹} Σ_B Ad_{X⁻¹}ᵀ,
    /// as `adjust::camera_frame_covariance` gives it), and [`Map::labels`] keeps the
    /// labels and the report. A 3D model built before is dropped (it belongs to the labels).
    ///
    /// # Errors
    /// The map was adjusted already (`labels`); as [`SceneModel::build`] and
    /// [`crate::adjust::bundle_adjust`].
    pub fn with_adjusted_labels(self, options: &AdjustmentOptions) -> Result<Self> {
        self.with_build_steps(&BuildSteps { adjustment: Some(*options), ..BuildSteps::default() })
    }

    /// Runs the build steps `steps` (see [`BuildSteps`]); keyframe pairs are matched once for
    /// all of them when the model's pair and matching options are [`calibration_tracks`]'s.
    ///
    /// # Errors
    /// As the steps.
    pub fn with_build_steps(mut self, steps: &BuildSteps) -> Result<Self> {
        if steps.calibration.is_some() && self.self_calibration.as_ref().is_some_and(|s| s.correction.is_some()) {
            return Err(GeolocError::invalid("intrinsics", "the map's keypoints are corrected already"));
        }
        if steps.adjustment.is_some() && self.labels.is_some() {
            return Err(GeolocError::invalid("labels", "the map's labels are adjusted already"));
        }
        if let Some(o) = &steps.adjustment {
            o.check()?;
        }
        let tracks = calibration_tracks();
        // (the adjustment matches its own skeleton's pairs)
        let needs_pairs = steps.calibration.is_some() || (steps.adjustment.is_some() && steps.model.is_some());
        let pair_matches = if needs_pairs { Some(PairMatches::compute(&self.keyframes, &tracks)?) } else { None };
        // the labels first: a camera estimated with the labels' poses absorbs their fixed
        // rotation from the camera into the principal point (measured on 7-Scenes 0-599,
        // every third frame: 1.00 cm / 1.03 deg against the reference with the camera
        // estimated first, 0.77 cm / 0.81 deg with the labels adjusted on the nominal camera)
        if let Some(options) = &steps.adjustment {
            self.adjust_labels(options)?;
        }
        if let (Some(options), Some(pairs)) = (&steps.calibration, &pair_matches) {
            self.refine_intrinsics(options, &tracks, pairs)?;
            // corrected keypoints: adjust again, from the adjusted poses, with the σ found
            // (labels the first adjustment kept stay kept: there is nothing to refine)
            if let (Some(adjustment), Some(record)) = (&steps.adjustment, &self.labels)
                && record.applied
                && self.intrinsics_correction().is_some()
            {
                let again = AdjustmentOptions { label_sigma: Some(record.label_sigma), ..*adjustment };
                self.adjust_labels(&again)?;
            }
        }
        let covariances = self.pose_covariances.as_deref();
        self.model = match (&steps.model, &pair_matches) {
            (None, _) => None,
            // the pair matches serve: the model from them (its options checked as
            // SceneModel::build checks them)
            (Some(o), Some(pairs)) if pairs.serves(o) => {
                o.check()?;
                Some(SceneModel::assemble(&self.camera, &self.keyframes, covariances, o, pairs)?)
            }
            (Some(o), _) => Some(SceneModel::build(&self.camera, &self.keyframes, covariances, o)?),
        };
        // prepared from the final poses and keypoints (anything prepared before is stale)
        self.group_matches = None;
        if steps.group_matches {
            let o = crate::localizer::LocalizerOptions::default();
            self.group_matches = Some(GroupMatches::compute(&self, &o.matching, o.epipolar_px, &o.keyframes)?);
        }
        Ok(self)
    }

    fn refine_intrinsics(
        &mut self,
        options: &SelfCalibrationOptions,
        tracks: &ModelOptions,
        pair_matches: &PairMatches,
    ) -> Result<()> {
        self.group_matches = None; // the keypoints may change
        let covariances = self.pose_covariances.as_deref();
        let model = SceneModel::assemble(&self.camera, &self.keyframes, covariances, tracks, pair_matches)?;
        let observations: Vec<TrackObservation> = model
            .observations(&self.keyframes)
            .map(|(keyframe, point, pixel)| TrackObservation { keyframe, point, pixel })
            .collect();
        let mut calibration = self_calibrate(&self.camera, &self.poses(), &model.points, &observations, options)?;
        if let Some(correction) = calibration.correction {
            match self.corrected_keypoints(&correction) {
                Ok(corrected) => {
                    for (kf, keypoints) in self.keyframes.iter_mut().zip(corrected) {
                        kf.keypoints = keypoints;
                    }
                }
                Err(e) => {
                    calibration.correction = None;
                    calibration.reason = format!("not applied: {e}");
                }
            }
        }
        self.self_calibration = Some(calibration);
        Ok(())
    }

    /// Adjusts the skeleton of keyframes ([`crate::adjust::skeleton`]: each at least
    /// [`crate::adjust::CORRELATION_SPACING`] from the last) and carries the corrections to
    /// the keyframes between by interpolation: Δ_k = L_k⁻¹ B_k, interpolated on SE(3) between
    /// the skeleton keyframes around k by capture index (label errors drift over tens of
    /// frames; keyframes closer than the spacing see the same images and add little but
    /// rounds and time). A keyframe between takes the marginal covariance of its nearer
    /// skeleton keyframe.
    fn adjust_labels(&mut self, options: &AdjustmentOptions) -> Result<()> {
        self.group_matches = None; // the poses change
        // a map adjusted before starts from its adjusted poses, its labels stay the priors
        // the first adjustment re-places the segments that jumps in the labels cut off
        // (label_breaks), then closes the revisits whose labels disagree with the images
        // (label_loops); a re-adjustment keeps what the first one found
        let (labels, start, offset, correlation, (breaks, replaced, loops)) = match self.labels.take() {
            Some(record) => (
                record.labels.clone(),
                record.label_poses(&self.poses()),
                record.offset,
                Some(record.correlation_keyframes),
                (record.breaks, record.replaced, record.loops),
            ),
            None => {
                let labels = self.poses();
                let (start, breaks, replaced) = label_breaks::repaired_start(self, &labels)?;
                let (start, loops) = label_loops::closed_start(self, &start)?;
                (labels, start, SE3::identity(), None, (breaks, replaced, loops))
            }
        };
        // tracks from the start poses where a segment was re-placed or a loop closed (from
        // the labels, they would keep it an island), else from the keyframes' poses
        let moved = correlation.is_none()
            && (replaced.iter().any(|r| r.correction.is_some()) || loops.iter().any(|l| l.closed));
        let problem = self.skeleton_problem(&labels, &start, moved.then_some(&start[..]))?;
        let chosen = &problem.keyframes;
        let adjustment = crate::adjust::bundle_adjust_with_candidates(
            &self.camera,
            &problem.labels,
            (&problem.start, &offset),
            &problem.points,
            &problem.observations,
            &problem.candidates,
            options,
        )?;
        let (adjusted, nearest) = interpolated_corrections(&labels, chosen, &adjustment.label_poses);
        let of_nearest = |c: &[Matrix6<f64>]| -> Vec<Matrix6<f64>> { nearest.iter().map(|&s| c[s]).collect() };
        let marginal = of_nearest(&adjustment.label_pose_covariances);
        let neighbourhood = of_nearest(&adjustment.label_neighbourhood_covariances);
        let mut record = LabelAdjustment::with_poses(labels, &adjusted, (&marginal, &neighbourhood), &adjustment);
        if let Some(tau) = correlation {
            // re-adjusted with the σ found before: keep how it was found
            record.correlation_keyframes = tau;
        }
        (record.breaks, record.replaced, record.loops) = (breaks, replaced, loops);
        // labels the images do not contradict stay as they are (the record says so); the
        // decision is the first adjustment's, a re-adjustment refines an applied one
        record.applied = correlation.is_some() || record.significant();
        if record.applied {
            let x = adjustment.offset;
            for (kf, b) in self.keyframes.iter_mut().zip(&adjusted) {
                kf.world_from_cam = *b * x;
            }
            // relative to the labels' frame: the offset's uncertainty is not the answers' error
            let covariances =
                nearest.iter().map(|&s| camera_frame_covariance(&x, &adjustment.label_pose_covariances[s]));
            self.pose_covariances = Some(covariances.collect());
        }
        self.labels = Some(record);
        self.model = None;
        Ok(())
    }

    /// The problem the labels' adjustment of this map solves ([`Map::with_adjusted_labels`]):
    /// the skeleton keyframes, their labels as the priors and the start, the points
    /// triangulated from the labels and the observations of the tracks (pairs proposed by the
    /// labels, see [`adjustment_tracks`]) — what [`crate::adjust::bundle_adjust`] takes, for
    /// adjusting it elsewhere (a peer's adjuster on the same problem) or with other options.
    ///
    /// # Errors
    /// The map's labels were adjusted already (`labels`: the problem is that of the labels as
    /// given); as [`PairMatches::compute`] and [`SceneModel::assemble`].
    pub fn label_adjustment_problem(&self) -> Result<AdjustmentProblem> {
        if self.labels.is_some() {
            return Err(GeolocError::invalid("labels", "the map's labels are adjusted already"));
        }
        let poses = self.poses();
        self.skeleton_problem(&poses, &poses, None)
    }

    /// The adjustment problem of the skeleton of `start` ([`crate::adjust::skeleton`]): the
    /// labels `labels` and the start poses `start` (one per keyframe) picked at the skeleton's
    /// keyframes, with the tracks the skeleton's pairs give — paired, checked and triangulated
    /// with the camera poses `track_poses` (one per keyframe; None: the keyframes' own).
    fn skeleton_problem(
        &self,
        labels: &[SE3],
        start: &[SE3],
        track_poses: Option<&[SE3]>,
    ) -> Result<AdjustmentProblem> {
        let chosen = crate::adjust::skeleton(start);
        let keyframes: Vec<Keyframe> = chosen
            .iter()
            .map(|&k| match track_poses {
                Some(poses) => Keyframe { world_from_cam: poses[k], ..self.keyframes[k].clone() },
                None => self.keyframes[k].clone(),
            })
            .collect();
        let tracks = adjustment_tracks();
        let pairs = PairMatches::compute(&keyframes, &tracks)?;
        let (model, rejected) = SceneModel::assemble_with_rejected(&self.camera, &keyframes, None, &tracks, &pairs)?;
        // every keypoint alike (σ 1): weighted by its detector scale (ORB 1.2^level) the
        // adjustment moved the 7-Scenes folds both ways — translation medians down on four,
        // rotation up on five (400–499 0.60 → 0.91°), recall down on five (docs/labels.md)
        let observations: Vec<Observation> = model
            .observations(&keyframes)
            .map(|(keyframe, point, pixel)| Observation { keyframe, point, pixel, sigma: 1.0 })
            .collect();
        let candidates = rejected
            .iter()
            .map(|v| Observation {
                keyframe: v.keyframe,
                point: v.point,
                pixel: keyframes[v.keyframe].keypoints[v.keypoint],
                sigma: 1.0,
            })
            .collect();
        let pick = |v: &[SE3]| chosen.iter().map(|&k| v[k]).collect::<Vec<_>>();
        Ok(AdjustmentProblem {
            labels: pick(labels),
            start: pick(start),
            points: model.points,
            observations,
            candidates,
            keyframes: chosen,
        })
    }

    /// The keyframe poses in the labels' convention: T_k X⁻¹ when the map applied its
    /// labels' adjustment, else the keyframes' poses (the labels).
    pub fn keyframe_label_poses(&self) -> Vec<SE3> {
        let poses = self.poses();
        match &self.labels {
            Some(l) => l.label_poses(&poses),
            None => poses,
        }
    }

    /// A localization against this map as the camera's own pose, with the label-to-camera
    /// offset's covariance added ([`LabelAdjustment::localization_to_camera`]; unchanged when
    /// the map did not apply a labels' adjustment).
    pub fn to_camera_convention(&self, localization: crate::localizer::Localization) -> crate::localizer::Localization {
        match &self.labels {
            Some(l) => l.localization_to_camera(localization),
            None => localization,
        }
    }

    /// A localization against this map in the labels' convention (unchanged when the map did
    /// not apply a labels' adjustment).
    pub fn to_label_convention(&self, localization: crate::localizer::Localization) -> crate::localizer::Localization {
        match &self.labels {
            Some(l) => l.localization_to_label(localization),
            None => localization,
        }
    }

    /// The camera correction the map applies to keypoints, if any.
    pub fn intrinsics_correction(&self) -> Option<&IntrinsicsCorrection> {
        self.self_calibration.as_ref().and_then(|s| s.correction.as_ref())
    }

    /// Every keyframe's keypoints corrected by `correction`.
    fn corrected_keypoints(&self, correction: &IntrinsicsCorrection) -> Result<Vec<Vec<Vector2<f64>>>> {
        self.keyframes
            .iter()
            .enumerate()
            .map(|(k, kf)| correction.correct_all(&self.camera, &format!("keypoints[{k}]"), &kf.keypoints))
            .collect()
    }

    /// The map with its 3D model built from all keyframes ([`SceneModel::build`]).
    ///
    /// # Errors
    /// As [`SceneModel::build`].
    pub fn with_model(mut self, options: &ModelOptions) -> Result<Self> {
        self.model = Some(SceneModel::build(&self.camera, &self.keyframes, self.pose_covariances.as_deref(), options)?);
        Ok(self)
    }

    /// The world_from_cam poses of the keyframes.
    pub fn poses(&self) -> Vec<SE3> {
        self.keyframes.iter().map(|k| k.world_from_cam).collect()
    }

    /// The keyframe most similar to a query (by its global descriptor, by its local
    /// descriptors through BoW, or both verified by its keypoints; ties go to the lower index).
    ///
    /// # Errors
    /// A query without what the map's retrieval needs, or of the wrong size
    /// (`global_descriptor`, `descriptors`).
    pub fn retrieve(&self, query: &RetrievalQuery<'_>) -> Result<usize> {
        // retrieve_top returns at least one keyframe or an error
        Ok(self.retrieve_top(query, 1, 0..0)?[0])
    }

    /// The `k` keyframes most similar to a query, best first, skipping those in `excluded`
    /// (the ranking of [`Map::retrieve`]; fewer when the map has fewer). A fused map
    /// verifies up to 2k candidates ([`fused_retrieval`]).
    ///
    /// # Errors
    /// A query without what the map's retrieval needs, or of the wrong size
    /// (`global_descriptor`, `descriptors`, `keypoints`); every keyframe excluded
    /// (`descriptors`); `k` 0 (`top_k`).
    pub fn retrieve_top(
        &self,
        query: &RetrievalQuery<'_>,
        k: usize,
        excluded: std::ops::Range<usize>,
    ) -> Result<Vec<usize>> {
        self.retrieve_ranked(query, k, excluded, Ranking::Map)
    }

    /// [`Map::retrieve_top`] by the given ranking: a fused map answers by its bag of words
    /// alone with [`Ranking::Words`] (the query's global descriptor is still checked); other
    /// maps have one ranking.
    ///
    /// # Errors
    /// As [`Map::retrieve_top`].
    pub fn retrieve_ranked(
        &self,
        query: &RetrievalQuery<'_>,
        k: usize,
        excluded: std::ops::Range<usize>,
        ranking: Ranking,
    ) -> Result<Vec<usize>> {
        if k == 0 {
            return Err(GeolocError::invalid("top_k", "must be ≥ 1"));
        }
        let n = self.keyframes.len();
        let want = (excluded.end.min(n).saturating_sub(excluded.start) + k).min(n);
        let kept =
            |ranked: Vec<usize>| -> Vec<usize> { ranked.into_iter().filter(|i| !excluded.contains(i)).collect() };
        let top: Vec<usize> = match &self.retrieval {
            Retrieval::Global(index) => kept(global_ranking(index, query.global, want)?).into_iter().take(k).collect(),
            Retrieval::Bow { vocabulary, database } => {
                kept(bow_ranking(vocabulary, database, &query.descriptors, want)?).into_iter().take(k).collect()
            }
            Retrieval::Fused { vocabulary, database, index } if ranking == Ranking::Words => {
                checked_global(index, query.global)?;
                kept(bow_ranking(vocabulary, database, &query.descriptors, want)?).into_iter().take(k).collect()
            }
            Retrieval::Fused { vocabulary, database, index } => {
                let bow = kept(bow_ranking(vocabulary, database, &query.descriptors, want)?);
                let network = kept(global_ranking(index, query.global, want)?);
                self.fused(query, &bow, &fused_retrieval::network_candidates(&bow, &network, k), k)?
            }
        };
        if top.is_empty() {
            return Err(GeolocError::invalid("descriptors", "the map has no keyframes outside the excluded ones"));
        }
        Ok(top)
    }

    /// A query's keypoints (the caller's undistorted pixels) as the keyframes' are stored:
    /// corrected by the map's camera estimate when it has one (u_c = K d⁻¹(K′⁻¹u)), else as
    /// given.
    ///
    /// # Errors
    /// A keypoint the lens correction does not invert (`keypoints`).
    pub fn query_keypoints<'k>(&self, keypoints: &'k [Vector2<f64>]) -> Result<Cow<'k, [Vector2<f64>]>> {
        Ok(match self.intrinsics_correction() {
            Some(c) => Cow::Owned(c.correct_all(&self.camera, "keypoints", keypoints)?),
            None => Cow::Borrowed(keypoints),
        })
    }

    /// [`Map::retrieve_top`] for a query whose keypoints are in the caller's pixels: corrected
    /// by the map's camera estimate first, as the localizer corrects a frame's
    /// (u_c = K d⁻¹(K′⁻¹u)), then the `k` best keyframes.
    ///
    /// # Errors
    /// As [`Map::retrieve_top`]; a keypoint the lens correction does not invert (`keypoints`).
    pub fn retrieve_frame(&self, query: &RetrievalQuery<'_>, k: usize) -> Result<Vec<usize>> {
        let corrected = self.query_keypoints(query.keypoints)?;
        self.retrieve_top(&RetrievalQuery { keypoints: &corrected, ..*query }, k, 0..0)
    }

    /// The first `k` of the fused ranking of BoW's `bow` and the `network` candidates
    /// ([`fused_retrieval`]).
    fn fused(&self, query: &RetrievalQuery<'_>, bow: &[usize], network: &[usize], k: usize) -> Result<Vec<usize>> {
        if query.keypoints.len() != query.descriptors.len() {
            return Err(GeolocError::invalid(
                "keypoints",
                format!("{} keypoints for {} descriptors", query.keypoints.len(), query.descriptors.len()),
            ));
        }
        if network.is_empty() {
            return Ok(bow.iter().copied().take(k).collect());
        }
        // BoW's first keyframe and the network candidates, verified in parallel (in order)
        let verified: Vec<usize> = bow.iter().copied().take(1).chain(network.iter().copied()).collect();
        let scores = crate::parallel::map_slice(&verified, 2, |&c| {
            let kf = &self.keyframes[c];
            fused_retrieval::verified_inliers(
                &self.camera,
                query.keypoints,
                &query.descriptors,
                &kf.keypoints,
                &kf.descriptors.view(),
            )
        })
        .into_iter()
        .collect::<Result<Vec<_>>>()?;
        let (bow_score, scores) = if bow.is_empty() { (0, &scores[..]) } else { (scores[0], &scores[1..]) };
        Ok(fused_retrieval::fused_order(bow, bow_score, network, scores, k))
    }
}

/// What retrieval compares a query by: its undistorted keypoints and their local descriptors
/// (BoW, and the verification of a fused map), and its global descriptor (maps that retrieve
/// by global descriptors, or fused).
#[derive(Clone, Copy, Debug)]
pub struct RetrievalQuery<'a> {
    /// Undistorted keypoints (px), one per descriptor.
    pub keypoints: &'a [Vector2<f64>],
    /// Local descriptors.
    pub descriptors: Descriptors<'a>,
    /// The global descriptor, if any.
    pub global: Option<&'a [f32]>,
}

/// Which ranking [`Map::retrieve_ranked`] answers by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ranking {
    /// The map's own: BoW, the network, or their fusion.
    Map,
    /// A fused map's bag of words alone (the same as `Map` for other maps).
    Words,
}

/// The keyframes by global-descriptor distance, nearest first (`want` of them).
fn global_ranking(index: &DescriptorIndex, global: Option<&[f32]>, want: usize) -> Result<Vec<usize>> {
    let g = checked_global(index, global)?;
    Ok(index.query(g, want)?.1)
}

/// The query's global descriptor, present, of the index's size and finite.
fn checked_global<'g>(index: &DescriptorIndex, global: Option<&'g [f32]>) -> Result<&'g [f32]> {
    let g = global.ok_or_else(|| {
        GeolocError::invalid("global_descriptor", "this map retrieves by global descriptor; give one")
    })?;
    if g.len() != index.dim() {
        return Err(GeolocError::invalid(
            "global_descriptor",
            format!("expected {} values, got {}", index.dim(), g.len()),
        ));
    }
    if let Some(i) = g.iter().position(|v| !v.is_finite()) {
        return Err(GeolocError::NonFinite { name: "global_descriptor".into(), index: i });
    }
    Ok(g)
}

/// The keyframes by BoW score, best first (`want` of them at most).
fn bow_ranking(
    vocabulary: &Vocabulary,
    database: &BowDatabase,
    descriptors: &Descriptors<'_>,
    want: usize,
) -> Result<Vec<usize>> {
    let words = vocabulary.words_of(descriptors)?;
    Ok(database.query(&words, want).into_iter().map(|(i, _)| i).collect())
}

/// The tracks [`Map::with_refined_intrinsics`] fits the camera to: the 3D model's, with the
/// epipolar check and the reprojection limit widened (4 and 8 px: the nominal camera may be
/// off by more than the model's 2 / 4 px at the image borders) and at least three
/// observations per track (two views fit any camera).
pub fn calibration_tracks() -> ModelOptions {
    let model = ModelOptions::default();
    ModelOptions {
        epipolar_px: 4.0,
        triangulation: TriangulationOptions { max_residual_px: 8.0, ..model.triangulation },
        min_track_length: 3,
        ..model
    }
}

/// The tracks [`Map::with_adjusted_labels`] adjusts: [`calibration_tracks`]' pairs and
/// matches, with the epipolar check and the reprojection limit widened to 12 px (labels a few
/// centimetres and a degree off move points by that much: the adjustment's robust loss and
/// its outlier rejection decide, not the labels), and [`ADJUSTMENT_REVISITS`] revisit pairs
/// per keyframe at least [`ADJUSTMENT_REVISIT_GAP`] skeleton keyframes apart in capture order:
/// the pairs whose label errors are independent are the ones that correct them. With the
/// nearest baselines alone a part of the trajectory that only revisits a place shares no pair
/// with the rest and keeps its labels' error (7-Scenes frames 0–84 of a map without 85–214:
/// no pair to the rest, 1.4° off the reference after the adjustment — its labels were 1.0°
/// off —, with revisits 0.5–0.6°).
pub fn adjustment_tracks() -> ModelOptions {
    let calibration = calibration_tracks();
    ModelOptions {
        epipolar_px: ADJUSTMENT_EPIPOLAR_PX,
        triangulation: TriangulationOptions { max_residual_px: ADJUSTMENT_EPIPOLAR_PX, ..calibration.triangulation },
        revisit_neighbours: ADJUSTMENT_REVISITS,
        revisit_gap: ADJUSTMENT_REVISIT_GAP,
        ..calibration
    }
}

/// The epipolar check and the triangulation's reprojection limit of the labels' adjustment's
/// tracks ([`adjustment_tracks`], px): labels a few centimetres and a degree off move points
/// by that much.
pub const ADJUSTMENT_EPIPOLAR_PX: f64 = 12.0;

/// Revisit pairs per skeleton keyframe in the labels' adjustment ([`adjustment_tracks`]).
pub const ADJUSTMENT_REVISITS: usize = 6;
/// Fewest skeleton keyframes between a revisit pair's two keyframes in capture order: 20
/// skeleton steps are ≥ 0.5 m of travel or 30° of turn ([`crate::adjust::CORRELATION_SPACING`]),
/// about as long as the labels' errors stay correlated (τ ≈ 9 steps in translation, 21 in
/// rotation on 7-Scenes frames 0–599).
pub const ADJUSTMENT_REVISIT_GAP: usize = 20;

/// The adjusted poses B_k = L_k Δ_k of every keyframe from those of the skeleton `chosen`
/// (B_s for s ∈ chosen, in order): Δ interpolated on SE(3) by capture index between the
/// skeleton keyframes around k (the nearest one's outside them); and for each keyframe the
/// position in `chosen` of its nearer skeleton keyframe.
fn interpolated_corrections(labels: &[SE3], chosen: &[usize], adjusted: &[SE3]) -> (Vec<SE3>, Vec<usize>) {
    let delta: Vec<SE3> = chosen.iter().zip(adjusted).map(|(&k, b)| labels[k].inverse() * *b).collect();
    let mut poses = Vec::with_capacity(labels.len());
    let mut nearest = Vec::with_capacity(labels.len());
    let mut i = 0;
    for (k, label) in labels.iter().enumerate() {
        while i + 1 < chosen.len() && chosen[i + 1] <= k {
            i += 1;
        }
        let (d, n) = if k <= chosen[i] || i + 1 == chosen.len() {
            (delta[i], i)
        } else {
            let alpha = (k - chosen[i]) as f64 / (chosen[i + 1] - chosen[i]) as f64;
            (delta[i].interpolate(&delta[i + 1], alpha), if alpha < 0.5 { i } else { i + 1 })
        };
        poses.push(*label * d);
        nearest.push(n);
    }
    (poses, nearest)
}

/// Every keyframe: as many finite keypoints as descriptors, descriptors valid and of
/// keyframe 0's kind and width, that width one a frame stream can carry
/// ([`crate::frames::MAX_DESCRIPTOR_WIDTH`]: a map that builds is one geoloc-rs can localize
/// against).
fn check_keyframes(keyframes: &[Keyframe]) -> Result<()> {
    let Some(first) = keyframes.first() else {
        return Err(GeolocError::invalid("keyframes", "the map needs at least one keyframe"));
    };
    let width = first.descriptors.view().width();
    if width > crate::frames::MAX_DESCRIPTOR_WIDTH {
        return Err(GeolocError::invalid(
            "descriptors",
            format!("width {width} is beyond the {} a frame stream carries", crate::frames::MAX_DESCRIPTOR_WIDTH),
        ));
    }
    let kind = |d: &DescriptorSet| (d.view().is_binary(), d.view().width());
    for (i, kf) in keyframes.iter().enumerate() {
        kf.descriptors.view().check(&format!("descriptors[{i}]"))?;
        if kf.keypoints.len() != kf.descriptors.len() {
            return Err(GeolocError::invalid(
                format!("keypoints[{i}]"),
                format!("{} keypoints but {} descriptors", kf.keypoints.len(), kf.descriptors.len()),
            ));
        }
        if let Some(j) = kf.keypoints.iter().position(|k| !(k.x.is_finite() && k.y.is_finite())) {
            return Err(GeolocError::NonFinite { name: format!("keypoints[{i}]"), index: j });
        }
        if kind(&kf.descriptors) != kind(&first.descriptors) {
            return Err(GeolocError::invalid(
                format!("descriptors[{i}]"),
                "descriptors differ in kind or width from keyframe 0's",
            ));
        }
    }
    Ok(())
}

/// One covariance per keyframe, each symmetric positive semi-definite.
fn check_pose_covariances(covariances: &[Matrix6<f64>], keyframes: usize) -> Result<()> {
    if covariances.len() != keyframes {
        return Err(GeolocError::invalid(
            "pose_covariances",
            format!("has {} entries for {keyframes} keyframes", covariances.len()),
        ));
    }
    check_covariances("pose_covariances", covariances)
}

/// (a) by global descriptor: the exact index over the keyframes' descriptors.
fn global_index(keyframes: &[Keyframe]) -> Result<DescriptorIndex> {
    let dim = keyframes[0].global.as_ref().map_or(0, Vec::len);
    let mut data = Vec::with_capacity(dim * keyframes.len());
    for (i, kf) in keyframes.iter().enumerate() {
        match &kf.global {
            Some(g) if g.len() == dim && dim > 0 => data.extend_from_slice(g),
            _ => {
                return Err(GeolocError::invalid(
                    "global_descriptors",
                    format!("keyframes[{i}] needs a global descriptor of length {dim}"),
                ));
            }
        }
    }
    if dim > crate::frames::MAX_GLOBAL_DIM {
        return Err(GeolocError::invalid(
            "global_descriptors",
            format!("length {dim} is beyond the {} a frame stream carries", crate::frames::MAX_GLOBAL_DIM),
        ));
    }
    if let Some(v) = data.iter().position(|v| !v.is_finite()) {
        return Err(GeolocError::NonFinite { name: "global_descriptors".into(), index: v / dim });
    }
    DescriptorIndex::new(data, dim)
}

/// (a) by bag of words: a vocabulary trained on every keyframe's descriptors, and the
/// TF-IDF database of the keyframes' words.
fn bow_retrieval(
    keyframes: &[Keyframe],
    branching: usize,
    depth: usize,
    seed: u64,
) -> Result<(Vocabulary, BowDatabase)> {
    let all = DescriptorSet::stack(keyframes.iter().map(|k| &k.descriptors));
    let vocabulary = Vocabulary::train(&all.view(), branching, depth, seed)?;
    let words: Vec<Vec<u32>> =
        keyframes.iter().map(|k| vocabulary.words_of(&k.descriptors.view())).collect::<Result<_>>()?;
    let database = BowDatabase::with_weighting(vocabulary.len(), &words, vocabulary.term_weighting())?;
    Ok((vocabulary, database))
}
