//! Co-visible keyframe selection (the paper's §"keyframe selection").
//!
//! The score of a pair of world_from_cam poses rewards a baseline near d_m and a small
//! rotation:
//!
//!   s(T₁, T₂) = exp(−(‖p₁ − p₂‖ − d_m)² / ℓ²) · min(α_m / Θ(R₁ᵀR₂), 1)
//!
//! with the min(·, 1) reading of the paper's `max` (which rewards Θ → 0 without bound);
//! Θ = 0 scores 1. The group grows from the seed k: alternately backward (in [k_b − Δk, k_b))
//! and forward (in (k_f, k_f + Δk]) the best-scoring pose relative to the current end becomes
//! the new end, until the group has `n` members or both sides run out of candidates that
//! overlap (score ≥ `min_score`).

use crate::error::{GeolocError, Result};
use crate::lie::SE3;

/// Options of [`select_keyframes`], with the paper's defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeyframeOptions {
    /// Group size, the seed included (default 7: 3 back, 3 forward).
    pub n: usize,
    /// Δk: how far (in frames) each step searches (default 100).
    pub window: usize,
    /// d_m: preferred baseline (default 0.1 m).
    pub d_m: f64,
    /// ℓ: tolerance of the baseline (default 0.2 m).
    pub ell: f64,
    /// α_m: rotation below which the score is not penalized (default 3°).
    pub alpha_m_rad: f64,
    /// Candidates scoring below this do not overlap and are skipped (default 1e-3).
    pub min_score: f64,
}

impl Default for KeyframeOptions {
    fn default() -> Self {
        Self { n: 7, window: 100, d_m: 0.1, ell: 0.2, alpha_m_rad: 3f64.to_radians(), min_score: 1e-3 }
    }
}

impl KeyframeOptions {
    /// Checks the score's parameters (d_m finite ≥ 0; ℓ, α_m finite > 0; `min_score` finite)
    /// and the group size (`n` ≥ 1).
    ///
    /// # Errors
    /// `InvalidInput` naming the offending option (`n`, `d_m`, `ell`, `alpha_m`, `min_score`).
    pub fn check(&self) -> Result<()> {
        if self.n == 0 {
            return Err(GeolocError::invalid("n", "must be at least 1"));
        }
        for (name, v) in [("ell", self.ell), ("alpha_m", self.alpha_m_rad)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")));
            }
        }
        if !(self.d_m.is_finite() && self.d_m >= 0.0) {
            return Err(GeolocError::invalid("d_m", format!("must be finite and ≥ 0, got {}", self.d_m)));
        }
        if !self.min_score.is_finite() {
            return Err(GeolocError::invalid("min_score", format!("must be finite, got {}", self.min_score)));
        }
        Ok(())
    }
}

/// s(T₁, T₂) of the module doc.
pub fn keyframe_score(a: &SE3, b: &SE3, d_m: f64, ell: f64, alpha_m_rad: f64) -> f64 {
    let baseline = (a.translation - b.translation).norm();
    let theta = a.rotation.distance(&b.rotation);
    let rotation_term = if theta <= alpha_m_rad { 1.0 } else { alpha_m_rad / theta };
    (-((baseline - d_m) / ell).powi(2)).exp() * rotation_term
}

