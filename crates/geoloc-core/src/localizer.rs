//! The per-frame localizer: the paper's pipeline (DESIGN.md §1) frame after frame.
//!
//! retrieval (global index or BoW) → keyframe group around the retrieved keyframe → matches
//! from the seed keyframe to the rest of the group, epipolar-checked with their known poses →
//! tracks → triangulation (cached per group) → query-to-map matching → PnP with the points'
//! uncertainty (T_G, C_G) → constant-velocity prediction from the last fused poses (T_M, C_M)
//! → gated fusion (T_F, C_F). The first frames, before there is any history, use the
//! geometric pose alone. Every result says which path produced it and why.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Matrix3, Matrix3x6, Matrix6, Vector2, Vector3};

use crate::error::{GeolocError, Result};
use crate::fusion::{FusionSource, Gate, fuse};
use crate::keyframes::{KeyframeOptions, select_keyframes};
use crate::lie::SE3;
use crate::map::{DescriptorSet, Map};
use crate::matching::{Descriptors, MatchOptions, epipolar_filter, match_descriptors};
use crate::motion::motion_predict;
use crate::pnp::{PnpOptions, PointUncertainty, SharedPoseUncertainty, solve_pnp};
use crate::triangulate::{TrackStatus, TriangulationOptions, triangulate};

/// Options of the [`Localizer`], defaults from the paper.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalizerOptions {
    /// Keyframe group selection.
    pub keyframes: KeyframeOptions,
    /// Local-descriptor matching (keyframe–keyframe and query–map).
    pub matching: MatchOptions,
    /// Sampson threshold of the keyframe–keyframe epipolar check (default 2 px).
    pub epipolar_px: f64,
    /// Forward intersection.
    pub triangulation: TriangulationOptions,
    /// Backward intersection.
    pub pnp: PnpOptions,
    /// t: fused poses the motion model is fitted to (default 4).
    pub history: usize,
    /// Gate of the geometric pose against the prediction, in σ (default 3).
    pub gate_sigma: f64,
    /// Which gate (default the paper's isometric one).
    pub gate: Gate,
    /// Fewest 2D–3D correspondences worth a PnP (default 12).
    pub min_correspondences: usize,
}

impl Default for LocalizerOptions {
    fn default() -> Self {
        Self {
            keyframes: KeyframeOptions::default(),
            matching: MatchOptions::default(),
            epipolar_px: 2.0,
            triangulation: TriangulationOptions::default(),
            pnp: PnpOptions::default(),
            history: 4,
            gate_sigma: 3.0,
            gate: Gate::Isometric,
            min_correspondences: 12,
        }
    }
}

/// One query frame: its features, from the caller's detector.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    /// Capture time (seconds, increasing).
    pub timestamp: f64,
    /// Keypoints, undistorted pixels.
    pub keypoints: &'a [Vector2<f64>],
    /// One local descriptor per keypoint.
    pub descriptors: Descriptors<'a>,
    /// Global descriptor, when the map retrieves by one.
    pub global: Option<&'a [f32]>,
}

/// Which path produced a result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// The geometric locator alone (no motion history yet).
    Geometric,
    /// Geometric and motion poses fused.
    Fused,
    /// The motion prediction (the geometric pose failed or was gated).
    Motion,
    /// Neither.
    Lost,
}

/// Milliseconds spent in each stage.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Timings {
    /// Retrieval of the most similar keyframe.
    pub retrieval_ms: f64,
    /// Keyframe group selection.
    pub keyframes_ms: f64,
    /// Keyframe matching and triangulation (0 when the group was cached).
    pub map_points_ms: f64,
    /// Query-to-map matching.
    pub matching_ms: f64,
    /// PnP.
    pub pnp_ms: f64,
    /// Motion model and fusion.
    pub motion_fusion_ms: f64,
    /// Everything.
    pub total_ms: f64,
}

/// The localization of one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Localization {
    /// world_from_cam (None when lost).
    pub world_from_cam: Option<SE3>,
    /// 6×6 covariance, right perturbation, translation first (None when lost).
    pub covariance: Option<Matrix6<f64>>,
    /// Which path produced it.
    pub source: Source,
    /// Why (e.g. why the geometric pose was not used).
    pub reason: String,
    /// The retrieved keyframe.
    pub keyframe: usize,
    /// PnP inliers (0 without a geometric pose).
    pub inliers: usize,
    /// Time per stage.
    pub timings: Timings,
}

/// D_jk (row-major points × group keyframes) and the group keyframes' pose covariances.
type SharedErrors = (Vec<Matrix3x6<f64>>, Vec<Matrix6<f64>>);

