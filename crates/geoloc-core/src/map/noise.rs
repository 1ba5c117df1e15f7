//! The map's own noise, estimated when it is built ([`Map::with_estimated_noise`]): the map-frame covariance
//! C_map from held-out keyframes re-localized against the rest of the map, and the
//! acceleration process noise from the keyframes' timestamps and poses.
//!
//! C_map: the keyframes are cut into contiguous blocks of `block`; every `holdout_step`-th
//! keyframe k is held out with its whole block and `margin` keyframes on either side (they
//! share its view and, on real data, its slowly drifting label error: a query block sees
//! the map built from *other* parts of the trajectory, so must the held-out keyframe —
//! holding out single keyframes measured only ~1/3 of the error a 100-frame test block
//! sees on 7-Scenes), localized by the geometric locator alone against the other keyframes, and the residual δ_k = log(T_label,k⁻¹ T_est,k)^∨ (right perturbation,
//! translation first) recorded with its PnP covariance C_G,k. If the held-out error is the
//! sum of the measurement error (covariance C_G) and an independent map-frame error
//! (covariance C_map), E[δδᵀ] = E[C_G] + C_map, so
//!
//!   C_map = diag( max(mean δ_a² − mean C_G,aa, f_a) ) · n/(n − 7),
//!
//! per axis a, with the floor f_a of [`excess_second_moment`]: an axis whose held-out errors the
//! measurement covariance already explains has a noise the samples cannot resolve — not a
//! zero one (clipping at zero gave maps with exactly zero noise on some axes, whose queries
//! were then covered far below 95 %). The second moment, not the centred covariance: a bias with respect to the
//! labels is error a query sees too. Diagonal, not the full 6×6: the held-out errors are
//! correlated within a block (the same drift), so ~50 samples carry the information of a
//! handful of blocks, far too few for 15 correlations; on 7-Scenes the full estimate had
//! per-axis coverage 85 % but 6-DoF NEES coverage 14 % (its small eigenvalues pointed the
//! wrong way), the diagonal one errs on the conservative side where the true errors are
//! correlated. n/(n − p − 1), p = 6, is the finite-sample inflation of a covariance
//! estimated from n samples and used to test a new one (Hotelling's T²). Gross failures
//! (RANSAC on the wrong place: more than `max_error_m` or `max_error_rad` off) are the
//! gate's business, not noise, and are left out. Everything else counts, the heavy tail
//! included: on the seven 7-Scenes fold maps 57 of 334 held-out keyframes are more than
//! 5 cm / 5° off (5–50 cm, mostly along the weakly constrained x/φy direction), in the parts
//! of the trajectory where the folds' test queries fail too (frames ≈ 95–145 and 350–475),
//! though the queries fail less often (22 of 697 against the SfM reference): a held-out
//! keyframe loses every point its block observed, a harsher test. An earlier version
//! trimmed samples beyond the χ²₆ 99.9 % quantile of a first estimate — exactly those — and
//! its C_map under-covered every query block with such runs (cross-validated NEES coverage
//! of the 7 folds 62–100 %; without the trim 70–100 %, median isometric σ 6.1 → 7.0 cm).
//!
//! C_map is the held-out keyframes' average, measured at their support: n̄, the median of
//! their PnP inliers, is stored with it, and a pose resting on fewer inliers gets C_map·n̄/n
//! ([`MapNoise::pose_covariance_at`]; never less than C_map). On the 7-Scenes folds the
//! queries of the block the map covers worst have half the held-out keyframes' support
//! (median 223 inliers against n̄ 532), and C_map alone covered 88 % of them in NEES and
//! 70 % on their weakest axis against the SfM reference; scaled, 99 % and 95 %, with the
//! other folds' coverage unchanged or higher.
//!
//! **The near regime.** C_map is the noise of a query as far from the keyframes as the
//! held-out keyframes were from those their re-localization kept (on the 7-Scenes fold maps
//! at least ν₁ = 1.1–1.7 in [`pose_distance`]'s units, 10 cm or 5° = 1; the folds' test
//! queries 1.35–6.3). A query beside the mapped path — the common case of a robot or a phone
//! in a mapped room — is as close to a keyframe as the keyframes are to each other (ν₀ =
//! 0.10–0.11 on 7-Scenes), and its pose shares the error those keyframes' poses have in
//! common, which the adjustment knows: C_near, per axis the median variance of the mean error
//! of a keyframe's neighbourhood ([`crate::map::LabelAdjustment::pose_variance`]; not one
//! keyframe's marginal variance, whose own part a frame resting on many keyframes' points does
//! not share; the offset's own uncertainty left out, as a result in the labels' convention
//! does not carry it). Between the two the noise is
//! interpolated linearly in ν ([`crate::map::NearNoise`], [`crate::map::MapNoise::covariance_at`]).
//! Measured on 7-Scenes 0–699 with every 10th frame a query against a map of the rest
//! (`benchmarks/calibration.py --near-path`, against the SfM reference, single image, 0.9 cm
//! median error): with C_map alone all 70 answers fell in their 95 % region at a median NEES
//! of 0.2 (σ_p 3.9 cm); with the near regime 91 % in NEES and 79 % on the weakest axis, at a
//! median NEES of 4.6 (σ_p 0.5 cm).

