//! The map's pose labels corrected by bundle adjustment ([`crate::adjust`]): what the labels
//! were, the label-to-camera offset, each label's correction and its significance, the
//! runs of keyframes whose labels disagree with the images, the steps where the labels'
//! motion jumps away from the images', and the breaks the images found before the adjustment
//! ([`super::label_breaks`]).
//!
//! After [`super::Map::with_adjusted_labels`] the keyframes' `world_from_cam` are the adjusted
//! *camera* poses T_k = B_k X (what triangulation and PnP need), `pose_covariances` their
//! marginal covariances relative to the labels' frame ([`camera_frame_covariance`]: X held,
//! its own uncertainty Σ_X is not an answer's error), and [`LabelAdjustment`] keeps the
//! labels L_k, X = label_from_cam and the report. A pose in the labels' convention is T X⁻¹
//! ([`LabelAdjustment::to_label`]).

use nalgebra::{Matrix6, Vector6};

use super::label_breaks::{LabelBreak, LabelSegment};
use super::label_loops::LabelLoop;
use crate::adjust::{Adjustment, LabelSigma, camera_frame_covariance, correction, robust_sigma};
use crate::lie::{SE3, se3};
use crate::stats::chi2::CHI2_6_999;
use crate::stats::{EvenMedian, median};

/// χ²₆ 99.9 % quantile: a correction beyond it is significant.
pub const SIGNIFICANT_CORRECTION_CHI2: f64 = CHI2_6_999;

/// Fewest consecutive keyframes with significant corrections that make a run.
pub const MIN_RUN_LENGTH: usize = 3;

/// Fewest consecutive keyframe pairs whose motion disagreements set the scale steps are
/// measured against ([`LabelAdjustment::steps`]); with fewer the labels have no steps.
pub const MIN_STEP_PAIRS: usize = 10;

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
    /// their neighbourhood's mean label-pose error ([`Adjustment::label_neighbourhood_covariances`],
    /// Σ̄_k) as a perturbation of the camera pose T_k = B_k X with X held fixed:
    /// diag(Ad_{X⁻¹} Σ̄_k Ad_{X⁻¹}ᵀ) (B_k exp(ε) X = T_k exp(Ad_{X⁻¹} ε)). How well the map's
    /// poses are known in the labels' frame, as far as a frame resting on a neighbourhood's
    /// points shares it, without the offset's own uncertainty
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
    /// Jumps in the labels the images show between consecutive keyframes
    /// ([`super::label_breaks`]); empty in files saved before them.
    pub breaks: Vec<LabelBreak>,
    /// The keyframes between the breaks outside the longest segment that were re-placed, each
    /// part with the correction that moved its start poses, and those the images could not
    /// place (no correction: they keep their labels).
    pub replaced: Vec<LabelSegment>,
    /// Revisits whose labels disagree with the images, found by retrieval
    /// ([`super::label_loops`]), and whether the pose graph closed them before the adjustment;
    /// empty in files saved before them.
    pub loops: Vec<LabelLoop>,
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

/// A step in the labels: consecutive keyframes between which the labels' relative motion
/// and the images' (the adjusted poses') differ beyond the labels' frame-to-frame scatter —
/// where the source of the labels jumped (a loop closure, a relocalization, a lost frame),
/// which a slow drift does not do ([`LabelAdjustment::steps`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelStep {
    /// First keyframe.
    pub start: usize,
    /// One past the last keyframe (at least start + 2).
    pub end: usize,
    /// ‖ρ‖ (m) of d = log((L_s⁻¹ L_e)⁻¹ (B_s⁻¹ B_e))^∨, s = start, e = end − 1: how far the
    /// labels' motion across the step is from the images'.
    pub translation_m: f64,
    /// ‖φ‖ (rad) of the same d.
    pub rotation_rad: f64,
    /// The largest q of its keyframe pairs ([`LabelAdjustment::steps`]).
    pub significance: f64,
}

impl LabelAdjustment {
    /// The record of `adjustment` of `labels` (one adjusted pose per label).
    pub fn new(labels: Vec<SE3>, adjustment: &Adjustment) -> Self {
        let covariances = (&adjustment.label_pose_covariances[..], &adjustment.label_neighbourhood_covariances[..]);
        Self::with_poses(labels, &adjustment.label_poses, covariances, adjustment)
    }

