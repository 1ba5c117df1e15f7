//! When a geometric pose may be reported: the acceptance rule applied after PnP, in both
//! locators, on top of PnP's own test (an observable pose from enough inliers that random
//! pixels would not give, [`crate::pnp::chance_probability`]).
//!
//! PnP's test asks whether the inliers could be chance; it cannot see two ways a pose is
//! wrong that a robot must never be told is right:
//!
//! 1. **Too uncertain to be a claim.** A pose whose own 1σ is a large part of a gross error
//!    cannot be told from one. Rule: every per-axis σ of the measurement covariance C_G
//!    (translation first) is at most the gross-error bound over the two-sided 99.9 %
//!    normal quantile z = 3.29: √C_G,aa ≤ 0.5 m / 3.29 = 0.152 m for a = ρ_x, ρ_y, ρ_z and
//!    ≤ 10° / 3.29 = 3.04° for a = φ_x, φ_y, φ_z. A pose within these has its 99.9 % interval
//!    on every axis inside 0.5 m / 10°.
//! 2. **Matched from where the features cannot be matched.** A local descriptor matches the
//!    same point only from a similar viewpoint. For each inlier point X with the keyframes
//!    that saw it at centres c_k, and the pose's centre c, the match is *viewpoint-consistent*
//!    when, for at least one k, the angle between the rays X − c and X − c_k is at most
//!    `max_view_angle_deg` (ORB-SLAM's 60°: cos ≥ 0.5) and the distance ratio
//!    ‖X − c‖ / ‖X − c_k‖ lies within [1/s, s] with s = `max_scale_ratio` (the scale range
//!    of an 8-level, factor-1.2 ORB pyramid: 1.2⁷ ≈ 3.58). A pose is accepted only if at
//!    least [`MIN_SUPPORTED`] of its inliers and at least `min_supported_fraction` (½) of them are
//!    viewpoint-consistent: a pose that puts the camera behind, beside or far from the
//!    places the points were seen from explains its matches by a geometry the descriptors
//!    could not have matched under.

use nalgebra::{Matrix6, Vector3};

use crate::error::{GeolocError, Result};
use crate::pnp::MIN_ACCEPTED_INLIERS;

/// Two-sided 99.9 % quantile of the standard normal: a per-axis 99.9 % interval is ±3.29σ.
pub const Z_999: f64 = 3.290_526_731_491_926;
/// A pose error beyond this translation (m) is a gross error.
pub const GROSS_ERROR_M: f64 = 0.5;
/// ... or beyond this rotation (degrees).
pub const GROSS_ERROR_DEG: f64 = 10.0;
/// Fewest viewpoint-consistent inliers an accepted pose has (PnP's own minimum).
pub const MIN_SUPPORTED: usize = MIN_ACCEPTED_INLIERS;

/// The acceptance rule's thresholds (see the module doc); the defaults are the documented rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AcceptanceOptions {
    /// Largest per-axis translation σ of C_G (m, default 0.5 / 3.29 = 0.152).
    pub max_sigma_position_m: f64,
    /// Largest per-axis rotation σ of C_G (degrees, default 10 / 3.29 = 3.04).
    pub max_sigma_rotation_deg: f64,
    /// Largest angle between the query's and a keyframe's ray to a matched point (degrees, default 60).
    pub max_view_angle_deg: f64,
    /// Largest ratio of the query's and the keyframe's distance to a matched point, either way (default 1.2⁷).
    pub max_scale_ratio: f64,
    /// Fewest viewpoint-consistent inliers as a fraction of all inliers (default 0.5).
    pub min_supported_fraction: f64,
}

impl Default for AcceptanceOptions {
    fn default() -> Self {
        Self {
            max_sigma_position_m: GROSS_ERROR_M / Z_999,
            max_sigma_rotation_deg: GROSS_ERROR_DEG / Z_999,
            max_view_angle_deg: 60.0,
            max_scale_ratio: 1.2f64.powi(7),
            min_supported_fraction: 0.5,
        }
    }
}

impl AcceptanceOptions {
    /// Checks the thresholds.
    ///
    /// # Errors
    /// `InvalidInput` naming the field for a non-finite or non-positive threshold, an angle
    /// above 180°, a scale ratio below 1 or a fraction outside [0, 1].
    pub fn check(&self) -> Result<()> {
        let positive = [
            ("max_sigma_position_m", self.max_sigma_position_m),
            ("max_sigma_rotation_deg", self.max_sigma_rotation_deg),
            ("max_view_angle_deg", self.max_view_angle_deg),
            ("max_scale_ratio", self.max_scale_ratio),
        ];
        if let Some((name, v)) = positive.into_iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")));
        }
        if self.max_view_angle_deg > 180.0 {
            return Err(GeolocError::invalid("max_view_angle_deg", "must be ≤ 180"));
        }
        if self.max_scale_ratio < 1.0 {
            return Err(GeolocError::invalid("max_scale_ratio", "must be ≥ 1"));
        }
        if !(0.0..=1.0).contains(&self.min_supported_fraction) {
            return Err(GeolocError::invalid("min_supported_fraction", "must be within [0, 1]"));
        }
        Ok(())
    }
}

