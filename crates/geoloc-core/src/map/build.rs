//! How a map is built, in one place: every build option, its default, and the recipe that
//! turns them into build steps.
//!
//! [`Map::build_with_options`] is what `geoloc.Map.build` / `geoloc.Map.from_features` and
//! every other front end call: the retrieval structure ([`Map::build`]), then
//! [`Map::with_build_steps`] — the labels' adjustment, the camera estimate, the 3D model,
//! the paper locator's prepared pair matches — then, when asked, the map's own noise
//! ([`Map::with_estimated_noise`]). The front ends take each option as "given or the
//! default" and never spell a default themselves.

use nalgebra::Matrix6;

use super::{BuildSteps, Keyframe, Map, ModelOptions, RetrievalMethod};
use crate::adjust::AdjustmentOptions;
use crate::camera::Camera;
use crate::error::Result;
use crate::localizer::NoiseOptions;
use crate::selfcal::{IntrinsicsModel, SelfCalibrationOptions};

/// The options of a map build that a user sets; [`Default`] is geoloc's recommended build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildOptions {
    /// Retrieval by bag of words (no network; default) or by the keyframes' global descriptors.
    pub retrieval: RetrievalMethod,
    /// BoW vocabulary: children per node (default 10).
    pub branching: usize,
    /// BoW vocabulary: levels (default 3: 10³ words).
    pub depth: usize,
    /// Seed of the vocabulary's k-means / k-majority (default 0).
    pub seed: u64,
    /// Estimate the map's own noise once built: C_map from held-out keyframes and, with
    /// timestamps, the motion model's process noise (default true).
    pub estimate_noise: bool,
    /// Build and store the map-level 3D model of the default (model) locator (default true;
    /// false: a model localizer builds it when it starts, the paper's does not need it).
    pub model: bool,
    /// Estimate the camera (focal lengths, principal point, distortion) from the keyframes'
    /// tracks and correct the keypoints with it (default true).
    pub refine_intrinsics: bool,
    /// The camera model the estimate fits (default radial-tangential).
    pub intrinsics_model: IntrinsicsModel,
    /// Correct the pose labels by bundle adjustment (default true).
    pub adjust_labels: bool,
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self {
            retrieval: RetrievalMethod::Bow,
            branching: 10,
            depth: 3,
            seed: 0,
            estimate_noise: true,
            model: true,
            refine_intrinsics: true,
            intrinsics_model: SelfCalibrationOptions::default().model,
            adjust_labels: true,
        }
    }
}

impl BuildOptions {
    /// The build steps these options ask for, each with the core's default options; the
    /// paper locator's pair matches are always prepared.
    pub fn steps(&self) -> BuildSteps {
        BuildSteps {
            calibration: self
                .refine_intrinsics
                .then(|| SelfCalibrationOptions { model: self.intrinsics_model, ..SelfCalibrationOptions::default() }),
            adjustment: self.adjust_labels.then(AdjustmentOptions::default),
            model: self.model.then(ModelOptions::default),
            group_matches: true,
        }
    }
}

impl Map {
    /// Builds a map with `options`: the retrieval structure, the build steps
    /// ([`BuildOptions::steps`]) and, with `options.estimate_noise`, the map's noise
    /// (`timestamps`, one per keyframe in seconds and strictly increasing, feed the motion
    /// model's process noise; None: no process noise).
    ///
    /// # Errors
    /// Those of [`Map::build`], [`Map::with_build_steps`] and [`Map::with_estimated_noise`].
    pub fn build_with_options(
        camera: Camera,
        keyframes: Vec<Keyframe>,
        pose_covariances: Option<Vec<Matrix6<f64>>>,
        timestamps: Option<&[f64]>,
        options: &BuildOptions,
    ) -> Result<Self> {
        let kind = options.retrieval.with(options.branching, options.depth);
        let map =
            Self::build(camera, keyframes, pose_covariances, kind, options.seed)?.with_build_steps(&options.steps())?;
        if options.estimate_noise { map.with_estimated_noise(timestamps, &NoiseOptions::default()) } else { Ok(map) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_steps_adjust_calibrate_model_and_prepare() {
        let steps = BuildOptions::default().steps();
        assert_eq!(steps.adjustment, Some(AdjustmentOptions::default()));
        assert_eq!(steps.calibration, Some(SelfCalibrationOptions::default()));
        assert_eq!(steps.model, Some(ModelOptions::default()));
        assert!(steps.group_matches);
    }

    #[test]
    fn every_switch_off_leaves_only_the_prepared_matches() {
        let options =
            BuildOptions { refine_intrinsics: false, adjust_labels: false, model: false, ..BuildOptions::default() };
        assert_eq!(options.steps(), BuildSteps { group_matches: true, ..BuildSteps::default() });
        let modelled = BuildOptions { model: true, intrinsics_model: IntrinsicsModel::Pinhole, ..options };
        assert_eq!(modelled.steps().model, Some(ModelOptions::default()));
        let calibrated = BuildOptions { refine_intrinsics: true, ..modelled };
        assert_eq!(calibrated.steps().calibration.map(|c| c.model), Some(IntrinsicsModel::Pinhole));
    }
}
