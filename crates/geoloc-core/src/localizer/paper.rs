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

use crate::camera::Camera;

use super::{Estimate, Frame, GeometricPose, Localizer, Timings, acceptance, ms};
use crate::error::{GeolocError, Result};
use crate::keyframes::select_keyframes;
use crate::lie::SE3;
use crate::map::DescriptorSet;
use crate::map::group_matches::pair_matches;
use crate::matching::match_descriptors;
use crate::pnp::{PointUncertainty, PosePartials, SharedPoseUncertainty, solve_pnp_with_pixel_sigmas};
use crate::triangulate::{PointCovarianceTerms, TrackStatus, point_covariance_terms, triangulate, view_weight};

/// Triangulated points of one keyframe group, with what query matching and PnP need.
///
/// A point keeps the group positions of its inlier views, not its covariance terms: Σ_pix
/// and the D_k (∂X/∂δ_k, shared by every point a keyframe sees) are recomputed for the points
/// a query matched ([`MapPoints::covariance_terms`], bit for bit the triangulation's). Kept
/// for every point, the D_k alone are 144 bytes per point and group keyframe: 364 MB for the
/// groups of a 600-keyframe 7-Scenes map, against about 20 MB for what is kept here.
pub(super) struct MapPoints {
    points: Vec<Vector3<f64>>,
    descriptors: DescriptorSet,
    /// Point j's inlier views are `view_cams[view_offsets[j]..view_offsets[j + 1]]` (group
    /// positions, in the triangulation's order).
    view_offsets: Vec<u32>,
    view_cams: Vec<u32>,
    /// The group keyframes' poses, and their covariances when the map has them.
    poses: Vec<SE3>,
    pose_covariances: Option<Vec<Matrix6<f64>>>,
}

impl MapPoints {
    /// Σ_pix and the D_k of point `j` (see [`point_covariance_terms`]), from its inlier views
    /// with the triangulation's pixel σ.
    fn covariance_terms(&self, camera: &Camera, j: usize, pixel_sigma: f64) -> Result<PointCovarianceTerms> {
        let cams = &self.view_cams[self.view_offsets[j] as usize..self.view_offsets[j + 1] as usize];
        let (x, poses, covs) = (&self.points[j], &self.poses[..], self.pose_covariances.as_deref());
        let views = cams.iter().map(|&c| (c as usize, view_weight(camera, poses, covs, pixel_sigma, c as usize, x)));
        point_covariance_terms(camera, poses, covs, pixel_sigma, x, views)
            .ok_or_else(|| GeolocError::invalid("map", format!("group point {j} has a singular covariance")))
    }
}

