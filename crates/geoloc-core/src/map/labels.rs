//! The map's pose labels corrected by bundle adjustment ([`crate::adjust`]): what the labels
//! were, the label-to-camera offset, each label's correction and its significance, and the
//! runs of keyframes whose labels disagree with the images.
//!
//! After [`super::Map::with_adjusted_labels`] the keyframes' `world_from_cam` are the adjusted
//! *camera* poses T_k = B_k X (what triangulation and PnP need), `pose_covariances` their
//! marginal covariances, and [`LabelAdjustment`] keeps the labels L_k, X = label_from_cam and
//! the report. A pose in the labels' convention is T X⁻¹ ([`LabelAdjustment::to_label`]).

use nalgebra::{Matrix6, Vector6};

use crate::adjust::{Adjustment, LabelSigma, correction};
use crate::lie::{SE3, se3};
use crate::stats::chi2::CHI2_6_999;
use crate::stats::{EvenMedian, median};

/// χ²₆ 99.9 % quantile: a correction beyond it is significant.
pub const SIGNIFICANT_CORRECTION_CHI2: f64 = CHI2_6_999;

/// Fewest consecutive keyframes with significant corrections that make a run.
pub const MIN_RUN_LENGTH: usize = 3;

/// The labels and what the adjustment found about them.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelAdjustment {
    /// L_k: the labels as given (world_from_label).
    pub labels: Vec<SE3>,
    /// X = label_from_cam.
    pub offset: SE3,
    /// Covariance of X (right perturbation, translation first).
    pub offset_covariance: Matrix6<f64>,
    /// Per keyframe: e_k = log(L_k⁻¹ B_k) (right perturbation, translation first).
    pub corrections: Vec<Vector6<f64>>,
    /// Per keyframe: e_kᵀ Σ_k⁻¹ e_k with Σ_k the adjusted label pose's marginal covariance.
    pub significance: Vec<f64>,
    /// Per twist axis (translation first), the median over the keyframes of the variance of
    /// the adjusted label pose B_k as a perturbation of the camera pose T_k = B_k X with X
    /// held fixed: diag(Ad_{X⁻¹} Σ_k Ad_{X⁻¹}ᵀ) (B_k exp(ε) X = T_k exp(Ad_{X⁻¹} ε)). How well
    /// the map's poses are known in the labels' frame, without the offset's own uncertainty
    /// (which a result in the labels' convention, T X⁻¹, does not carry): the map noise of a
    /// query as close to the keyframes as they are to each other
    /// ([`crate::map::noise`], the near regime). Zero in files saved before it.
    pub pose_variance: Vector6<f64>,
    /// The labels' σ the adjustment used.
    pub label_sigma: LabelSigma,
    /// τ of the label corrections (translation, rotation; keyframes): how many neighbouring
    /// keyframes share a label error ([`crate::adjust::correlation_lengths`]).
    pub correlation_keyframes: (f64, f64),
    /// RMS reprojection error (px) with the labels and after the adjustment.
    pub rms_px: (f64, f64),
    /// Observations the adjustment used, and those it rejected.
    pub observations: (usize, usize),
    /// Whether the map uses the adjustment: false when no label correction and not the
    /// offset is significant ([`LabelAdjustment::significant`]) — the images then agree with
    /// the labels, and the map keeps them (its keyframes hold the labels, results need no
    /// conversion).
    pub applied: bool,
}

/// A run of consecutive keyframes whose labels the images correct significantly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelRun {
    /// First keyframe.
    pub start: usize,
    /// One past the last keyframe.
    pub end: usize,
    /// Largest translation correction in the run (m).
    pub max_translation_m: f64,
    /// Largest rotation correction in the run (rad).
    pub max_rotation_rad: f64,
}

impl LabelAdjustment {
    /// The record of `adjustment` of `labels` (one adjusted pose per label).
    pub fn new(labels: Vec<SE3>, adjustment: &Adjustment) -> Self {
        Self::with_poses(labels, &adjustment.label_poses, &adjustment.label_pose_covariances, adjustment)
    }