use std::sync::Arc;

use nalgebra::{Matrix6, Vector6};

use super::{HoldoutSample, Map, MapNoise, NearNoise};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::localizer::{Localizer, LocalizerOptions, Locator};
use crate::motion::{VelocityPrior, estimate_acceleration_psd, estimate_velocity_prior};
use crate::stats::{EvenMedian, median};

/// [`pose_distance`]'s translation scale (m) ...
pub const POSE_DISTANCE_SCALE_M: f64 = 0.1;
/// ... and rotation scale (degrees): 10 cm count as much as 5°.
pub const POSE_DISTANCE_SCALE_DEG: f64 = 5.0;

/// The distance of two camera poses, ν = √((‖t_a − t_b‖ / 0.1 m)² + (∠(R_aᵀR_b) / 5°)²).
pub fn pose_distance(a: &SE3, b: &SE3) -> f64 {
    let t = (a.translation - b.translation).norm() / POSE_DISTANCE_SCALE_M;
    let r = a.rotation.distance(&b.rotation).to_degrees() / POSE_DISTANCE_SCALE_DEG;
    t.hypot(r)
}

/// The least [`pose_distance`] from `pose` to any of `others` (∞ for none).
fn nearest_distance<'a>(pose: &SE3, others: impl IntoIterator<Item = &'a SE3>) -> f64 {
    others.into_iter().map(|o| pose_distance(o, pose)).fold(f64::INFINITY, f64::min)
}

impl Map {
    /// ν of `world_from_cam`: its [`pose_distance`] from the nearest keyframe (∞ for a map
    /// without keyframes).
    pub fn novelty(&self, world_from_cam: &SE3) -> f64 {
        nearest_distance(world_from_cam, self.keyframes.iter().map(|k| &k.world_from_cam))
    }
}

/// Fewest held-out samples for a C_map estimate (below: [`default_map_covariance`];
/// `holdout_samples` says how many there were).
pub const MIN_NOISE_SAMPLES: usize = 12;
/// Per-axis translation σ of C_map when too few held-out samples estimate it (m).
pub const DEFAULT_MAP_SIGMA_M: f64 = 0.05;
/// Per-axis rotation σ of C_map when too few held-out samples estimate it (degrees).
pub const DEFAULT_MAP_SIGMA_DEG: f64 = 2.0;

/// C_map of a map too small to estimate it (fewer than [`MIN_NOISE_SAMPLES`] held-out
/// keyframes): diag(σ_p², σ_p², σ_p², σ_r², σ_r², σ_r²) with σ_p = 5 cm, σ_r = 2°, the size of
/// the label errors measured on 7-Scenes tracks (1–10 cm and 0.8–4° per 100-frame block
/// against an SfM reference). Never zero: a map that cannot measure its own error must not
/// claim it has none.
pub fn default_map_covariance() -> Matrix6<f64> {
    let (p, r) = (DEFAULT_MAP_SIGMA_M.powi(2), DEFAULT_MAP_SIGMA_DEG.to_radians().powi(2));
    Matrix6::from_diagonal(&Vector6::new(p, p, p, r, r, r))
}

/// How the map's noise is estimated ([`Map::with_estimated_noise`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseOptions {
    /// Hold out every this-th keyframe (default 10).
    pub holdout_step: usize,
    /// Keyframes per held-out block (default 100; at most a quarter of the map is used).
    pub block: usize,
    /// Keyframes on either side of a held-out block excluded with it (default 15).
    pub margin: usize,
    /// Held-out errors beyond this translation (m, default 0.5) are gross failures.
    pub max_error_m: f64,
    /// ... or beyond this rotation (rad, default 15°).
    pub max_error_rad: f64,
    /// The localizer used for the held-out keyframes ...
    pub localizer: LocalizerOptions,
    /// ... with this locator; None (default): the one the map is built for — the model
    /// locator when the map holds a map-level model that can place a frame (at least
    /// `min_correspondences` points), the paper's otherwise (C_map is the
    /// noise the queries will see, so it is measured with the locator they will use).
    pub locator: Option<Locator>,
}

impl Default for NoiseOptions {
    fn default() -> Self {
        Self {
            holdout_step: 10,
            block: 100,
            margin: 15,
            max_error_m: 0.5,
            max_error_rad: 15f64.to_radians(),
            localizer: LocalizerOptions::default(),
            locator: None,
        }
    }
}