/// The keyframe group around `seed` (sorted indices into `poses`; see the module doc).
///
/// # Errors
/// `seed` out of range (named `k`), or options refused by [`KeyframeOptions::check`].
pub fn select_keyframes(poses: &[SE3], seed: usize, options: &KeyframeOptions) -> Result<Vec<usize>> {
    if seed >= poses.len() {
        return Err(GeolocError::invalid("k", format!("{seed} is out of range for {} poses", poses.len())));
    }
    options.check()?;
    let score =
        |a: usize, b: usize| keyframe_score(&poses[a], &poses[b], options.d_m, options.ell, options.alpha_m_rad);
    let mut group = vec![seed];
    let (mut back, mut forward) = (Some(seed), Some(seed));
    let mut backward_turn = true;
    while group.len() < options.n && (back.is_some() || forward.is_some()) {
        let side_is_back = if back.is_none() {
            false
        } else if forward.is_none() {
            true
        } else {
            backward_turn
        };
        backward_turn = !backward_turn;
        let end = if side_is_back { back } else { forward }.expect("invariant: the chosen side is open");
        let candidates: Box<dyn Iterator<Item = usize>> = if side_is_back {
            Box::new(end.saturating_sub(options.window)..end)
        } else {
            Box::new(end + 1..(end + 1 + options.window).min(poses.len()))
        };
        // best score; ties go to the candidate nearest in time
        let best = candidates
            .map(|j| (j, score(end, j)))
            .filter(|&(_, s)| s >= options.min_score)
            .max_by(|a, b| a.1.total_cmp(&b.1).then_with(|| end.abs_diff(b.0).cmp(&end.abs_diff(a.0))));
        match (best, side_is_back) {
            (Some((j, _)), true) => {
                group.push(j);
                back = Some(j);
            }
            (Some((j, _)), false) => {
                group.push(j);
                forward = Some(j);
            }
            (None, true) => back = None,
            (None, false) => forward = None,
        }
    }
    group.sort_unstable();
    Ok(group)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::SO3;
    use nalgebra::Vector3;

    fn at(x: f64, yaw_deg: f64) -> SE3 {
        SE3::new(SO3::exp(&Vector3::new(0.0, yaw_deg.to_radians(), 0.0)), Vector3::new(x, 0.0, 0.0))
    }

    #[test]
    fn score_hand_computed_cases() {
        let o = KeyframeOptions::default();
        let s = |a: &SE3, b: &SE3| keyframe_score(a, b, o.d_m, o.ell, o.alpha_m_rad);
        // baseline exactly d_m, no rotation: 1
        assert!((s(&at(0.0, 0.0), &at(0.1, 0.0)) - 1.0).abs() < 1e-15);
        // same pose (Θ = 0): exp(−(0 − 0.1)²/0.04) = exp(−0.25)
        assert!((s(&at(0.0, 0.0), &at(0.0, 0.0)) - (-0.25f64).exp()).abs() < 1e-15);
        // 6° rotation at d_m: α_m/Θ = 0.5
        assert!((s(&at(0.0, 0.0), &at(0.1, 6.0)) - 0.5).abs() < 1e-12);
        // 2° rotation is under α_m: not penalized
        assert!((s(&at(0.0, 0.0), &at(0.1, 2.0)) - 1.0).abs() < 1e-12);
        // 0.5 m: exp(−(0.4/0.2)²) = exp(−4)
        assert!((s(&at(0.0, 0.0), &at(0.5, 0.0)) - (-4f64).exp()).abs() < 1e-15);
    }

    /// A straight track with 2 cm steps: the best neighbours are ~5 frames (0.1 m) apart.
    #[test]
    fn group_on_a_straight_track() {
        let poses: Vec<SE3> = (0..200).map(|i| at(0.02 * i as f64, 0.0)).collect();
        let g = select_keyframes(&poses, 100, &KeyframeOptions::default()).expect("valid");
        assert_eq!(g, vec![85, 90, 95, 100, 105, 110, 115]);
    }

    #[test]
    fn sequence_ends_give_smaller_or_one_sided_groups() {
        let poses: Vec<SE3> = (0..30).map(|i| at(0.02 * i as f64, 0.0)).collect();
        let g = select_keyframes(&poses, 0, &KeyframeOptions::default()).expect("valid");
        // nothing behind frame 0: all six come from the forward side, the last one at the end
        assert_eq!(g, vec![0, 5, 10, 15, 20, 25, 29]);
        let short: Vec<SE3> = (0..12).map(|i| at(0.02 * i as f64, 0.0)).collect();
        assert_eq!(select_keyframes(&short, 11, &KeyframeOptions::default()).expect("valid"), vec![0, 1, 6, 11]);
        let single = select_keyframes(&poses[..1], 0, &KeyframeOptions::default()).expect("valid");
        assert_eq!(single, vec![0]);
    }

    /// A stopped camera (repeated poses) still yields a group (Θ = 0 scores 1, baseline 0
    /// scores exp(−0.25)), and pure rotation is penalized by α_m/Θ.
    #[test]
    fn repeated_poses_and_pure_rotation() {
        let stopped: Vec<SE3> = (0..20).map(|_| at(1.0, 10.0)).collect();
        let g = select_keyframes(&stopped, 10, &KeyframeOptions::default()).expect("valid");
        assert_eq!(g.len(), 7);
        let spinning: Vec<SE3> = (0..50).map(|i| at(0.0, 10.0 * i as f64)).collect();
        let o = KeyframeOptions::default();
        // 10°/frame: neighbours score exp(−0.25)·0.3; farther ones less
        let g = select_keyframes(&spinning, 25, &o).expect("valid");
        assert!(g.contains(&24) && g.contains(&26), "{g:?}");
        // a 90° spin at the seed: no overlap beyond min_score with a strict threshold
        let strict = KeyframeOptions { min_score: 0.5, ..o };
        assert_eq!(select_keyframes(&spinning, 25, &strict).expect("valid"), vec![25]);
    }

    #[test]
    fn bad_arguments() {
        let poses = vec![SE3::identity(); 3];
        assert!(select_keyframes(&poses, 3, &KeyframeOptions::default()).is_err());
        assert!(select_keyframes(&poses, 0, &KeyframeOptions { n: 0, ..Default::default() }).is_err());
        assert!(select_keyframes(&poses, 0, &KeyframeOptions { ell: 0.0, ..Default::default() }).is_err());
    }
}
