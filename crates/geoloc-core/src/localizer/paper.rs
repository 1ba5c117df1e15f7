//! The paper's geometric locator (`Locator::Paper`), steps (a)–(c) of the localizer:
//!
//! (a) retrieval of one keyframe ([`crate::map::Map::retrieve`]); (b) the co-visible keyframe group
//! around it ([`select_keyframes`]); (c) forward intersection — tracks of the seed's
//! keypoints matched into every other group keyframe and epipolar-checked with the known
//! poses ([`pair_matches`], or the map's prepared matches), triangulated with the keyframe
//! poses' covariances ([`triangulate`]) and cached per (seed, group) — then backward
//! intersection: the query matched to the group's points and PnP with the points'
//! uncertainty and the keyframe poses' shared uncertainty ([`solve_pnp_with_pixel_sigmas`]),
//! giving T_G and C_G (right perturbation of world_from_cam, translation first), checked by
//! the acceptance test ([`super::acceptance`]). Tracking: a frame whose retrieved group gives
//! fewer than half the last frame's inliers is also tried against the last frame's group.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Matrix3, Matrix3x6, Matrix6, Vector2, Vector3};

use super::{Estimate, Frame, GeometricPose, Localizer, Timings, acceptance, ms};
use crate::error::Result;
use crate::keyframes::select_keyframes;
use crate::lie::SE3;
use crate::map::DescriptorSet;
use crate::map::group_matches::pair_matches;
use crate::matching::match_descriptors;
use crate::pnp::{PointUncertainty, SharedPoseUncertainty, solve_pnp_with_pixel_sigmas};
use crate::triangulate::{TrackStatus, triangulate};

/// D_jk (row-major points × group keyframes) and the group keyframes' pose covariances.
type SharedErrors = (Vec<Matrix3x6<f64>>, Vec<Matrix6<f64>>);

/// Triangulated points of one keyframe group, with what query matching and PnP need.
pub(super) struct MapPoints {
    points: Vec<Vector3<f64>>,
    descriptors: DescriptorSet,
    pixel_covariances: Vec<Matrix3<f64>>,
    /// Row-major points × group keyframes, with their covariances (when the map has them).
    shared: Option<SharedErrors>,
}

impl Localizer {
    /// The paper's geometric locator: (a) retrieval, (b) the co-visible keyframe group
    /// around the retrieved keyframe, (c) forward intersection (cached per group), then
    /// backward intersection. The keyframe whose group gave the pose, T_G and C_G or why
    /// not, the inliers; and a note when the pose came from tracking.
    ///
    /// Tracking (sequential use): when the retrieved group gives fewer than half the inliers
    /// of the last frame whose geometric pose was used (or none), and the last frame's seed
    /// keyframe is another one, its group is tried too and the pose with more inliers kept.
    /// One wrong retrieval (7-Scenes 600–699: frames 674–678 retrieve keyframe 182, whose
    /// group gives 13–18 inliers and poses 21–27 cm off, between frames of 100+ inliers)
    /// otherwise passes the gate, bends the motion history and gets the next good pose
    /// rejected. A frame localized alone (after [`Localizer::reset`]) has no last frame.
    pub(super) fn paper_pose(
        &mut self,
        frame: &Frame<'_>,
        timings: &mut Timings,
    ) -> Result<(GeometricPose, Option<String>)> {
        let t = Instant::now();
        let keyframe = self.map.retrieve(&frame.retrieval_query())?;
        timings.retrieval_ms = ms(t);
        let (geometric, inliers) = self.group_pose(frame, keyframe, timings)?;
        if let Some((last, support)) = self.last_support
            && last != keyframe
            && 2 * inliers < support
        {
            let (tracked, n) = self.group_pose(frame, last, timings)?;
            if n > inliers && tracked.is_ok() {
                let note = format!(
                    "tracked through the last frame's keyframe {last} ({n} inliers; the retrieved keyframe {keyframe} gave {inliers})"
                );
                return Ok(((last, tracked, n), Some(note)));
            }
        }
        Ok(((keyframe, geometric, inliers), None))
    }

    /// (b) and (c) for the group around `seed`: T_G and C_G or why not, the inliers.
    fn group_pose(
        &mut self,
        frame: &Frame<'_>,
        seed: usize,
        timings: &mut Timings,
    ) -> Result<(std::result::Result<Estimate, String>, usize)> {
        let t = Instant::now();
        let group = select_keyframes(&self.map.poses(), seed, &self.options.keyframes)?;
        timings.keyframes_ms += ms(t);
        let t = Instant::now();
        let points = self.map_points(seed, &group)?;
        timings.map_points_ms += ms(t);
        self.geometric_pose(frame, seed, &points, group.len(), timings)
    }