impl Map {
    /// The map with [`MapNoise`] estimated from its own keyframes (see the module doc):
    /// C_map from held-out re-localization, and the acceleration PSD from `timestamps`
    /// (one per keyframe, seconds; None leaves it 0).
    ///
    /// # Errors
    /// `holdout_step` 0, `timestamps` of the wrong length or not increasing, bad localizer
    /// options.
    pub fn with_estimated_noise(self, timestamps: Option<&[f64]>, options: &NoiseOptions) -> Result<Self> {
        if options.holdout_step == 0 {
            return Err(GeolocError::invalid("holdout_step", "must be ≥ 1"));
        }
        if options.block == 0 {
            return Err(GeolocError::invalid("block", "must be ≥ 1"));
        }
        let (acceleration_psd, velocity_prior) = match timestamps {
            Some(t) if t.len() != self.keyframes.len() => {
                return Err(GeolocError::invalid(
                    "timestamps",
                    format!("has {} entries for {} keyframes", t.len(), self.keyframes.len()),
                ));
            }
            Some(t) if t.len() >= 3 => {
                let poses = self.poses();
                (estimate_acceleration_psd(&poses, t)?, estimate_velocity_prior(&poses, t)?)
            }
            _ => (Vector6::zeros(), VelocityPrior::default()),
        };
        let map = Arc::new(self);
        let samples = {
            // the model locator where the map's model can place a frame at all
            let serves = map.model.as_ref().is_some_and(|m| m.len() >= options.localizer.min_correspondences);
            let default_locator = if serves { Locator::Model } else { Locator::Paper };
            let localizer =
                LocalizerOptions { locator: options.locator.unwrap_or(default_locator), ..options.localizer };
            let mut loc = Localizer::unprepared(Arc::clone(&map), localizer)?;
            holdout_residuals(&map, &mut loc, options)?
        };
        let mut map = Arc::try_unwrap(map).map_err(|_| GeolocError::invalid("map", "is shared"))?;
        let mut holdout = samples;
        let keyframe_variance = median_variance(map.pose_covariances.as_deref());
        let (pose_covariance, used) = map_covariance(&holdout, &keyframe_variance);
        for (sample, used) in holdout.iter_mut().zip(used) {
            sample.used = used;
        }
        let holdout_samples = holdout.len();
        let holdout_inliers = typical_support(&holdout);
        let near = near_noise(&map, &holdout, &pose_covariance);
        map.noise = MapNoise {
            pose_covariance,
            acceleration_psd,
            velocity_prior,
            holdout_samples,
            holdout_inliers,
            resolved: resolved_axes(&holdout),
            holdout,
            near,
        };
        Ok(map)
    }
}

/// (k, δ_k, C_G,k) of every held-out keyframe the locator placed within the gross-failure bounds.
fn holdout_residuals(map: &Map, loc: &mut Localizer, options: &NoiseOptions) -> Result<Vec<HoldoutSample>> {
    let n = map.keyframes.len();
    let block = options.block.min(n / 4).max(1);
    let mut samples = Vec::new();
    for k in (options.holdout_step / 2..n).step_by(options.holdout_step) {
        let b = k / block;
        let excluded = (b * block).saturating_sub(options.margin)..((b + 1) * block + options.margin).min(n);
        if excluded.len() >= n {
            continue; // a map this small has nothing to re-localize against
        }
        let Some((estimate, inliers)) = loc.localize_held_out(k, excluded.clone())? else { continue };
        let delta = (map.keyframes[k].world_from_cam.inverse() * estimate.world_from_cam).log();
        let rotation = delta.fixed_rows::<3>(3).norm();
        if delta.fixed_rows::<3>(0).norm() <= options.max_error_m && rotation <= options.max_error_rad {
            let kept = (0..n).filter(|j| !excluded.contains(j)).map(|j| &map.keyframes[j].world_from_cam);
            let novelty = nearest_distance(&map.keyframes[k].world_from_cam, kept);
            samples.push(HoldoutSample {
                keyframe: k,
                delta,
                covariance: estimate.covariance,
                inliers,
                used: false,
                novelty,
            });
        }
    }
    Ok(samples)
}