/// Whether the match of `point`, seen from keyframe centres `observers`, is plausible from
/// the query centre `center` (module doc, rule 2). A point at a centre is never consistent.
pub fn viewpoint_consistent(
    center: &Vector3<f64>,
    point: &Vector3<f64>,
    observers: &[Vector3<f64>],
    options: &AcceptanceOptions,
) -> bool {
    let query = point - center;
    let dq = query.norm();
    let min_cos = options.max_view_angle_deg.to_radians().cos();
    observers.iter().any(|c_k| {
        let seen = point - c_k;
        let dk = seen.norm();
        if dq <= 0.0 || dk <= 0.0 {
            return false;
        }
        let ratio = dq / dk;
        query.dot(&seen) >= min_cos * dq * dk
            && ratio <= options.max_scale_ratio
            && ratio * options.max_scale_ratio >= 1.0
    })
}

/// Why a pose with measurement covariance `covariance` (translation first) is too uncertain
/// to be told from a gross error (module doc, rule 1: a per-axis σ above the caps), if it is.
pub fn too_uncertain(covariance: &Matrix6<f64>, options: &AcceptanceOptions) -> Option<String> {
    // NaN propagates: a covariance with a NaN variance is never within the caps
    let sigma = covariance.diagonal().map(|v| if v.is_nan() { v } else { v.max(0.0).sqrt() });
    let largest =
        |from: usize| sigma.rows(from, 3).iter().fold(0.0f64, |m, s| if s.is_nan() || *s > m { *s } else { m });
    let (sigma_p, sigma_r) = (largest(0), largest(3).to_degrees());
    (!(sigma_p <= options.max_sigma_position_m && sigma_r <= options.max_sigma_rotation_deg)).then(|| {
        format!(
            "too uncertain to be told from a gross error: σ {sigma_p:.3} m / {sigma_r:.2}° > {:.3} m / {:.2}°",
            options.max_sigma_position_m, options.max_sigma_rotation_deg
        )
    })
}