    /// The record of `labels` adjusted to `adjusted` (world_from_label) with the marginal
    /// covariances `covariances`, the rest from `adjustment` (which may have adjusted a
    /// subset of the keyframes).
    pub fn with_poses(
        labels: Vec<SE3>,
        adjusted: &[SE3],
        covariances: &[Matrix6<f64>],
        adjustment: &Adjustment,
    ) -> Self {
        let (corrections, significance) =
            labels.iter().zip(adjusted).zip(covariances).map(|((l, b), c)| correction(l, b, c)).unzip();
        let pose_variance = camera_frame_variance(&adjustment.offset, covariances);
        let used = adjustment.inliers.iter().filter(|i| **i).count();
        Self {
            labels,
            offset: adjustment.offset,
            offset_covariance: adjustment.offset_covariance,
            corrections,
            significance,
            pose_variance,
            label_sigma: adjustment.label_sigma,
            correlation_keyframes: adjustment.correlation_keyframes,
            rms_px: adjustment.rms_px,
            observations: (used, adjustment.inliers.len() - used),
            applied: true,
        }
    }

    /// Whether the images disagree with the labels: some correction or the offset beyond
    /// [`SIGNIFICANT_CORRECTION_CHI2`] (e_Xᵀ Σ_X⁻¹ e_X for the offset, e_X = log(X)). A
    /// singular Σ_X counts the offset as not significant (0, where [`correction`] gives ∞):
    /// it is the covariance of an offset that was not estimated (X = I, Σ_X = 0).
    pub fn significant(&self) -> bool {
        let e = self.offset.log();
        let offset = self.offset_covariance.try_inverse().map_or(0.0, |i| (e.transpose() * i * e)[0]);
        offset > SIGNIFICANT_CORRECTION_CHI2 || self.significance.iter().any(|m| *m > SIGNIFICANT_CORRECTION_CHI2)
    }

    /// A world_from_cam pose T in the labels' convention: T X⁻¹.
    pub fn to_label(&self, world_from_cam: &SE3) -> SE3 {
        if self.applied { *world_from_cam * self.offset.inverse() } else { *world_from_cam }
    }

    /// A covariance of T (right perturbation) as one of T X⁻¹: Ad_X Σ Ad_Xᵀ, made exactly
    /// symmetric (the product's two triangles differ in the last bits, and a user's Cholesky
    /// or a file that keeps one triangle must not depend on which).
    pub fn covariance_to_label(&self, covariance: &Matrix6<f64>) -> Matrix6<f64> {
        if !self.applied {
            return *covariance;
        }
        let a = self.offset.adjoint();
        let c = a * covariance * a.transpose();
        (c + c.transpose()) * 0.5
    }

    /// A localizer's estimate (camera pose) in the labels' convention.
    pub fn estimate_to_label(&self, e: &crate::localizer::Estimate) -> crate::localizer::Estimate {
        crate::localizer::Estimate {
            world_from_cam: self.to_label(&e.world_from_cam),
            covariance: self.covariance_to_label(&e.covariance),
        }
    }

    /// A localization with its estimate in the labels' convention (what the bindings and the
    /// robot binary return).
    pub fn localization_to_label(&self, mut l: crate::localizer::Localization) -> crate::localizer::Localization {
        l.estimate = l.estimate.map(|e| self.estimate_to_label(&e));
        l
    }

    /// A localization as the camera's own pose with the offset's uncertainty: T = (T X⁻¹) X,
    /// so δT = Ad_{X⁻¹} δL + δ_X and the camera pose carries C + Σ_X. The localizer's C holds
    /// the map noise a result in the labels' convention carries — near the keyframes the
    /// label poses' own variance, which leaves the offset's error out — so the camera's pose,
    /// which the offset's error moves, adds Σ_X (beyond the keyframes C_map's floor may hold
    /// part of it already: conservative there). Unchanged when the adjustment is not applied.
    pub fn localization_to_camera(&self, mut l: crate::localizer::Localization) -> crate::localizer::Localization {
        if self.applied
            && let Some(e) = &mut l.estimate
        {
            e.covariance += self.offset_covariance;
        }
        l
    }

    /// One line for people: σ, τ, the offset, the median correction, the runs.
    pub fn summary(&self) -> String {
        let (mt, mr) = self.median_correction();
        let x = self.offset.log();
        let state = self.state();
        format!(
            "{state}: label σ {:.1} mm / {:.2}°, offset label_from_cam {:.1} cm / {:.2}°, median correction {:.1} mm / \
             {:.2}°, {} run(s) of significant corrections, reprojection {:.2} -> {:.2} px rms",
            1e3 * self.label_sigma.translation_m,
            self.label_sigma.rotation_rad.to_degrees(),
            1e2 * self.offset.translation.norm(),
            se3::phi(&x).norm().to_degrees(),
            1e3 * mt,
            mr.to_degrees(),
            self.runs().len(),
            self.rms_px.0,
            self.rms_px.1,
        )
    }