/// C_map = diag(max(m_a − c_a, f_a))·n/(n − 7) over every held-out sample, per axis a, with
/// m_a = mean δ_a², c_a = mean C_G,aa and the floor f_a of [`excess_second_moment`]; with which
/// samples were used (all, or none when there are fewer than 12: C_map is then
/// [`default_map_covariance`]). The
/// factor n/(n − p − 1), p = 6, is the finite-sample inflation of a covariance estimated
/// from n samples when it is used to test a new one (Hotelling's T²: a new sample's
/// E[δᵀŜ⁻¹δ] ≈ p·n/(n − p − 1), so Ŝ scaled by it keeps the χ²₆ mean).
fn map_covariance(samples: &[HoldoutSample], keyframe_variance: &Vector6<f64>) -> (Matrix6<f64>, Vec<bool>) {
    if samples.len() < MIN_NOISE_SAMPLES {
        return (default_map_covariance(), vec![false; samples.len()]);
    }
    let n = samples.len() as f64;
    let (excess, standard_error) = excess_second_moment(samples);
    let diagonal = Vector6::from_fn(|a, _| excess[a].max(standard_error[a]).max(keyframe_variance[a]));
    (Matrix6::from_diagonal(&diagonal) * (n / (n - 7.0)), vec![true; samples.len()])
}

/// Per axis a, the excess second moment m_a − c_a (m_a = mean δ_a², c_a = mean C_G,aa) and
/// the standard error of m_a, s_a / √n with s_a² = Σ (δ_a² − m_a)² / (n − 1) (0 for n < 2).
///
/// The floor of C_map is the larger of that standard error — an axis whose held-out errors
/// the measurement covariance already explains (m_a ≤ c_a) has a map noise the samples cannot
/// resolve, not a zero one, and one standard error is the smallest noise they cannot rule
/// out — and the median variance of the keyframe poses (the bundle adjustment's marginal
/// covariances relative to the labels' frame, the offset's own uncertainty left out as in the
/// near regime; zero when the map has none): the map's poses are known no better than that,
/// so its points are not either.
fn excess_second_moment(samples: &[HoldoutSample]) -> (Vector6<f64>, Vector6<f64>) {
    let n = samples.len() as f64;
    let mut excess = Vector6::zeros();
    let mut standard_error = Vector6::zeros();
    for a in 0..6 {
        let second: Vec<f64> = samples.iter().map(|s| s.delta[a] * s.delta[a]).collect();
        let mean = second.iter().sum::<f64>() / n;
        let measured = samples.iter().map(|s| s.covariance[(a, a)]).sum::<f64>() / n;
        let spread = if n > 1.0 { second.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0) } else { 0.0 };
        excess[a] = mean - measured;
        standard_error[a] = (spread / n).sqrt();
    }
    (excess, standard_error)
}

/// The near regime ([`NearNoise`]) of a map whose C_map `c_map` was estimated from `samples`:
/// C_near from the keyframe poses' variance in the labels' frame — the adjustment's
/// ([`crate::map::LabelAdjustment::pose_variance`]) when the map uses it; the labels' σ the
/// adjustment estimated when the images agreed with them (the map keeps the labels, known
/// that well); else the given pose covariances' median variance — capped per axis at C_map,
/// ν₀ the keyframes' median spacing, ν₁ the least distance of a used sample. None without
/// pose variances (or all zero), when C_map is the default (no sample used), or when ν₁ ≤ ν₀.
fn near_noise(map: &Map, samples: &[HoldoutSample], c_map: &Matrix6<f64>) -> Option<NearNoise> {
    let variance = match &map.labels {
        Some(l) if l.applied => l.pose_variance,
        Some(l) => {
            let (t, r) = (l.label_sigma.translation_m.powi(2), l.label_sigma.rotation_rad.powi(2));
            Vector6::new(t, t, t, r, r, r)
        }
        None => map.pose_covariances.as_deref().map(|c| median_variance(Some(c)))?,
    };
    if variance.iter().all(|v| *v <= 0.0) {
        return None;
    }
    let holdout_distance = samples.iter().filter(|s| s.used).map(|s| s.novelty).fold(f64::INFINITY, f64::min);
    let spacing = keyframe_spacing(map)?;
    if !(holdout_distance.is_finite() && holdout_distance > spacing) {
        return None;
    }
    let covariance = Matrix6::from_diagonal(&Vector6::from_fn(|a, _| variance[a].min(c_map[(a, a)])));
    Some(NearNoise { covariance, spacing, holdout_distance })
}

/// ν₀: the median over the keyframes of the [`pose_distance`] to the nearest other keyframe
/// (None for fewer than two keyframes).
fn keyframe_spacing(map: &Map) -> Option<f64> {
    let poses = map.poses();
    let mut nearest: Vec<f64> = (0..poses.len())
        .map(|k| nearest_distance(&poses[k], poses.iter().enumerate().filter(|&(j, _)| j != k).map(|(_, p)| p)))
        .filter(|d| d.is_finite())
        .collect();
    median(&mut nearest, EvenMedian::Mean)
}

/// n̄ = the median PnP inliers of the samples C_map was estimated from (the mean of the two
/// middle ones for an even count), the support [`MapNoise::pose_covariance_at`] scales C_map
/// by; 0 when none were used (C_map is then the default, which no support scales).
fn typical_support(samples: &[HoldoutSample]) -> f64 {
    let mut inliers: Vec<f64> = samples.iter().filter(|s| s.used).map(|s| s.inliers as f64).collect();
    median(&mut inliers, EvenMedian::Mean).unwrap_or(0.0)
}