/// Why the geometric pose with centre `center`, measurement covariance `covariance`
/// (translation first) and inlier `points` (each with the centres of the keyframes that saw
/// it) may not be reported, if it may not; see the module doc.
pub fn rejection(
    center: &Vector3<f64>,
    covariance: &Matrix6<f64>,
    points: &[Vector3<f64>],
    observers: &[Vec<Vector3<f64>>],
    options: &AcceptanceOptions,
) -> Option<String> {
    if let Some(why) = too_uncertain(covariance, options) {
        return Some(why);
    }
    let supported =
        points.iter().zip(observers).filter(|(x, seen)| viewpoint_consistent(center, x, seen, options)).count();
    let needed = MIN_SUPPORTED.max((options.min_supported_fraction * points.len() as f64).ceil() as usize);
    (supported < needed).then(|| {
        format!(
            "the pose sees its matches from where they were not seen: {supported} of {} inliers viewpoint-consistent < {needed}",
            points.len()
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    /// The rule written out with angles (acos) and both ratios, as a brute-force reference.
    fn reference_consistent(c: &Vector3<f64>, x: &Vector3<f64>, seen: &[Vector3<f64>], o: &AcceptanceOptions) -> bool {
        seen.iter().any(|k| {
            let (a, b) = (x - c, x - k);
            let angle = (a.dot(&b) / (a.norm() * b.norm())).clamp(-1.0, 1.0).acos().to_degrees();
            let (r1, r2) = (a.norm() / b.norm(), b.norm() / a.norm());
            angle <= o.max_view_angle_deg && r1 <= o.max_scale_ratio && r2 <= o.max_scale_ratio
        })
    }

    fn random_vec(rng: &mut SplitMix64, scale: f64) -> Vector3<f64> {
        Vector3::new(rng.normal(), rng.normal(), rng.normal()) * scale
    }

    #[test]
    fn viewpoint_test_agrees_with_the_angle_reference() {
        let o = AcceptanceOptions::default();
        let mut rng = SplitMix64::new(7);
        let (mut yes, mut no) = (0, 0);
        for _ in 0..20_000 {
            let c = random_vec(&mut rng, 1.0);
            let x = random_vec(&mut rng, 2.0);
            let seen: Vec<Vector3<f64>> =
                (0..1 + (rng.next_u64() % 3) as usize).map(|_| random_vec(&mut rng, 1.5)).collect();
            let got = viewpoint_consistent(&c, &x, &seen, &o);
            assert_eq!(got, reference_consistent(&c, &x, &seen, &o), "c {c:?} x {x:?} seen {seen:?}");
            if got { yes += 1 } else { no += 1 }
        }
        assert!(yes > 2000 && no > 2000, "both outcomes exercised: {yes} / {no}");
    }

    #[test]
    fn viewpoint_edges() {
        let o = AcceptanceOptions::default();
        let x = Vector3::new(0.0, 0.0, 2.0);
        let k = [Vector3::zeros()];
        // 59° and 61° off the keyframe's ray at the same distance
        let at = |deg: f64| x - 2.0 * Vector3::new(deg.to_radians().sin(), 0.0, deg.to_radians().cos());
        assert!(viewpoint_consistent(&at(59.0), &x, &k, &o));
        assert!(!viewpoint_consistent(&at(61.0), &x, &k, &o));
        // straight on, 3.5× and 3.6× as far (limit 1.2⁷ = 3.583)
        assert!(viewpoint_consistent(&Vector3::new(0.0, 0.0, 2.0 - 7.0), &x, &k, &o));
        assert!(!viewpoint_consistent(&Vector3::new(0.0, 0.0, 2.0 - 7.2), &x, &k, &o));
        assert!(!viewpoint_consistent(&Vector3::new(0.0, 0.0, 2.0 - 0.55), &x, &k, &o));
        assert!(!viewpoint_consistent(&x, &x, &k, &o), "a centre on the point");
        assert!(!viewpoint_consistent(&Vector3::zeros(), &x, &[], &o), "a point no keyframe saw");
    }

    #[test]
    fn rejection_counts_and_caps() {
        let o = AcceptanceOptions::default();
        let cov = Matrix6::from_diagonal(&nalgebra::Vector6::new(1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6));
        let k = vec![Vector3::zeros()];
        let front: Vec<Vector3<f64>> = (0..20).map(|i| Vector3::new(0.1 * i as f64 - 1.0, 0.0, 3.0)).collect();
        let seen = vec![k.clone(); 20];
        assert_eq!(rejection(&Vector3::new(0.1, 0.0, 0.0), &cov, &front, &seen, &o), None);
        // the camera moved behind the points: none consistent
        let why = rejection(&Vector3::new(0.0, 0.0, 6.0), &cov, &front, &seen, &o).expect("rejected");
        assert!(why.contains("0 of 20"), "{why}");
        // half the points seen only from the far side (180° off): half consistent passes,
        // one fewer does not
        let far_side = vec![Vector3::new(0.0, 0.0, 6.0)];
        let mut half_seen = seen.clone();
        half_seen[10..].fill(far_side.clone());
        let center = Vector3::new(0.1, 0.0, 0.0);
        assert_eq!(rejection(&center, &cov, &front, &half_seen, &o), None);
        half_seen[0] = far_side;
        let why = rejection(&center, &cov, &front, &half_seen, &o).expect("9 of 20 < 10");
        assert!(why.contains("9 of 20"), "{why}");
        // σ caps: just below and just above 0.152 m and 3.04°
        for (axis, limit) in [(0, o.max_sigma_position_m), (5, o.max_sigma_rotation_deg.to_radians())] {
            let mut c = cov;
            c[(axis, axis)] = (0.99 * limit).powi(2);
            assert_eq!(rejection(&Vector3::zeros(), &c, &front, &seen, &o), None);
            c[(axis, axis)] = (1.01 * limit).powi(2);
            assert!(rejection(&Vector3::zeros(), &c, &front, &seen, &o).expect("capped").contains("too uncertain"));
        }
        let mut nan = cov;
        nan[(2, 2)] = f64::NAN;
        assert!(rejection(&Vector3::zeros(), &nan, &front, &seen, &o).is_some(), "NaN σ is never accepted");
    }

    #[test]
    fn defaults_are_the_documented_rule_and_checked() {
        let o = AcceptanceOptions::default();
        assert!((o.max_sigma_position_m - 0.152).abs() < 1e-3 && (o.max_sigma_rotation_deg - 3.039).abs() < 1e-3);
        // Z_999 against the normal CDF by its series: Φ(3.2905) = 0.9995
        let z: f64 = Z_999;
        let (mut term, mut sum, mut k) = (z, z, 0.0);
        while term.abs() > 1e-18 {
            k += 1.0;
            term *= z * z / (2.0 * k + 1.0);
            sum += term;
        }
        let cdf = 0.5 + (-z * z / 2.0).exp() / (2.0 * std::f64::consts::PI).sqrt() * sum;
        assert!((cdf - 0.9995).abs() < 1e-12, "{cdf}");
        o.check().expect("defaults valid");
        for bad in [
            AcceptanceOptions { max_sigma_position_m: 0.0, ..o },
            AcceptanceOptions { max_view_angle_deg: 181.0, ..o },
            AcceptanceOptions { max_scale_ratio: 0.5, ..o },
            AcceptanceOptions { min_supported_fraction: 1.5, ..o },
            AcceptanceOptions { max_sigma_rotation_deg: f64::NAN, ..o },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
    }
}