    /// The adjusted keyframe poses in the labels' convention, B_k = T_k X⁻¹, from the
    /// keyframes' camera poses T_k.
    pub fn label_poses(&self, camera_poses: &[SE3]) -> Vec<SE3> {
        camera_poses.iter().map(|t| self.to_label(t)).collect()
    }

    /// What became of the labels, in words: "adjusted", "kept (the images agree with them)",
    /// or — when no observation linked the keyframes — "kept (not checked: no tracks between
    /// the keyframes)": an adjustment without observations has only the priors and confirms
    /// nothing.
    pub fn state(&self) -> &'static str {
        if self.applied {
            "adjusted"
        } else if self.observations.0 == 0 {
            "kept (not checked: no tracks between the keyframes)"
        } else {
            "kept (the images agree with them)"
        }
    }

    /// The report as JSON: σ, offset (label_from_cam X as a 4×4 matrix, T_cam = T_label·X; its
    /// translation m, rotation deg, their σ, and its full 6×6 covariance Σ_X: right
    /// perturbation of X, translation first), medians, runs.
    pub fn report_json(&self) -> serde_json::Value {
        let (mt, mr) = self.median_correction();
        let offset = self.offset.log();
        let sd = |i: usize| self.offset_covariance[(i, i)].max(0.0).sqrt();
        serde_json::json!({
            "applied": self.applied,
            "state": self.state(),
            "label_sigma_m": self.label_sigma.translation_m,
            "label_sigma_deg": self.label_sigma.rotation_rad.to_degrees(),
            "correlation_keyframes": [self.correlation_keyframes.0, self.correlation_keyframes.1],
            "label_from_cam": rows(&self.offset.matrix()),
            "label_from_cam_translation_m": [self.offset.translation.x, self.offset.translation.y, self.offset.translation.z],
            "label_from_cam_translation_sigma_m": [sd(0), sd(1), sd(2)],
            "label_from_cam_rotation_deg": se3::phi(&offset).norm().to_degrees(),
            "label_from_cam_rotation_sigma_deg": [sd(3).to_degrees(), sd(4).to_degrees(), sd(5).to_degrees()],
            "label_from_cam_covariance": rows(&self.offset_covariance),
            "median_correction_m": mt,
            "median_correction_deg": mr.to_degrees(),
            "rms_px": [self.rms_px.0, self.rms_px.1],
            "observations": [self.observations.0, self.observations.1],
            "runs": self.runs().iter().map(|r| serde_json::json!({
                "start": r.start, "end": r.end,
                "max_translation_m": r.max_translation_m,
                "max_rotation_deg": r.max_rotation_rad.to_degrees(),
            })).collect::<Vec<_>>(),
        })
    }

    /// The runs of at least [`MIN_RUN_LENGTH`] consecutive keyframes whose corrections are
    /// significant (beyond [`SIGNIFICANT_CORRECTION_CHI2`]).
    pub fn runs(&self) -> Vec<LabelRun> {
        let mut runs = Vec::new();
        let mut k = 0;
        let n = self.significance.len();
        while k < n {
            if self.significance[k] <= SIGNIFICANT_CORRECTION_CHI2 {
                k += 1;
                continue;
            }
            let start = k;
            while k < n && self.significance[k] > SIGNIFICANT_CORRECTION_CHI2 {
                k += 1;
            }
            if k - start >= MIN_RUN_LENGTH {
                let part = &self.corrections[start..k];
                let max = |f: fn(&Vector6<f64>) -> f64| part.iter().map(f).fold(0.0, f64::max);
                runs.push(LabelRun {
                    start,
                    end: k,
                    max_translation_m: max(|e| se3::rho(e).norm()),
                    max_rotation_rad: max(|e| se3::phi(e).norm()),
                });
            }
        }
        runs
    }

    /// Median translation (m) and rotation (rad) corrections over the keyframes.
    pub fn median_correction(&self) -> (f64, f64) {
        let median = |mut v: Vec<f64>| median(&mut v, EvenMedian::Upper).unwrap_or(0.0);
        (
            median(self.corrections.iter().map(|e| se3::rho(e).norm()).collect()),
            median(self.corrections.iter().map(|e| se3::phi(e).norm()).collect()),
        )
    }
}