/// Per axis (translation first), whether the held-out samples resolve C_map: its excess
/// second moment exceeds one standard error ([`excess_second_moment`]); an unresolved axis
/// is floored, never zero. None with fewer than [`MIN_NOISE_SAMPLES`] samples (C_map is then
/// [`default_map_covariance`]) — and for a loaded map, which keeps no samples.
pub fn resolved_axes(samples: &[HoldoutSample]) -> Option<[bool; 6]> {
    (samples.len() >= MIN_NOISE_SAMPLES).then(|| {
        let (excess, standard_error) = excess_second_moment(samples);
        std::array::from_fn(|a| excess[a] > standard_error[a])
    })
}

/// Twist axis names, translation first (for the descriptions).
const AXES: [&str; 6] = ["tx", "ty", "tz", "φx", "φy", "φz"];

/// [`MapNoise::description`]: "none: …" when C_map is zero; the default and why when too few
/// held-out keyframes estimated it; else how many did, and the axes they do not resolve
/// ([`resolved_axes`], when the samples are at hand); then, when n̄ > 0, the support rule of
/// [`MapNoise::pose_covariance_at`]: a pose on n < n̄ inliers gets C_map·n̄/n.
pub(super) fn describe(noise: &MapNoise) -> String {
    let c = &noise.pose_covariance;
    if *c == Matrix6::zeros() {
        return "none: not estimated, covariances are the measurement's alone".to_string();
    }
    let samples = noise.holdout_samples;
    let source = if samples < MIN_NOISE_SAMPLES {
        format!(
            "default: {samples} held-out keyframes < {MIN_NOISE_SAMPLES} cannot estimate it (σ {:.0} cm / {:.0}° per axis)",
            100.0 * c[(0, 0)].max(0.0).sqrt(),
            c[(3, 3)].max(0.0).sqrt().to_degrees()
        )
    } else {
        let unresolved: Vec<&str> = noise
            .resolved_axes()
            .map(|r| AXES.iter().zip(r).filter(|(_, ok)| !ok).map(|(name, _)| *name).collect())
            .unwrap_or_default();
        if unresolved.is_empty() {
            format!("estimated from {samples} held-out keyframes")
        } else {
            format!(
                "estimated from {samples} held-out keyframes; on {} they do not resolve it (floored at one standard \
                 error or the keyframe poses' variance, never zero)",
                unresolved.join(", ")
            )
        }
    };
    let source = if noise.holdout_inliers > 0.0 {
        format!("{source}; a pose on n < {0:.0} inliers (their median) gets C_map·{0:.0}/n", noise.holdout_inliers)
    } else {
        source
    };
    match noise.near {
        Some(near) => format!(
            "{source}; a pose as near a keyframe as the keyframes are to each other (ν ≤ {:.2}; 10 cm or 5° = 1) \
             gets their poses' own variance (σ {:.1} cm / {:.2}° per axis, median), rising linearly to C_map at the \
             held-out keyframes' least distance (ν ≥ {:.2})",
            near.spacing,
            100.0 * (near.covariance.fixed_view::<3, 3>(0, 0).trace() / 3.0).max(0.0).sqrt(),
            (near.covariance.fixed_view::<3, 3>(3, 3).trace() / 3.0).max(0.0).sqrt().to_degrees(),
            near.holdout_distance
        ),
        None => source,
    }
}