/// Triangulated points of one keyframe group, with what query matching and PnP need.
struct MapPoints {
    points: Vec<Vector3<f64>>,
    descriptors: DescriptorSet,
    pixel_covariances: Vec<Matrix3<f64>>,
    /// Row-major points × group keyframes, with their covariances (when the map has them).
    shared: Option<SharedErrors>,
}

/// Localizes frame after frame against a [`Map`], keeping the motion history.
pub struct Localizer {
    map: Arc<Map>,
    options: LocalizerOptions,
    history: VecDeque<(f64, SE3, Matrix6<f64>)>,
    cache: HashMap<(usize, Vec<usize>), Arc<MapPoints>>,
}

fn ms(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

impl Localizer {
    /// A localizer with an empty history.
    pub fn new(map: Arc<Map>, options: LocalizerOptions) -> Self {
        Self { map, options, history: VecDeque::new(), cache: HashMap::new() }
    }

    /// Forgets the motion history (e.g. after a jump).
    pub fn reset(&mut self) {
        self.history.clear();
    }

    /// Localizes one frame; see the module doc.
    ///
    /// # Errors
    /// Invalid frames: keypoints and descriptors of different counts, a non-increasing
    /// timestamp, descriptors the map cannot compare with, a missing global descriptor.
    /// A frame that cannot be localized is not an error: it comes back with source `Lost`.
    pub fn localize(&mut self, frame: &Frame<'_>) -> Result<Localization> {
        let start = Instant::now();
        let n_desc = match frame.descriptors {
            Descriptors::Binary { data, width } => data.len() / width.max(1),
            Descriptors::Float { data, width } => data.len() / width.max(1),
        };
        if n_desc != frame.keypoints.len() {
            return Err(GeolocError::invalid(
                "descriptors",
                format!("{n_desc} descriptors for {} keypoints", frame.keypoints.len()),
            ));
        }
        if !frame.timestamp.is_finite() || self.history.back().is_some_and(|(t, _, _)| frame.timestamp <= *t) {
            return Err(GeolocError::invalid(
                "timestamp",
                format!("must be finite and increase, got {}", frame.timestamp),
            ));
        }
        let mut timings = Timings::default();
        let t = Instant::now();
        let keyframe = self.map.retrieve(&frame.descriptors, frame.global)?;
        timings.retrieval_ms = ms(t);
        let t = Instant::now();
        let group = select_keyframes(&self.map.poses(), keyframe, &self.options.keyframes)?;
        timings.keyframes_ms = ms(t);
        let t = Instant::now();
        let points = self.map_points(keyframe, &group)?;
        timings.map_points_ms = ms(t);

        // geometric pose
        let t = Instant::now();
        let matches = match_descriptors(&frame.descriptors, &points.descriptors.view(), &self.options.matching)?;
        timings.matching_ms = ms(t);
        let t = Instant::now();
        let mut inliers = 0;
        let geometric = if matches.len() < self.options.min_correspondences {
            Err(format!("{} query-map matches < {}", matches.len(), self.options.min_correspondences))
        } else {
            let pts: Vec<Vector3<f64>> = matches.iter().map(|m| points.points[m.b]).collect();
            let px: Vec<Vector2<f64>> = matches.iter().map(|m| frame.keypoints[m.a]).collect();
            let covs: Vec<Matrix3<f64>> = matches.iter().map(|m| points.pixel_covariances[m.b]).collect();
            let k = group.len();
            let jacobians: Option<Vec<Matrix3x6<f64>>> = points
                .shared
                .as_ref()
                .map(|(j, _)| matches.iter().flat_map(|m| j[m.b * k..(m.b + 1) * k].iter().copied()).collect());
            let shared = match (&jacobians, &points.shared) {
                (Some(j), Some((_, c))) => Some(SharedPoseUncertainty { jacobians: j, pose_covariances: c }),
                _ => None,
            };
            let uncertainty = PointUncertainty { covariances: &covs, shared };
            let res = solve_pnp(&self.map.camera, &pts, &px, None, Some(&uncertainty), &self.options.pnp)?;
            inliers = res.inliers.iter().filter(|b| **b).count();
            if res.success { Ok((res.world_from_cam, res.covariance)) } else { Err(res.reason) }
        };
        timings.pnp_ms = ms(t);

        // motion model and fusion
        let t = Instant::now();
        let prediction = if self.history.len() >= 2 {
            let (ts, poses, covs): (Vec<f64>, Vec<SE3>, Vec<Matrix6<f64>>) =
                self.history.iter().fold((vec![], vec![], vec![]), |(mut a, mut b, mut c), (t, p, cv)| {
                    a.push(*t);
                    b.push(*p);
                    c.push(*cv);
                    (a, b, c)
                });
            motion_predict(&poses, &ts, frame.timestamp, Some(&covs)).ok()
        } else {
            None
        };
        let (pose, covariance, source, reason) = match (geometric, prediction) {
            (Ok((tg, cg)), Some(pred)) => {
                match fuse(&pred.world_from_cam, &pred.covariance, &tg, &cg, self.options.gate_sigma, self.options.gate)
                {
                    Ok(f) if f.details == FusionSource::Fused => {
                        (Some(f.world_from_cam), Some(f.covariance), Source::Fused, "ok".to_string())
                    }
                    Ok(f) => (
                        Some(f.world_from_cam),
                        Some(f.covariance),
                        Source::Motion,
                        "geometric pose outside the motion gate".to_string(),
                    ),
                    Err(e) => (Some(tg), Some(cg), Source::Geometric, format!("fusion skipped: {e}")),
                }
            }
            (Ok((tg, cg)), None) => (Some(tg), Some(cg), Source::Geometric, "ok (no motion history yet)".to_string()),
            (Err(why), Some(pred)) => (
                Some(pred.world_from_cam),
                Some(pred.covariance),
                Source::Motion,
                format!("geometric locator failed: {why}"),
            ),
            (Err(why), None) => {
                (None, None, Source::Lost, format!("geometric locator failed and no motion history: {why}"))
            }
        };
        timings.motion_fusion_ms = ms(t);
        if let (Some(p), Some(c)) = (pose, covariance) {
            self.history.push_back((frame.timestamp, p, c));
            while self.history.len() > self.options.history.max(2) {
                self.history.pop_front();
            }
        }
        timings.total_ms = ms(start);
        Ok(Localization { world_from_cam: pose, covariance, source, reason, keyframe, inliers, timings })
    }

    /// Triangulated points of the group around `seed`: tracks from the seed's keypoints
    /// matched (and epipolar-checked) into every other group keyframe. Cached.
    fn map_points(&mut self, seed: usize, group: &[usize]) -> Result<Arc<MapPoints>> {
        let key = (seed, group.to_vec());
        if let Some(hit) = self.cache.get(&key) {
            return Ok(Arc::clone(hit));
        }
        let map = &self.map;
        let kf = &map.keyframes;
        let seed_local = group.iter().position(|&g| g == seed).expect("invariant: the group holds its seed");
        let (mut cam_ids, mut track_ids, mut pixels) = (Vec::new(), Vec::new(), Vec::new());
        for (local, &g) in group.iter().enumerate() {
            if g == seed {
                continue;
            }
            let matches =
                match_descriptors(&kf[seed].descriptors.view(), &kf[g].descriptors.view(), &self.options.matching)?;
            let kept = epipolar_filter(
                &map.camera,
                &kf[seed].world_from_cam,
                &kf[g].world_from_cam,
                &kf[seed].keypoints,
                &kf[g].keypoints,
                &matches,
                self.options.epipolar_px,
            )?;
            for m in kept {
                cam_ids.push(local);
                track_ids.push(m.a);
                pixels.push(kf[g].keypoints[m.b]);
            }
        }
        // the seed's own observation of every track that reached another keyframe
        let mut tracked: Vec<usize> = track_ids.clone();
        tracked.sort_unstable();
        tracked.dedup();
        for &i in &tracked {
            cam_ids.push(seed_local);
            track_ids.push(i);
            pixels.push(kf[seed].keypoints[i]);
        }
        let poses: Vec<SE3> = group.iter().map(|&g| kf[g].world_from_cam).collect();
        let covs: Option<Vec<Matrix6<f64>>> =
            map.pose_covariances.as_ref().map(|c| group.iter().map(|&g| c[g]).collect());
        let tri = triangulate(
            &map.camera,
            &poses,
            covs.as_deref(),
            &cam_ids,
            &track_ids,
            &pixels,
            &self.options.triangulation,
        )?;
        let by_id = |i: usize| tri.point(i).expect("invariant: tracked holds exactly the triangulated track ids");
        let valid: Vec<usize> = tracked.iter().copied().filter(|&i| by_id(i).status == TrackStatus::Valid).collect();
        let k = group.len();
        let shared = covs.map(|c| {
            let mut jac = vec![Matrix3x6::zeros(); valid.len() * k];
            for (row, &i) in valid.iter().enumerate() {
                for (cam, d) in &by_id(i).pose_jacobians {
                    jac[row * k + cam] = *d;
                }
            }
            (jac, c)
        });
        let points = Arc::new(MapPoints {
            points: valid.iter().map(|&i| by_id(i).point).collect(),
            descriptors: kf[seed].descriptors.select(&valid),
            pixel_covariances: valid.iter().map(|&i| by_id(i).pixel_covariance).collect(),
            shared,
        });
        self.cache.insert(key, Arc::clone(&points));
        Ok(points)
    }
}