/// Per twist axis, the median over `covariances` (of label poses B_k, right perturbation) of
/// the variance of the camera pose T_k = B_k X they imply with X = `offset` fixed:
/// diag(Ad_{X⁻¹} Σ_k Ad_{X⁻¹}ᵀ) ([`LabelAdjustment::pose_variance`]); zero for none.
pub(crate) fn camera_frame_variance(offset: &SE3, covariances: &[Matrix6<f64>]) -> Vector6<f64> {
    let a = offset.inverse().adjoint();
    Vector6::from_fn(|axis, _| {
        let mut v: Vec<f64> = covariances.iter().map(|c| (a * c * a.transpose())[(axis, axis)].max(0.0)).collect();
        median(&mut v, EvenMedian::Mean).unwrap_or(0.0)
    })
}

/// A matrix as nested lists, one per row (the report's JSON form of X and Σ_X).
fn rows<const R: usize, const C: usize>(m: &nalgebra::SMatrix<f64, R, C>) -> Vec<Vec<f64>> {
    m.row_iter().map(|r| r.iter().copied().collect()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The camera-frame variance against a finite-difference Jacobian of ε ↦ log(T⁻¹ B exp(ε) X)
    /// (T = B X), pushed through each covariance, then the median per axis.
    #[test]
    fn the_pose_variance_is_the_label_covariance_seen_from_the_camera() {
        let mut rng = crate::testing::SplitMix64::new(9);
        let x = SE3::exp(&rng.twist(0.3, 0.2));
        let b = SE3::exp(&rng.twist(1.0, 2.0));
        let t = b * x;
        let h = 1e-6;
        let j = nalgebra::Matrix6::from_fn(|r, c| {
            let e = Vector6::from_fn(|i, _| if i == c { h } else { 0.0 });
            let plus = (t.inverse() * b * SE3::exp(&e) * x).log();
            let minus = (t.inverse() * b * SE3::exp(&(-e)) * x).log();
            (plus[r] - minus[r]) / (2.0 * h)
        });
        let covariances: Vec<Matrix6<f64>> = (1..=5)
            .map(|k| {
                let m = Matrix6::from_fn(|r, c| ((r * 7 + c * 3 + k) % 5) as f64 * 1e-4);
                m * m.transpose() + Matrix6::identity() * (k as f64) * 1e-5
            })
            .collect();
        let got = camera_frame_variance(&x, &covariances);
        for axis in 0..6 {
            let mut v: Vec<f64> = covariances.iter().map(|c| (j * c * j.transpose())[(axis, axis)]).collect();
            v.sort_by(f64::total_cmp);
            assert!((got[axis] - v[2]).abs() < 1e-6 * v[2], "axis {axis}: {} vs {}", got[axis], v[2]);
        }
        assert_eq!(camera_frame_variance(&x, &[]), Vector6::zeros());
    }

    fn record(significance: Vec<f64>) -> LabelAdjustment {
        let n = significance.len();
        LabelAdjustment {
            labels: vec![SE3::identity(); n],
            offset: SE3::identity(),
            offset_covariance: Matrix6::identity(),
            corrections: (0..n).map(|k| Vector6::new(0.01 * k as f64, 0.0, 0.0, 0.0, 0.0, 0.001)).collect(),
            significance,
            pose_variance: Vector6::zeros(),
            label_sigma: LabelSigma { translation_m: 0.01, rotation_rad: 0.01 },
            correlation_keyframes: (1.0, 1.0),
            rms_px: (1.0, 1.0),
            observations: (0, 0),
            applied: true,
        }
    }

    /// The significance threshold is the χ²₆ 99.9 % quantile: the closed-form CDF
    /// 1 − e^{−x/2}(1 + x/2 + x²/8) there is 0.999.
    #[test]
    fn significance_threshold_is_the_chi2_6_999_quantile() {
        let x = SIGNIFICANT_CORRECTION_CHI2;
        let cdf = 1.0 - (-x / 2.0).exp() * (1.0 + x / 2.0 + x * x / 8.0);
        assert!((cdf - 0.999).abs() < 1e-12, "{cdf}");
    }

    /// Labels kept after an adjustment that had no observation are not "agreed with" by the
    /// images: nothing checked them.
    #[test]
    fn the_state_says_whether_anything_checked_the_labels() {
        let adjusted = record(vec![0.0]);
        let agreed = LabelAdjustment { applied: false, observations: (500, 3), ..adjusted.clone() };
        let unchecked = LabelAdjustment { applied: false, observations: (0, 0), ..adjusted.clone() };
        assert_eq!(adjusted.state(), "adjusted");
        assert_eq!(agreed.state(), "kept (the images agree with them)");
        assert_eq!(unchecked.state(), "kept (not checked: no tracks between the keyframes)");
        assert!(unchecked.summary().starts_with("kept (not checked"));
        assert_eq!(unchecked.report_json()["state"], unchecked.state());
    }

    /// Runs against a brute-force scan of every window.
    #[test]
    fn runs_are_the_maximal_windows_of_significant_corrections() {
        let s = vec![0.0, 30.0, 30.0, 30.0, 1.0, 40.0, 40.0, 0.0, 50.0, 50.0, 50.0, 50.0];
        let got: Vec<(usize, usize)> = record(s.clone()).runs().iter().map(|r| (r.start, r.end)).collect();
        let mut want = Vec::new();
        for a in 0..s.len() {
            for b in a + MIN_RUN_LENGTH..=s.len() {
                let maximal = (a == 0 || s[a - 1] <= SIGNIFICANT_CORRECTION_CHI2)
                    && (b == s.len() || s[b] <= SIGNIFICANT_CORRECTION_CHI2);
                if maximal && s[a..b].iter().all(|v| *v > SIGNIFICANT_CORRECTION_CHI2) {
                    want.push((a, b));
                }
            }
        }
        assert_eq!(got, want);
        let run = record(s).runs()[1];
        assert!((run.max_translation_m - 0.11).abs() < 1e-12);
    }

    /// The camera's pose carries the offset's covariance on top: C + Σ_X when applied, C when not.
    #[test]
    fn the_camera_pose_adds_the_offsets_covariance() {
        let c = Matrix6::from_fn(|r, k| 1e-4 / (1.0 + (r + k) as f64)) + Matrix6::identity() * 1e-3;
        let localization = |c| crate::localizer::Localization {
            estimate: Some(crate::localizer::Estimate { world_from_cam: SE3::identity(), covariance: c }),
            source: crate::localizer::Source::Geometric,
            reason: String::new(),
            keyframe: 0,
            inliers: 10,
            map_noise_scale: 1.0,
            novelty: Some(0.5),
            timings: crate::localizer::Timings::default(),
        };
        let mut r = record(vec![0.0]);
        r.offset_covariance = Matrix6::from_diagonal(&Vector6::new(4e-4, 1e-4, 9e-4, 1e-6, 4e-6, 1e-6));
        let got = r.localization_to_camera(localization(c)).estimate.expect("estimate");
        assert_eq!(got.covariance, c + r.offset_covariance);
        r.applied = false;
        let kept = r.localization_to_camera(localization(c)).estimate.expect("estimate");
        assert_eq!(kept.covariance, c);
    }

    /// to_label and covariance_to_label agree with a perturbation pushed through T X⁻¹.
    #[test]
    fn label_convention_is_t_times_x_inverse() {
        let mut rng = crate::testing::SplitMix64::new(3);
        let mut r = record(vec![0.0]);
        r.offset = SE3::exp(&rng.twist(0.1, 0.1));
        let t = SE3::exp(&rng.twist(1.0, 2.0));
        let d = rng.twist(1e-3, 1e-3);
        let label = r.to_label(&t);
        let moved = r.to_label(&(t * SE3::exp(&d)));
        let a = r.offset.adjoint();
        assert!(((label.inverse() * moved).log() - a * d).norm() < 1e-8);
    }

    /// Ad_X Σ Ad_Xᵀ comes back exactly symmetric (the plain product's triangles differ in the
    /// last bits for almost any X) and equal to the product to rounding.
    #[test]
    fn a_covariance_in_the_labels_convention_is_exactly_symmetric() {
        let mut rng = crate::testing::SplitMix64::new(5);
        let mut r = record(vec![0.0]);
        let mut asymmetric_products = 0;
        for _ in 0..20 {
            r.offset = SE3::exp(&rng.twist(0.2, 0.1));
            let b = nalgebra::Matrix6::from_fn(|_, _| rng.normal());
            let c = b * b.transpose() + nalgebra::Matrix6::identity() * 1e-3;
            let a = r.offset.adjoint();
            let product = a * c * a.transpose();
            asymmetric_products += usize::from(product != product.transpose());
            let label = r.covariance_to_label(&c);
            assert_eq!(label, label.transpose());
            assert!((label - product).norm() <= 1e-14 * product.norm());
        }
        assert!(asymmetric_products > 0, "the test must see products whose triangles differ");
    }
}

/// The map pipeline: labels displaced over a run are corrected from the keyframes' own
/// features, and the record survives the map file.
#[cfg(test)]
mod map_tests {
    use crate::adjust::AdjustmentOptions;
    use crate::lie::{SE3, se3};
    use crate::map::model::fixture;
    use crate::map::{Keyframe, Map, RetrievalKind};

    #[test]
    fn a_displaced_run_of_labels_is_corrected_and_stored() {
        let (_, truth_map, _) = fixture::scene(40, false);
        let truth = truth_map.poses();
        let bump =
            SE3::exp(&se3::twist(&nalgebra::Vector3::new(0.08, -0.05, 0.06), &nalgebra::Vector3::new(0.0, 0.04, 0.02)));
        let run = 15..22;
        let keyframes: Vec<Keyframe> = truth_map
            .keyframes
            .iter()
            .enumerate()
            .map(|(k, kf)| Keyframe {
                world_from_cam: if run.contains(&k) { bump * kf.world_from_cam } else { kf.world_from_cam },
                ..kf.clone()
            })
            .collect();
        let kind = RetrievalKind::Bow { branching: 8, depth: 3 };
        let map = Map::build(truth_map.camera, keyframes, None, kind, 1).expect("valid map");
        let adjusted = map.with_adjusted_labels(&AdjustmentOptions::default()).expect("adjusts");
        let worst =
            adjusted.poses().iter().zip(&truth).map(|(a, t)| (a.inverse() * *t).translation.norm()).fold(0.0, f64::max);
        // (the run was 11 cm / 2.6° off; a straight walk leaves the offset's translation, and
        // so a common shift of the cameras, known to a few centimetres only)
        assert!(worst < 0.04, "worst camera error {worst} m");
        let worst_angle =
            adjusted.poses().iter().zip(&truth).map(|(a, t)| a.rotation.distance(&t.rotation)).fold(0.0, f64::max);
        assert!(worst_angle < 0.3f64.to_radians(), "worst camera rotation error {worst_angle} rad");
        let record = adjusted.labels.as_ref().expect("adjusted");
        let runs = record.runs();
        assert!(runs.iter().any(|r| r.start <= 16 && r.end >= 21), "{runs:?}");
        assert!(adjusted.pose_covariances.is_some());
        let file = adjusted.to_map_file("{}").expect("file");
        let back = Map::from_map_file(&file).expect("loads").0;
        assert_eq!(back.labels, adjusted.labels);
        // a damaged record is refused with the field or array named
        let damaged = |edit: &dyn Fn(&mut serde_json::Value)| {
            crate::map::persist::read_with_edited_header(&file, "labels", edit).expect_err("damaged labels").to_string()
        };
        let err = damaged(&|l| l["label_from_cam"][1] = 0.5.into());
        assert!(err.contains("labels.label_from_cam"), "{err}");
        let err = damaged(&|l| l["label_from_cam_covariance"] = serde_json::json!([1.0, 2.0]));
        assert!(err.contains("labels"), "{err}");
        let err = damaged(&|l| l["label_sigma"][0] = (-1.0).into());
        assert!(err.contains("labels.label_sigma"), "{err}");
        let mut missing = file.clone();
        missing.tensors.remove("keyframes.labels");
        let err = Map::from_map_file(&missing).expect_err("missing labels").to_string();
        assert!(err.contains("keyframes.labels"), "{err}");
        assert_eq!(back.poses(), adjusted.poses());
        let err = adjusted.with_adjusted_labels(&AdjustmentOptions::default()).expect_err("twice");
        assert!(err.to_string().contains("labels"), "{err}");
    }
}