/// Per axis, the median over `covariances` of the diagonal entry (zero for none): the typical
/// variance of a keyframe pose.
fn median_variance(covariances: Option<&[Matrix6<f64>]>) -> Vector6<f64> {
    let Some(c) = covariances.filter(|c| !c.is_empty()) else { return Vector6::zeros() };
    Vector6::from_fn(|a, _| {
        let mut v: Vec<f64> = c.iter().map(|m| m[(a, a)].max(0.0)).collect();
        median(&mut v, EvenMedian::Mean).unwrap_or(0.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_covariance_subtracts_the_measured_part() {
        // δ = ±0.3 along each axis in turn: mean δδᵀ = diag(0.09)/6, C_G = 0.001 I
        let mut samples = Vec::new();
        for axis in 0..6 {
            for s in [-1.0, 1.0] {
                let mut d = Vector6::zeros();
                d[axis] = s * 0.3;
                samples.push(HoldoutSample {
                    keyframe: 0,
                    delta: d,
                    covariance: Matrix6::identity() * 0.001,
                    inliers: 100,
                    used: false,
                    novelty: 1.0,
                });
            }
        }
        let (c, used) = map_covariance(&samples, &Vector6::zeros());
        assert!(used.iter().all(|u| *u));
        let want = (0.09 / 6.0 - 0.001) * 12.0 / 5.0;
        assert!((c - Matrix6::identity() * want).amax() < 1e-12, "{c}");
    }

    #[test]
    #[allow(clippy::float_cmp)] // medians of integers and their ratios: exact equality is the claim
    fn the_map_noise_grows_as_the_support_falls_below_the_held_out_median() {
        // inliers 40, 10, 30, 20 (+ one unused 1000): n̄ = (20 + 30) / 2 = 25, written out
        let used = |inliers, used| HoldoutSample {
            keyframe: 0,
            delta: Vector6::zeros(),
            covariance: Matrix6::zeros(),
            inliers,
            used,
            novelty: 1.0,
        };
        let samples = [used(40, true), used(10, true), used(30, true), used(20, true), used(1000, false)];
        assert_eq!(typical_support(&samples), 25.0);
        assert_eq!(typical_support(&samples[..3]), 30.0);
        assert_eq!(typical_support(&[used(7, false)]), 0.0, "none used: the default C_map, unscaled");
        let c = Matrix6::from_fn(|r, k| 1e-4 / (1.0 + r as f64 + k as f64));
        let noise = MapNoise { pose_covariance: c, holdout_inliers: 25.0, ..MapNoise::default() };
        // C_map·max(1, n̄/n): 25/10 = 2.5 at 10 inliers, 1 at n̄ and above, unscaled when unknown
        assert_eq!(noise.pose_covariance_at(Some(10)), c * 2.5);
        assert_eq!(noise.pose_covariance_at(Some(5)), c * 5.0);
        for n in [Some(25), Some(26), Some(5000), None, Some(0)] {
            assert_eq!(noise.pose_covariance_at(n), c, "{n:?}");
        }
        let unscaled = MapNoise { pose_covariance: c, ..MapNoise::default() };
        assert_eq!(unscaled.pose_covariance_at(Some(1)), c, "n̄ 0: a map saved without it");
    }

    #[test]
    fn too_few_samples_give_the_conservative_default_never_zero() {
        let sample = HoldoutSample {
            keyframe: 0,
            delta: Vector6::zeros(),
            covariance: Matrix6::zeros(),
            inliers: 100,
            used: false,
            novelty: 1.0,
        };
        for n in [0, 1, MIN_NOISE_SAMPLES - 1] {
            let (c, used) = map_covariance(&vec![sample; n], &Vector6::from_element(1.0));
            assert!(used.iter().all(|u| !*u));
            // 5 cm and 2° per axis, written out
            let deg2 = (2.0 * std::f64::consts::PI / 180.0f64).powi(2);
            let want = Matrix6::from_diagonal(&Vector6::new(0.0025, 0.0025, 0.0025, deg2, deg2, deg2));
            assert!((c - want).amax() < 1e-15, "{n}: {c}");
        }
    }

    /// Held-out samples whose errors the measurement covariance over-explains on axis 1
    /// (δ₁ small, C_G,11 large): the classic estimate clips that axis to zero.
    fn over_explained() -> Vec<HoldoutSample> {
        (0..20)
            .map(|i| {
                let x = i as f64;
                let delta = Vector6::new(0.02 * (x - 9.5) / 9.5, 0.001 * (x % 3.0 - 1.0), 0.01, 0.0, 0.0, 0.002);
                let covariance = Matrix6::from_diagonal(&Vector6::new(1e-5, 1e-3, 1e-5, 1e-6, 1e-6, 1e-6));
                HoldoutSample { keyframe: i, delta, covariance, inliers: 100, used: false, novelty: 1.0 }
            })
            .collect()
    }

    #[test]
    fn an_axis_the_samples_cannot_resolve_gets_the_standard_error_never_zero() {
        let samples = over_explained();
        let n = samples.len() as f64;
        let (c, _) = map_covariance(&samples, &Vector6::zeros());
        for a in 0..6 {
            // written out: mean of δ_a², its sample variance, the standard error of the mean
            let mut sum = 0.0;
            for s in &samples {
                sum += s.delta[a] * s.delta[a];
            }
            let mean = sum / n;
            let mut ss = 0.0;
            for s in &samples {
                ss += (s.delta[a] * s.delta[a] - mean) * (s.delta[a] * s.delta[a] - mean);
            }
            let standard_error = (ss / (n - 1.0) / n).sqrt();
            let measured = samples.iter().map(|s| s.covariance[(a, a)]).sum::<f64>() / n;
            let want = (mean - measured).max(standard_error) * n / (n - 7.0);
            assert!((c[(a, a)] - want).abs() <= 1e-15 * want.max(1e-12), "axis {a}: {} vs {want}", c[(a, a)]);
        }
        // axis 1 is over-explained (mean δ² 6.7e-7 < mean C_G 1e-3) and still not zero
        assert!(c[(1, 1)] > 0.0 && c[(1, 1)] < 1e-5, "{}", c[(1, 1)]);
        // constant δ on axes 3 (zero) and 5: the standard error is zero, and so is the
        // floor without keyframe covariances — the keyframes' variance then floors them
        let kf = Vector6::from_element(4e-6);
        let (floored, _) = map_covariance(&samples, &kf);
        assert!((floored[(3, 3)] - 4e-6 * n / (n - 7.0)).abs() < 1e-18, "{}", floored[(3, 3)]);
        assert!(floored.diagonal().iter().all(|v| *v >= 4e-6 * n / (n - 7.0) - 1e-18));
    }

    #[test]
    fn resolved_axes_are_those_above_one_standard_error() {
        let samples = over_explained();
        // axis 0: δ spread over ±2 cm against C_G 1e-5 — resolved; 1: over-explained; 2: constant
        // 1 cm against C_G 1e-5 (excess 9e-5, no spread) — resolved; 3: zero; 4: zero;
        // 5: constant 2 mrad against C_G 1e-6 (excess 3e-6) — resolved
        assert_eq!(resolved_axes(&samples), Some([true, false, true, false, false, true]));
        assert_eq!(resolved_axes(&samples[..MIN_NOISE_SAMPLES - 1]), None);
    }

    #[test]
    fn the_description_says_the_source_the_unresolved_axes_and_the_support() {
        assert_eq!(MapNoise::default().description(), "none: not estimated, covariances are the measurement's alone");
        let default = MapNoise { pose_covariance: default_map_covariance(), holdout_samples: 3, ..MapNoise::default() };
        assert_eq!(
            default.description(),
            "default: 3 held-out keyframes < 12 cannot estimate it (σ 5 cm / 2° per axis)"
        );
        let c = Matrix6::identity() * 1e-4;
        let loaded =
            MapNoise { pose_covariance: c, holdout_samples: 40, holdout_inliers: 531.5, ..MapNoise::default() };
        // n̄ 531.5 is written as 532 in both places; no resolved axes recorded: nothing named
        assert_eq!(
            loaded.description(),
            "estimated from 40 held-out keyframes; a pose on n < 532 inliers (their median) gets C_map·532/n"
        );
        let holdout = over_explained();
        let built = MapNoise {
            pose_covariance: c,
            holdout_samples: holdout.len(),
            resolved: resolved_axes(&holdout),
            holdout,
            ..MapNoise::default()
        };
        assert_eq!(
            built.description(),
            format!(
                "estimated from {} held-out keyframes; on ty, φx, φy they do not resolve it (floored at one standard \
                 error or the keyframe poses' variance, never zero)",
                built.holdout_samples
            )
        );
    }

    #[test]
    fn the_keyframe_variance_is_the_median_of_the_diagonals() {
        assert_eq!(median_variance(None), Vector6::zeros());
        assert_eq!(median_variance(Some(&[])), Vector6::zeros());
        let c: Vec<Matrix6<f64>> = [1.0, 5.0, 2.0, 9.0]
            .iter()
            .map(|v| Matrix6::from_diagonal(&Vector6::from_fn(|a, _| v * (a + 1) as f64)))
            .collect();
        // sorted 1, 2, 5, 9: the mean of the middle two is 3.5, times the axis number
        assert_eq!(median_variance(Some(&c)), Vector6::from_fn(|a, _| 3.5 * (a + 1) as f64));
    }

    /// C(ν) = (1 − w) C_near + w C_map·max(1, n̄/n), w = clamp((ν − ν₀)/(ν₁ − ν₀), 0, 1),
    /// written out at the ends, the middle and outside; C_map alone without a near regime or
    /// a distance.
    #[test]
    #[allow(clippy::float_cmp)] // exact arithmetic on these values is the claim
    fn the_map_noise_rises_from_c_near_at_the_keyframe_spacing_to_c_map_at_the_held_out_distance() {
        let c = Matrix6::from_diagonal(&Vector6::new(4.0, 4.0, 4.0, 2.0, 2.0, 2.0));
        let c_near = Matrix6::from_diagonal(&Vector6::new(1.0, 2.0, 1.0, 1.0, 0.5, 1.0));
        let near = NearNoise { covariance: c_near, spacing: 0.5, holdout_distance: 2.5 };
        let noise = MapNoise { pose_covariance: c, holdout_inliers: 100.0, near: Some(near), ..MapNoise::default() };
        for (nu, w) in [(0.0, 0.0), (0.5, 0.0), (1.0, 0.25), (1.5, 0.5), (2.5, 1.0), (40.0, 1.0)] {
            assert_eq!(noise.novelty_weight(Some(nu)), w, "ν {nu}");
            assert_eq!(noise.covariance_at(Some(100), Some(nu)), c_near * (1.0 - w) + c * w, "ν {nu}");
            // the support scales C_map's part only
            assert_eq!(noise.covariance_at(Some(50), Some(nu)), c_near * (1.0 - w) + c * (2.0 * w), "ν {nu}");
        }
        assert_eq!(noise.novelty_weight(None), 1.0);
        assert_eq!(noise.covariance_at(Some(50), None), c * 2.0);
        let without = MapNoise { near: None, ..noise.clone() };
        assert_eq!(without.covariance_at(Some(100), Some(0.0)), c);
    }

    /// ν against an independent computation: the rotation angle from the trace of R_aᵀR_b.
    #[test]
    #[allow(clippy::float_cmp)] // a pose's distance from itself is exactly zero
    fn pose_distance_counts_ten_centimetres_as_five_degrees() {
        let mut rng = crate::testing::SplitMix64::new(11);
        for _ in 0..50 {
            let a = SE3::exp(&rng.twist(1.0, 2.0));
            let b = SE3::exp(&rng.twist(1.0, 2.0));
            let (ma, mb) = (a.matrix(), b.matrix());
            let r = ma.fixed_view::<3, 3>(0, 0).transpose() * mb.fixed_view::<3, 3>(0, 0);
            let angle = ((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
            let t = (ma.fixed_view::<3, 1>(0, 3) - mb.fixed_view::<3, 1>(0, 3)).norm();
            let want = ((t / 0.1).powi(2) + (angle / 5.0).powi(2)).sqrt();
            assert!((pose_distance(&a, &b) - want).abs() < 1e-6 * want.max(1.0), "{} vs {want}", pose_distance(&a, &b));
        }
        let a = SE3::exp(&rng.twist(1.0, 2.0));
        assert_eq!(pose_distance(&a, &a), 0.0);
    }

    /// The near regime of a map: C_near the keyframe poses' median variance capped at C_map,
    /// ν₀ their median spacing (brute force here), ν₁ the least distance of a used sample;
    /// none without pose covariances, without a used sample, or when ν₁ ≤ ν₀.
    #[test]
    #[allow(clippy::float_cmp)] // ν₁ is one of the given values, exactly
    fn the_near_regime_comes_from_the_keyframe_poses_and_the_used_samples() {
        let (_, mut map, _) = crate::map::model::fixture::scene(12, false);
        let sample = |novelty, used| HoldoutSample {
            keyframe: 0,
            delta: Vector6::zeros(),
            covariance: Matrix6::zeros(),
            inliers: 100,
            used,
            novelty,
        };
        let samples = [sample(3.0, true), sample(2.0, true), sample(0.01, false), sample(4.0, true)];
        let c_map = Matrix6::from_diagonal(&Vector6::new(1e-4, 1e-4, 1e-6, 1e-4, 1e-4, 1e-4));
        assert_eq!(near_noise(&map, &samples, &c_map), None, "no pose covariances");
        let variance = Vector6::new(4e-6, 9e-6, 4e-6, 1e-6, 1e-6, 1e-6);
        map.pose_covariances = Some(vec![Matrix6::from_diagonal(&variance); 12]);
        let near = near_noise(&map, &samples, &c_map).expect("a near regime");
        let mut nearest: Vec<f64> = (0..12)
            .map(|k| {
                (0..12)
                    .filter(|&j| j != k)
                    .map(|j| {
                        let (a, b) = (&map.keyframes[k].world_from_cam, &map.keyframes[j].world_from_cam);
                        let t = (a.translation - b.translation).norm() / 0.1;
                        let r = a.rotation.distance(&b.rotation).to_degrees() / 5.0;
                        (t * t + r * r).sqrt()
                    })
                    .fold(f64::INFINITY, f64::min)
            })
            .collect();
        nearest.sort_by(f64::total_cmp);
        assert!((near.spacing - (nearest[5] + nearest[6]) / 2.0).abs() < 1e-12, "{} {nearest:?}", near.spacing);
        assert_eq!(near.holdout_distance, 2.0, "the least distance of a used sample");
        // per axis min(variance, C_map): tz is capped at C_map's 1e-6
        assert_eq!(near.covariance, Matrix6::from_diagonal(&Vector6::new(4e-6, 9e-6, 1e-6, 1e-6, 1e-6, 1e-6)));
        assert_eq!(near_noise(&map, &[sample(2.0, false)], &c_map), None, "no used sample: C_map is the default");
        assert_eq!(near_noise(&map, &[sample(near.spacing, true)], &c_map), None, "ν₁ ≤ ν₀");
        map.pose_covariances = Some(vec![Matrix6::zeros(); 12]);
        assert_eq!(near_noise(&map, &samples, &c_map), None, "zero variances");
    }
}