    /// The record of `labels` adjusted to `adjusted` (world_from_label) with `covariances`
    /// (per keyframe the marginal one, and that of its neighbourhood's mean error,
    /// [`Adjustment::label_neighbourhood_covariances`]), the rest from `adjustment` (which
    /// may have adjusted a subset of the keyframes).
    pub fn with_poses(
        labels: Vec<SE3>,
        adjusted: &[SE3],
        covariances: (&[Matrix6<f64>], &[Matrix6<f64>]),
        adjustment: &Adjustment,
    ) -> Self {
        let (marginal, neighbourhood) = covariances;
        let (corrections, significance) =
            labels.iter().zip(adjusted).zip(marginal).map(|((l, b), c)| correction(l, b, c)).unzip();
        let pose_variance = camera_frame_variance(&adjustment.offset, neighbourhood);
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
            breaks: Vec::new(),
            replaced: Vec::new(),
            loops: Vec::new(),
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
            pixel_covariance: self.covariance_to_label(&e.pixel_covariance),
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

    /// One line for people: σ, τ, the offset, the median correction, the runs, the steps.
    pub fn summary(&self) -> String {
        let (mt, mr) = self.median_correction();
        let x = self.offset.log();
        let state = self.state();
        if self.observations.0 == 0 {
            // only the priors were adjusted: σ, offset and corrections are theirs, not measured
            return state.to_string();
        }
        format!(
            "{state}: label σ {:.1} mm / {:.2}°, offset label_from_cam {:.1} cm / {:.2}°, median correction {:.1} mm / \
             {:.2}°, {} run(s) of significant corrections, {}, reprojection {:.2} -> {:.2} px rms",
            1e3 * self.label_sigma.translation_m,
            self.label_sigma.rotation_rad.to_degrees(),
            1e2 * self.offset.translation.norm(),
            se3::phi(&x).norm().to_degrees(),
            1e3 * mt,
            mr.to_degrees(),
            self.runs().len(),
            describe_steps(&self.steps()),
            self.rms_px.0,
            self.rms_px.1,
        ) + &self.describe_breaks()
            + &self.describe_loops()
    }

    /// The loops in words, empty when there are none: how many revisits disagree with the
    /// labels, how many the pose graph closed, and the largest disagreement it closed.
    fn describe_loops(&self) -> String {
        if self.loops.is_empty() {
            return String::new();
        }
        let closed: Vec<&LabelLoop> = self.loops.iter().filter(|l| l.closed).collect();
        let largest =
            closed.iter().filter_map(|l| l.disagreement.as_ref().map(twist_size)).max_by(|a, b| a.0.total_cmp(&b.0));
        let mut text = format!(
            "; {} revisit(s) whose labels disagree with the images, {} closed before the adjustment",
            self.loops.len(),
            closed.len()
        );
        if let Some((m, deg)) = largest {
            text += &format!(" (largest {:.1} cm / {:.1}°)", 1e2 * m, deg);
        }
        if closed.len() < self.loops.len() {
            text += &format!(
                "; {} left open (they disagree with the other loops and the labels' motion)",
                self.loops.len() - closed.len()
            );
        }
        text
    }

    /// Whether the break before keyframe `at` was repaired: a re-placed part begins or ends there.
    pub fn break_repaired(&self, at: usize) -> bool {
        self.replaced.iter().any(|r| r.correction.is_some() && (r.start == at || r.end == at))
    }

    /// The breaks in words, empty when there are none: how many, the keyframes re-placed and
    /// how far, and the breaks no re-placed part reconciles.
    fn describe_breaks(&self) -> String {
        if self.breaks.is_empty() {
            return String::new();
        }
        let moved: Vec<String> = self
            .replaced
            .iter()
            .filter_map(|r| {
                let (m, deg) = twist_size(r.correction.as_ref()?);
                Some(format!("{}-{} by {:.1} cm / {:.1}°", r.start, r.end - 1, 1e2 * m, deg))
            })
            .collect();
        let left: Vec<String> =
            self.breaks.iter().filter(|b| !self.break_repaired(b.at)).map(|b| b.at.to_string()).collect();
        let mut text = format!(
            "; {} jump(s) in the labels the images show, re-placed: {}",
            self.breaks.len(),
            if moved.is_empty() { "none".to_string() } else { moved.join(", ") }
        );
        if !left.is_empty() {
            text += &format!("; WARNING: the images could not place the labels beyond keyframe(s) {}", left.join(", "));
        }
        text
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

    /// The report as JSON: its [`LabelAdjustment::summary`], σ, offset (label_from_cam X as a 4×4 matrix, T_cam = T_label·X; its
    /// translation m, rotation deg, their σ, and its full 6×6 covariance Σ_X: right
    /// perturbation of X, translation first), medians, runs, the steps and their scale.
    pub fn report_json(&self) -> serde_json::Value {
        let (mt, mr) = self.median_correction();
        let offset = self.offset.log();
        let sd = |i: usize| self.offset_covariance[(i, i)].max(0.0).sqrt();
        let step_sigma = self.step_sigma();
        serde_json::json!({
            "applied": self.applied,
            "state": self.state(),
            "summary": self.summary(),
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
            "step_sigma_m": step_sigma.translation_m,
            "step_sigma_deg": step_sigma.rotation_rad.to_degrees(),
            "breaks": self.breaks.iter().map(|b| serde_json::json!({
                "at": b.at, "matches": b.matches,
                "label_inliers": b.label_inliers, "image_inliers": b.image_inliers,
                "rotation_deg": b.rotation_deg, "repaired": self.break_repaired(b.at),
            })).collect::<Vec<_>>(),
            "replaced": self.replaced.iter().map(|r| {
                let (t, deg) = r.correction.as_ref().map(twist_size).unzip();
                serde_json::json!({
                    "start": r.start, "end": r.end, "correction": r.correction,
                    "correction_m": t, "correction_deg": deg,
                    "localized": r.localized, "agreeing": r.agreeing,
                })
            }).collect::<Vec<_>>(),
            "loops": self.loops.iter().map(|l| {
                let (t, deg) = l.disagreement.as_ref().map(twist_size).unzip();
                serde_json::json!({
                    "a": l.a, "b": l.b, "matches": l.matches,
                    "label_inliers": l.label_inliers, "image_inliers": l.image_inliers,
                    "disagreement": l.disagreement, "disagreement_m": t, "disagreement_deg": deg,
                    "closed": l.closed,
                })
            }).collect::<Vec<_>>(),
            "steps": self.steps().iter().map(|s| serde_json::json!({
                "start": s.start, "end": s.end,
                "translation_m": s.translation_m,
                "rotation_deg": s.rotation_rad.to_degrees(),
                "significance": s.significance,
            })).collect::<Vec<_>>(),
        })
    }

    /// The runs of at least [`MIN_RUN_LENGTH`] consecutive keyframes whose corrections are
    /// significant (beyond [`SIGNIFICANT_CORRECTION_CHI2`]).
    pub fn runs(&self) -> Vec<LabelRun> {
        above_threshold(&self.significance)
            .filter(|r| r.len() >= MIN_RUN_LENGTH)
            .map(|r| {
                let part = &self.corrections[r.clone()];
                let max = |f: fn(&Vector6<f64>) -> f64| part.iter().map(f).fold(0.0, f64::max);
                LabelRun {
                    start: r.start,
                    end: r.end,
                    max_translation_m: max(|e| se3::rho(e).norm()),
                    max_rotation_rad: max(|e| se3::phi(e).norm()),
                }
            })
            .collect()
    }

    /// The adjusted label poses B_k = L_k exp(e_k) (world_from_label).
    fn adjusted_labels(&self) -> Vec<SE3> {
        self.labels.iter().zip(&self.corrections).map(|(l, e)| *l * SE3::exp(e)).collect()
    }

    /// Per pair of consecutive keyframes k, k + 1: how the labels' relative motion differs
    /// from the adjusted one, d_k = log((L_k⁻¹ L_{k+1})⁻¹ (B_k⁻¹ B_{k+1}))^∨ (right
    /// perturbation in keyframe k + 1's label frame, translation first; to first order
    /// e_{k+1} − Ad_{M⁻¹} e_k with M = L_k⁻¹ L_{k+1}: the change of the correction).
    pub fn motion_disagreements(&self) -> Vec<Vector6<f64>> {
        let b = self.adjusted_labels();
        let l = &self.labels;
        (1..l.len()).map(|k| (relative(&l[k - 1], &l[k]).inverse() * relative(&b[k - 1], &b[k])).log()).collect()
    }

    /// The labels' frame-to-frame scatter: [`robust_sigma`] of the motion disagreements d_k
    /// ([`LabelAdjustment::motion_disagreements`]) — the σ of a label's relative motion
    /// against the images' where nothing jumped (half of the pairs may be steps).
    pub fn step_sigma(&self) -> LabelSigma {
        robust_sigma(&self.motion_disagreements())
    }

    /// The steps in the labels: maximal runs of consecutive keyframe pairs whose motion
    /// disagreement is beyond the scatter, q_k = ‖ρ_k‖² / σ_t² + ‖φ_k‖² / σ_r² above the χ²₆
    /// 99.9 % quantile ([`SIGNIFICANT_CORRECTION_CHI2`]) with σ = [`LabelAdjustment::step_sigma`]
    /// (keyframes in capture order). The adjustment spreads a jump of the labels over the
    /// few keyframes that share its images, so a step spans them; its size is the
    /// disagreement across it. None with fewer than [`MIN_STEP_PAIRS`] pairs.
    pub fn steps(&self) -> Vec<LabelStep> {
        let d = self.motion_disagreements();
        if d.len() < MIN_STEP_PAIRS {
            return Vec::new();
        }
        let sigma = self.step_sigma();
        let q: Vec<f64> = d
            .iter()
            .map(|e| {
                se3::rho(e).norm_squared() / sigma.translation_m.powi(2)
                    + se3::phi(e).norm_squared() / sigma.rotation_rad.powi(2)
            })
            .collect();
        let b = self.adjusted_labels();
        above_threshold(&q)
            .map(|pairs| {
                // pairs first..last join keyframes first..=last
                let (first, last) = (pairs.start, pairs.end);
                let span =
                    (relative(&self.labels[first], &self.labels[last]).inverse() * relative(&b[first], &b[last])).log();
                LabelStep {
                    start: first,
                    end: last + 1,
                    translation_m: se3::rho(&span).norm(),
                    rotation_rad: se3::phi(&span).norm(),
                    significance: q[pairs].iter().copied().fold(0.0, f64::max),
                }
            })
            .collect()
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

/// "N step(s) in the labels' motion (largest X cm / Y° at keyframes a-b)", or "no step in
/// the labels' motion".
/// The size of a stored twist (translation first): ‖ρ‖ in metres and ‖φ‖ in degrees.
fn twist_size(twist: &[f64; 6]) -> (f64, f64) {
    let t = Vector6::from(*twist);
    (se3::rho(&t).norm(), se3::phi(&t).norm().to_degrees())
}

fn describe_steps(steps: &[LabelStep]) -> String {
    match steps.iter().max_by(|a, b| a.translation_m.total_cmp(&b.translation_m)) {
        None => "no step in the labels' motion".to_string(),
        Some(s) => format!(
            "{} step(s) in the labels' motion (largest {:.1} cm / {:.2}° at keyframes {}-{})",
            steps.len(),
            1e2 * s.translation_m,
            s.rotation_rad.to_degrees(),
            s.start,
            s.end - 1
        ),
    }
}

/// The maximal ranges of consecutive values above [`SIGNIFICANT_CORRECTION_CHI2`], in order.
fn above_threshold(values: &[f64]) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
    let mut k = 0;
    std::iter::from_fn(move || {
        while k < values.len() && values[k] <= SIGNIFICANT_CORRECTION_CHI2 {
            k += 1;
        }
        let start = k;
        while k < values.len() && values[k] > SIGNIFICANT_CORRECTION_CHI2 {
            k += 1;
        }
        (k > start).then_some(start..k)
    })
}

/// A⁻¹ B: the motion from pose A to pose B.
fn relative(a: &SE3, b: &SE3) -> SE3 {
    a.inverse() * *b
}

/// Per twist axis, the median over `covariances` (of label poses B_k, right perturbation) of
/// the variance of the camera pose T_k = B_k X they imply with X = `offset` fixed:
/// diag([`camera_frame_covariance`]) ([`LabelAdjustment::pose_variance`]); zero for none.
pub(crate) fn camera_frame_variance(offset: &SE3, covariances: &[Matrix6<f64>]) -> Vector6<f64> {
    Vector6::from_fn(|axis, _| {
        let mut v: Vec<f64> =
            covariances.iter().map(|c| camera_frame_covariance(offset, c)[(axis, axis)].max(0.0)).collect();
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

    /// The camera-frame covariance and variance against a finite-difference Jacobian J of
    /// ε ↦ log(T⁻¹ B exp(ε) X) (T = B X): J Σ Jᵀ for each covariance, then the median per axis.
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
        for c in &covariances {
            let (got, want) = (camera_frame_covariance(&x, c), j * c * j.transpose());
            assert!((got - want).abs().max() < 1e-6 * want.abs().max(), "{got} vs {want}");
            assert_eq!(got, got.transpose());
        }
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
            breaks: Vec::new(),
            replaced: Vec::new(),
            loops: Vec::new(),
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
        // its σ and corrections are the priors', nothing measured: the summary says the state alone
        assert_eq!(unchecked.summary(), unchecked.state());
        assert!(agreed.summary().starts_with("kept (the images agree with them): label σ"));
        assert_eq!(unchecked.report_json()["state"], unchecked.state());
    }

    /// The summary names the jumps, the parts re-placed and how far, warns of a jump no part
    /// reconciles, and counts the loops and those left open; without them it says nothing of
    /// them.
    #[test]
    fn the_summary_names_jumps_and_loops_and_warns_of_an_unrepaired_jump() {
        use crate::map::label_breaks::{LabelBreak, LabelSegment};
        use crate::map::label_loops::LabelLoop;
        let quiet = LabelAdjustment { observations: (1000, 10), ..record(vec![0.0]) };
        let jump = |at| LabelBreak { at, matches: 900, label_inliers: 40, image_inliers: 850, rotation_deg: 1.0 };
        let moved =
            se3::twist(&nalgebra::Vector3::new(0.3, 0.0, 0.25), &nalgebra::Vector3::new(0.0, 10f64.to_radians(), 0.0));
        let revisit = |a: usize, closed| LabelLoop {
            a,
            b: a + 80,
            matches: 900,
            label_inliers: 0,
            image_inliers: 850,
            disagreement: Some(moved.into()),
            closed,
        };
        let found = LabelAdjustment {
            breaks: vec![jump(42), jump(90)],
            replaced: vec![
                LabelSegment { start: 30, end: 42, correction: Some(moved.into()), localized: 12, agreeing: 12 },
                LabelSegment { start: 90, end: 95, correction: None, localized: 0, agreeing: 0 },
            ],
            loops: (0..5).map(|a| revisit(a, a != 4)).collect(),
            ..quiet.clone()
        };
        let text = found.summary();
        assert!(
            text.contains("; 2 jump(s) in the labels the images show, re-placed: 30-41 by 39.1 cm / 10.0°; WARNING: the images could not place the labels beyond keyframe(s) 90;"),
            "{text}"
        );
        assert!(
            text.ends_with(
                "; 5 revisit(s) whose labels disagree with the images, 4 closed before the adjustment (largest 39.1 cm \
                 / 10.0°); 1 left open (they disagree with the other loops and the labels' motion)"
            ),
            "{text}"
        );
        assert_eq!(found.report_json()["summary"], text);
        let plain = quiet.summary();
        assert!(!plain.contains("jump") && !plain.contains("WARNING") && !plain.contains("revisit"), "{plain}");
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

    /// Labels L_k of a walk whose source jumped by exp(j) at keyframe `jump` (expressed at the
    /// keyframe before it) over Gaussian label noise; the record's corrections take them to
    /// the truth B_k.
    fn jumped_labels(n: usize, jumps: &[(usize, Vector6<f64>)], seed: u64) -> LabelAdjustment {
        let mut rng = crate::testing::SplitMix64::new(seed);
        let mut truth = vec![SE3::identity()];
        for _ in 1..n {
            let last = *truth.last().expect("one pose");
            truth.push(last * SE3::exp(&rng.twist(0.05, 0.1)));
        }
        let mut world_jump = SE3::identity();
        let labels: Vec<SE3> = (0..n)
            .map(|k| {
                for (at, j) in jumps {
                    if k == *at {
                        world_jump = truth[k - 1] * SE3::exp(j) * truth[k - 1].inverse() * world_jump;
                    }
                }
                world_jump * truth[k] * SE3::exp(&rng.pose_noise(0.001, 0.05f64.to_radians()))
            })
            .collect();
        let corrections = labels.iter().zip(&truth).map(|(l, b)| (l.inverse() * *b).log()).collect();
        LabelAdjustment { labels, corrections, ..record(vec![0.0; n]) }
    }

    /// d_k against its first-order closed form e_{k+1} − Ad_{M⁻¹} e_k (M = L_k⁻¹ L_{k+1}) for
    /// small corrections, and zero when the adjusted poses are the labels.
    #[test]
    fn a_motion_disagreement_is_the_change_of_the_correction() {
        let mut r = jumped_labels(12, &[], 4);
        let mut rng = crate::testing::SplitMix64::new(6);
        r.corrections = (0..12).map(|_| rng.pose_noise(1e-5, 1e-5)).collect();
        for (k, d) in r.motion_disagreements().iter().enumerate() {
            let m = r.labels[k].inverse() * r.labels[k + 1];
            let first_order = r.corrections[k + 1] - m.inverse().adjoint() * r.corrections[k];
            assert!((d - first_order).norm() <= 1e-3 * first_order.norm(), "pair {k}: {d} vs {first_order}");
        }
        r.corrections = vec![Vector6::zeros(); 12];
        assert!(r.motion_disagreements().iter().all(|d| d.norm() < 1e-12));
    }

    /// Steps against a brute-force scan: q_k from 4×4 matrices and a sorted median, the
    /// maximal windows of pairs above the χ²₆ 99.9 % quantile; the two jumps of the labels
    /// (6.2 cm / 1°, 3.6 cm / 0°) are found where they are and as large as they are, and
    /// elsewhere steps appear at the test's false-alarm rate.
    #[test]
    fn steps_are_the_jumps_of_the_labels_motion() {
        let jumps = [
            (20, Vector6::new(0.05, -0.03, 0.02, 0.0, 0.0, 1f64.to_radians())),
            (45, Vector6::new(0.0, 0.02, 0.03, 0.0, 0.0, 0.0)),
        ];
        let r = jumped_labels(60, &jumps, 8);
        let steps = r.steps();
        // brute force
        let b: Vec<nalgebra::Matrix4<f64>> =
            r.labels.iter().zip(&r.corrections).map(|(l, e)| l.matrix() * SE3::exp(e).matrix()).collect();
        let l: Vec<nalgebra::Matrix4<f64>> = r.labels.iter().map(SE3::matrix).collect();
        let inv = |m: &nalgebra::Matrix4<f64>| m.try_inverse().expect("invertible");
        let d: Vec<Vector6<f64>> = (1..60)
            .map(|k| {
                let m = inv(&(inv(&l[k - 1]) * l[k])) * inv(&b[k - 1]) * b[k];
                SE3::from_matrix_projected(&m).expect("rigid").log()
            })
            .collect();
        let sigma = |part: fn(&Vector6<f64>) -> f64, floor: f64| {
            let mut v: Vec<f64> = d.iter().map(part).collect();
            v.sort_by(f64::total_cmp);
            (v[v.len() / 2] / crate::stats::chi2::CHI2_3_MEDIAN).sqrt().max(floor)
        };
        let st = sigma(|e| e.fixed_rows::<3>(0).norm_squared(), 1e-3);
        let sr = sigma(|e| e.fixed_rows::<3>(3).norm_squared(), 0.05f64.to_radians());
        let q: Vec<f64> = d
            .iter()
            .map(|e| e.fixed_rows::<3>(0).norm_squared() / (st * st) + e.fixed_rows::<3>(3).norm_squared() / (sr * sr))
            .collect();
        let mut want = Vec::new();
        for a in 0..q.len() {
            for z in a + 1..=q.len() {
                let maximal = (a == 0 || q[a - 1] <= SIGNIFICANT_CORRECTION_CHI2)
                    && (z == q.len() || q[z] <= SIGNIFICANT_CORRECTION_CHI2);
                if maximal && q[a..z].iter().all(|v| *v > SIGNIFICANT_CORRECTION_CHI2) {
                    want.push((a, z + 1));
                }
            }
        }
        let got: Vec<(usize, usize)> = steps.iter().map(|s| (s.start, s.end)).collect();
        assert_eq!(got, want);
        // every jump found, as large as it is (within 4σ of a pair's noise: labels 1 mm /
        // 0.05° per axis, a pair √2 of that), on 50 draws of the noise; elsewhere a pair is
        // a step by chance at the test's 0.1 % (59 pairs × 50 draws: about 3 expected)
        let mut by_chance = 0;
        for seed in 0..50 {
            let steps = jumped_labels(60, &jumps, seed).steps();
            for (at, j) in jumps {
                let step = steps
                    .iter()
                    .find(|s| s.start < at && at < s.end)
                    .unwrap_or_else(|| panic!("seed {seed}, jump at {at}: {steps:?}"));
                let size = se3::rho(&j).norm();
                assert!((step.translation_m - size).abs() < 0.006, "seed {seed}, jump at {at}: {step:?} for {size} m");
                assert!(
                    (step.rotation_rad - se3::phi(&j).norm()).abs() < 0.3f64.to_radians(),
                    "seed {seed}, jump at {at}: {step:?}"
                );
            }
            by_chance += steps.len() - jumps.len();
        }
        assert!(by_chance <= 10, "{by_chance} steps where the labels did not jump");
        // too few pairs to measure the scatter: no step
        assert!(jumped_labels(MIN_STEP_PAIRS, &[(5, jumps[0].1)], 8).steps().is_empty());
        assert_eq!(jumped_labels(MIN_STEP_PAIRS + 1, &[(5, jumps[0].1)], 8).steps().len(), 1);
    }

    /// The camera's pose carries the offset's covariance on top: C + Σ_X when applied, C when not.
    #[test]
    fn the_camera_pose_adds_the_offsets_covariance() {
        let c = Matrix6::from_fn(|r, k| 1e-4 / (1.0 + (r + k) as f64)) + Matrix6::identity() * 1e-3;
        let localization = |c| crate::localizer::Localization {
            estimate: Some(crate::localizer::Estimate {
                world_from_cam: SE3::identity(),
                covariance: c,
                pixel_covariance: c,
            }),
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
        // the labels jump where the run starts and ends (12–13 cm / 2.6° across either): each
        // found there, as large as the labels' motion differs from the truth across its span
        let steps = record.steps();
        for edge in [15, 22] {
            let s =
                steps.iter().find(|s| s.start < edge && edge < s.end).unwrap_or_else(|| panic!("{edge}: {steps:?}"));
            let span = |p: &[SE3]| p[s.start].inverse() * p[s.end - 1];
            let d = (span(&record.labels).inverse() * span(&truth)).log();
            assert!((s.translation_m - se3::rho(&d).norm()).abs() < 0.015, "{s:?} against {d}");
            assert!((s.rotation_rad - se3::phi(&d).norm()).abs() < 0.3f64.to_radians(), "{s:?} against {d}");
        }
        assert!(steps.iter().all(|s| s.translation_m < 0.01 || [15, 22].iter().any(|e| s.start < *e && *e < s.end)));
        // the keyframe covariances, seen back in the labels' frame (Ad_X C Ad_Xᵀ), are the
        // ones each correction's significance was measured with: the offset's Σ_X is not in them
        assert!(record.offset_covariance.trace() > 0.0, "the offset was estimated");
        for (k, c) in adjusted.pose_covariances.as_ref().expect("covariances").iter().enumerate() {
            let e = record.corrections[k];
            let q = (e.transpose() * record.covariance_to_label(c).try_inverse().expect("spd") * e)[0];
            let want = record.significance[k];
            assert!((q - want).abs() <= 1e-6 * want.max(1.0), "keyframe {k}: {q} against {want}");
        }
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