impl Localizer {
    /// The paper's geometric locator from the retrieved `keyframe` ((a) retrieval is the
    /// caller's): (b) the co-visible keyframe group around it, (c) forward intersection
    /// (cached per group), then backward intersection. The keyframe whose group gave the
    /// pose, T_G and C_G or why not, the inliers; and a note when the pose came from tracking.
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
        keyframe: usize,
        timings: &mut Timings,
    ) -> Result<(GeometricPose, Option<String>)> {
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
        let sigma = self.options.triangulation.pixel_sigma;
        let terms: Vec<PointCovarianceTerms> =
            matches.iter().map(|m| points.covariance_terms(&self.map.camera, m.b, sigma)).collect::<Result<_>>()?;
        let covs: Vec<Matrix3<f64>> = terms.iter().map(|t| t.pixel).collect();
        // D_jk of every group keyframe k, zero where point j has no view in k
        let jacobians: Option<Vec<PosePartials>> = points.pose_covariances.as_ref().map(|_| {
            terms
                .iter()
                .map(|t| {
                    let mut row: PosePartials = (0..group_len).map(|k| (k, Matrix3x6::zeros())).collect();
                    for (cam, d) in &t.pose_jacobians {
                        row[*cam].1 = *d;
                    }
                    row
                })
                .collect()
        });
        let shared = match (&jacobians, &points.pose_covariances) {
            (Some(j), Some(c)) => Some(SharedPoseUncertainty { jacobians: j, pose_covariances: c }),
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
        Ok((
            Ok(Estimate {
                world_from_cam: res.world_from_cam,
                covariance: res.covariance,
                pixel_covariance: res.pixel_covariance,
            }),
            inliers,
        ))
    }

    /// (c) forward intersection: triangulated points of the group around `seed`, from
    /// tracks of the seed's keypoints matched (and epipolar-checked) into every other group
    /// keyframe. Cached per (seed, group).
    pub(super) fn map_points(&mut self, seed: usize, group: &[usize]) -> Result<Arc<MapPoints>> {
        let key = (seed, group.to_vec());
        if let Some(hit) = self.cache.get(&key) {
            return Ok(Arc::clone(hit));
        }
        let points = Arc::new(self.triangulated_group(seed, group)?);
        self.cache.insert(key, Arc::clone(&points));
        Ok(points)
    }

    /// Triangulates the group of every keyframe ahead, in parallel, into the cache
    /// ([`Localizer::map_points`]): a frame then never pays for forward intersection (on the
    /// paper's 7-Scenes split, triangulating a group on a frame's first use of it made the
    /// per-frame p99 2.3× the median). The cached points are those [`Localizer::map_points`]
    /// would compute.
    pub(super) fn prepare_groups(&mut self) -> Result<()> {
        let poses = self.map.poses();
        let groups: Vec<Vec<usize>> = (0..poses.len())
            .map(|seed| select_keyframes(&poses, seed, &self.options.keyframes))
            .collect::<Result<_>>()?;
        let points = crate::parallel::map_indices(groups.len(), 2, |seed| self.triangulated_group(seed, &groups[seed]));
        for (seed, (group, points)) in groups.into_iter().zip(points).enumerate() {
            self.cache.insert((seed, group), Arc::new(points?));
        }
        Ok(())
    }

    /// (c) forward intersection of the group around `seed` (see [`Localizer::map_points`]):
    /// its valid points with their inlier views.
    fn triangulated_group(&self, seed: usize, group: &[usize]) -> Result<MapPoints> {
        let (observations, tracked) = self.group_tracks(seed, group)?;
        let kf = &self.map.keyframes;
        let poses: Vec<SE3> = group.iter().map(|&g| kf[g].world_from_cam).collect();
        let pose_covariances: Option<Vec<Matrix6<f64>>> =
            self.map.pose_covariances.as_ref().map(|c| group.iter().map(|&g| c[g]).collect());
        let tri = triangulate(
            &self.map.camera,
            &poses,
            pose_covariances.as_deref(),
            &observations.cam_ids,
            &observations.track_ids,
            &observations.pixels,
            &self.options.triangulation,
        )?;
        let by_id = |i: usize| tri.point(i).expect("invariant: tracked holds exactly the triangulated track ids");
        let valid: Vec<usize> = tracked.iter().copied().filter(|&i| by_id(i).status == TrackStatus::Valid).collect();
        // each valid point's inlier views in input order (the triangulation's order): the
        // observations it kept, stably sorted by point
        let mut views: Vec<(usize, u32)> = (0..observations.track_ids.len())
            .filter(|&o| tri.observation_inliers[o])
            .map(|o| {
                let row =
                    valid.binary_search(&observations.track_ids[o]).expect("invariant: kept views are valid points'");
                (row, u32::try_from(observations.cam_ids[o]).expect("invariant: a group has < 2³² keyframes"))
            })
            .collect();
        views.sort_by_key(|&(row, _)| row);
        let mut view_offsets = vec![0u32; valid.len() + 1];
        for &(row, _) in &views {
            view_offsets[row + 1] += 1;
        }
        for row in 0..valid.len() {
            view_offsets[row + 1] += view_offsets[row];
        }
        let view_cams = views.into_iter().map(|(_, cam)| cam).collect();
        Ok(MapPoints {
            points: valid.iter().map(|&i| by_id(i).point).collect(),
            descriptors: kf[seed].descriptors.select(&valid),
            view_offsets,
            view_cams,
            poses,
            pose_covariances,
        })
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

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::localizer::{Frame, Localization, LocalizerOptions, Locator};
    use crate::map::BuildSteps;
    use crate::map::model::fixture;
    use crate::testing::{SplitMix64, walk};
    use crate::triangulate::TriangulatedPoint;

    /// Keyframe pose covariances of about 1 cm and 0.2° (translation first).
    fn small_pose_covariances(n: usize) -> Vec<Matrix6<f64>> {
        let diagonal = nalgebra::Vector6::new(1e-4, 1.2e-4, 0.8e-4, 1.2e-5, 1e-5, 1.5e-5);
        vec![Matrix6::from_diagonal(&diagonal); n]
    }

    /// A paper localizer on a map with prepared pair matches triangulates every keyframe's
    /// group when it starts: frames add nothing to the cache, and the results are bit for bit
    /// those of a localizer that triangulates each group on first use.
    #[test]
    fn groups_prepared_at_start_give_the_results_of_first_use() {
        let (world, mut map, _) = fixture::scene(30, false);
        map.pose_covariances = Some(small_pose_covariances(map.keyframes.len()));
        let steps = BuildSteps { group_matches: true, ..BuildSteps::default() };
        let map = Arc::new(map.with_build_steps(&steps).expect("prepared"));
        let options = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
        let mut prepared = Localizer::new(Arc::clone(&map), options).expect("localizer");
        assert!(prepared.prepared_matches);
        assert_eq!(prepared.cache.len(), map.keyframes.len());
        let mut lazy = Localizer::unprepared(map, options).expect("localizer");
        assert!(lazy.cache.is_empty());
        let mut rng = SplitMix64::new(4);
        let bits = |l: &Localization| {
            l.estimate
                .as_ref()
                .map(|e| (e.world_from_cam.translation.map(f64::to_bits), e.covariance.map(f64::to_bits)))
        };
        for i in 0..8 {
            let truth = walk(0.3 + i as f64 * 0.3, 0.15, -1.5);
            let (keypoints, data) = world.observe(&mut rng, &truth, 5);
            let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
            let frame =
                Frame { timestamp: i as f64, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
            let before = prepared.cache.len();
            let (a, b) = (prepared.localize(&frame).expect("valid"), lazy.localize(&frame).expect("valid"));
            assert_eq!(prepared.cache.len(), before, "frame {i} triangulated a group");
            assert!(a.estimate.is_some(), "frame {i}: {}", a.reason);
            assert_eq!(bits(&a), bits(&b), "frame {i}");
            assert_eq!(a.source, b.source);
        }
        assert!(!lazy.cache.is_empty());
    }

    /// A group's points keep their inlier views, and the covariance terms recomputed from them
    /// are the triangulation's own (Σ_pix, D_k), bit for bit, for every point of every group —
    /// on a map whose keyframe poses carry covariances (so the D_k are not empty).
    #[test]
    fn recomputed_covariance_terms_are_the_triangulations() {
        let (_, mut map, _) = fixture::scene(20, true);
        map.pose_covariances = Some(small_pose_covariances(map.keyframes.len()));
        let options = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
        let localizer = Localizer::unprepared(Arc::new(map), options).expect("localizer");
        let poses = localizer.map.poses();
        let mut checked = 0;
        for seed in 0..poses.len() {
            let group = select_keyframes(&poses, seed, &options.keyframes).expect("group");
            let points = localizer.triangulated_group(seed, &group).expect("triangulated");
            // the reference: the triangulation's own points, with the covariances it returned
            let (obs, tracked) = localizer.group_tracks(seed, &group).expect("tracks");
            let tri = triangulate(
                &localizer.map.camera,
                &points.poses,
                points.pose_covariances.as_deref(),
                &obs.cam_ids,
                &obs.track_ids,
                &obs.pixels,
                &options.triangulation,
            )
            .expect("triangulated");
            let valid: Vec<&TriangulatedPoint> =
                tracked.iter().filter_map(|&i| tri.point(i)).filter(|p| p.status == TrackStatus::Valid).collect();
            assert_eq!(valid.len(), points.points.len());
            for (j, reference) in valid.iter().enumerate() {
                let terms = points
                    .covariance_terms(&localizer.map.camera, j, options.triangulation.pixel_sigma)
                    .expect("regular");
                assert_eq!(terms.pixel.map(f64::to_bits), reference.pixel_covariance.map(f64::to_bits), "point {j}");
                assert!(!terms.pose_jacobians.is_empty());
                assert_eq!(terms.pose_jacobians, reference.pose_jacobians, "point {j}");
                checked += 1;
            }
        }
        assert!(checked > 100, "only {checked} points checked");
    }
}