    /// (c) backward intersection: the query's keypoints matched to the group's points, then
    /// PnP with the points' uncertainty (and the keyframe poses' shared uncertainty): T_G, C_G,
    /// or why not; with the PnP inlier count.
    pub(super) fn geometric_pose(
        &self,
        frame: &Frame<'_>,
        seed: usize,
        points: &MapPoints,
        group_len: usize,
        timings: &mut Timings,
    ) -> Result<(std::result::Result<Estimate, String>, usize)> {
        let t = Instant::now();
        let matches = match_descriptors(&frame.descriptors, &points.descriptors.view(), &self.options.matching)?;
        timings.matching_ms += ms(t);
        let t = Instant::now();
        if matches.len() < self.options.min_correspondences {
            timings.pnp_ms += ms(t);
            let why = format!("{} query-map matches < {}", matches.len(), self.options.min_correspondences);
            return Ok((Err(why), 0));
        }
        let pts: Vec<Vector3<f64>> = matches.iter().map(|m| points.points[m.b]).collect();
        let px: Vec<Vector2<f64>> = matches.iter().map(|m| frame.keypoints[m.a]).collect();
        let covs: Vec<Matrix3<f64>> = matches.iter().map(|m| points.pixel_covariances[m.b]).collect();
        let jacobians: Option<Vec<Matrix3x6<f64>>> = points.shared.as_ref().map(|(j, _)| {
            matches.iter().flat_map(|m| j[m.b * group_len..(m.b + 1) * group_len].iter().copied()).collect()
        });
        let shared = match (&jacobians, &points.shared) {
            (Some(j), Some((_, c))) => Some(SharedPoseUncertainty { jacobians: j, pose_covariances: c }),
            _ => None,
        };
        let uncertainty = PointUncertainty { covariances: &covs, shared };
        let sigmas: Option<Vec<f64>> = frame.pixel_sigmas.map(|s| matches.iter().map(|m| s[m.a]).collect());
        let res = solve_pnp_with_pixel_sigmas(
            &self.map.camera,
            &pts,
            &px,
            sigmas.as_deref(),
            None,
            Some(&uncertainty),
            &self.options.pnp,
        )?;
        timings.pnp_ms += ms(t);
        let inliers = res.inliers.iter().filter(|b| **b).count();
        if !res.success {
            return Ok((Err(res.reason), inliers));
        }
        // every group point is a track of the seed's keypoints, matched by the seed's descriptor
        let seen = vec![self.map.keyframes[seed].world_from_cam.translation];
        let inlier_points: Vec<Vector3<f64>> =
            pts.iter().zip(&res.inliers).filter(|(_, i)| **i).map(|(x, _)| *x).collect();
        let observers = vec![seen; inlier_points.len()];
        let center = res.world_from_cam.translation;
        if let Some(why) =
            acceptance::rejection(&center, &res.covariance, &inlier_points, &observers, &self.options.acceptance)
        {
            return Ok((Err(why), inliers));
        }
        Ok((Ok(Estimate { world_from_cam: res.world_from_cam, covariance: res.covariance }), inliers))
    }

    /// (c) forward intersection: triangulated points of the group around `seed`, from
    /// tracks of the seed's keypoints matched (and epipolar-checked) into every other group
    /// keyframe. Cached per (seed, group).
    pub(super) fn map_points(&mut self, seed: usize, group: &[usize]) -> Result<Arc<MapPoints>> {
        let key = (seed, group.to_vec());
        if let Some(hit) = self.cache.get(&key) {
            return Ok(Arc::clone(hit));
        }
        let (observations, tracked) = self.group_tracks(seed, group)?;
        let kf = &self.map.keyframes;
        let poses: Vec<SE3> = group.iter().map(|&g| kf[g].world_from_cam).collect();
        let covs: Option<Vec<Matrix6<f64>>> =
            self.map.pose_covariances.as_ref().map(|c| group.iter().map(|&g| c[g]).collect());
        let tri = triangulate(
            &self.map.camera,
            &poses,
            covs.as_deref(),
            &observations.cam_ids,
            &observations.track_ids,
            &observations.pixels,
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

    /// The observations of the group's tracks (a track is a keypoint of the seed, by index):
    /// the seed's keypoints matched into each other group keyframe and epipolar-checked with
    /// the known poses, plus the seed's own observation of every track that reached another
    /// keyframe. Returns them with the sorted tracked keypoints.
    fn group_tracks(&self, seed: usize, group: &[usize]) -> Result<(Observations, Vec<usize>)> {
        let kf = &self.map.keyframes;
        let seed_local = group.iter().position(|&g| g == seed).expect("invariant: the group holds its seed");
        let o = &self.options;
        let prepared = self.map.group_matches.as_ref().filter(|_| self.prepared_matches);
        let mut obs = Observations::default();
        for (local, &g) in group.iter().enumerate() {
            if g == seed {
                continue;
            }
            let pairs = match prepared.and_then(|m| m.pair(seed, g)) {
                Some(pairs) => pairs,
                None => pair_matches(&self.map.camera, &kf[seed], &kf[g], &o.matching, o.epipolar_px)?,
            };
            for (a, b) in pairs {
                obs.push(local, a, kf[g].keypoints[b]);
            }
        }
        let mut tracked: Vec<usize> = obs.track_ids.clone();
        tracked.sort_unstable();
        tracked.dedup();
        for &i in &tracked {
            obs.push(seed_local, i, kf[seed].keypoints[i]);
        }
        Ok((obs, tracked))
    }
}

/// Observations for [`triangulate`]: camera (group position), track, pixel.
#[derive(Default)]
struct Observations {
    cam_ids: Vec<usize>,
    track_ids: Vec<usize>,
    pixels: Vec<Vector2<f64>>,
}

impl Observations {
    fn push(&mut self, cam: usize, track: usize, pixel: Vector2<f64>) {
        self.cam_ids.push(cam);
        self.track_ids.push(track);
        self.pixels.push(pixel);
    }
}
