//! The map-level 3D model: points triangulated once, at map time, from all
//! keyframes with their known poses, for the model locator (`Locator::Model`).
//!
//! Build, every step deterministic and bit-identical with any thread count:
//! 1. **Pose-neighbour pairs.** For each keyframe a, the other keyframes b with baseline
//!    ‖t_a − t_b‖ ∈ (`min_distance_m`, `max_distance_m`) and relative rotation angle
//!    ∠(R_aᵀR_b) < `max_angle_rad`, ordered by |baseline − `baseline_m`| (ties: lower index),
//!    the first `neighbours` of them, then the next `revisit_neighbours` in that order that are
//!    at least `revisit_gap` keyframes away in capture order (revisits of the place); the
//!    pairs (min, max) of all keyframes, sorted, deduplicated.
//! 2. **Matches** of each pair: mutual ratio matching of the local descriptors
//!    ([`match_descriptors`]), then the Sampson check against the epipolar geometry of the two
//!    known poses ([`epipolar_checked`], `epipolar_px`) — the localizer's own keyframe check.
//! 3. **Tracks** by union-find over the global keypoint index g = offset_k + i, pairs in
//!    order, the larger root joining the smaller (so a track's root is its smallest g);
//!    tracks are numbered by root. A track with two observations in one keyframe (matching
//!    was inconsistent) is dropped whole, as is one shorter than two.
//! 4. **Points**: [`triangulate`] (forward intersection with the keyframe poses and their
//!    covariances, if the map has them); a point is kept when it is valid and has at least
//!    `min_track_length` inlier observations (reprojection ≤ `max_residual_px`); outlier
//!    observations do not map to it. Σ_X is the triangulation's full point covariance
//!    (pixel noise and, if known, pose-label noise).
//! 5. **Representative descriptor** of a point: the medoid of its inlier observations'
//!    descriptors, argmin_i Σ_j d(f_i, f_j) (Hamming or L2; ties: the first observation in
//!    keyframe order).
//!
//! Stored per point: X (world), Σ_X (3×3), the representative descriptor; per (keyframe,
//! keypoint): the point id, if any. The observing keyframes of each point are derived from
//! the latter (sorted).

use nalgebra::{Matrix3, Vector2, Vector3};

use super::Keyframe;
use super::group_matches::epipolar_checked;
use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::matching::{DescriptorSet, Match, MatchOptions, match_descriptors};
use crate::parallel::{map_indices, map_slice};
use crate::triangulate::{TrackStatus, TriangulationOptions, triangulate};

/// How the [`SceneModel`] is built (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelOptions {
    /// Pose neighbours matched per keyframe (default 6).
    pub neighbours: usize,
    /// Largest baseline of a pair (m, default 0.8).
    pub max_distance_m: f64,
    /// Smallest baseline of a pair (m, default 0.03): below, a pair triangulates nothing.
    pub min_distance_m: f64,
    /// Largest relative rotation of a pair (rad, default 30°).
    pub max_angle_rad: f64,
    /// Preferred baseline (m, default 0.2): neighbours closest to it come first.
    pub baseline_m: f64,
    /// Keyframe–keyframe matching (default mutual, ratio 0.8).
    pub matching: MatchOptions,
    /// Sampson threshold of the epipolar check (px, default 2).
    pub epipolar_px: f64,
    /// Forward intersection (default: ε_r = 4 px, smallest ray angle 2°).
    pub triangulation: TriangulationOptions,
    /// Fewest inlier observations of a kept point (default 2, at least 2).
    pub min_track_length: usize,
    /// Revisits matched per keyframe besides its `neighbours` (default 0): the next candidates
    /// by the same order that lie at least `revisit_gap` keyframes away in capture order.
    /// The nearest-baseline neighbours of a keyframe are almost always the frames just
    /// before and after it; a part of the trajectory that only revisits a place shares no
    /// pair with it then, and its tracks cannot tie the two passes together.
    pub revisit_neighbours: usize,
    /// Fewest keyframes between a and b in capture order for b to count as a revisit of a
    /// (default 20).
    pub revisit_gap: usize,
}

impl Default for ModelOptions {
    fn default() -> Self {
        Self {
            neighbours: 6,
            max_distance_m: 0.8,
            min_distance_m: 0.03,
            max_angle_rad: 30f64.to_radians(),
            baseline_m: 0.2,
            matching: MatchOptions::default(),
            epipolar_px: 2.0,
            triangulation: TriangulationOptions {
                max_residual_px: 4.0,
                min_angle_rad: 2f64.to_radians(),
                ..TriangulationOptions::default()
            },
            min_track_length: 2,
            revisit_neighbours: 0,
            revisit_gap: 20,
        }
    }
}

impl ModelOptions {
    /// Checks the options the build uses itself (matching and triangulation check theirs).
    ///
    /// # Errors
    /// `neighbours` 0, `min_track_length` < 2, distances or angles not finite and ≥ 0 (or
    /// `max_distance_m` ≤ `min_distance_m`), `epipolar_px` not finite and > 0.
    pub fn check(&self) -> Result<()> {
        if self.neighbours == 0 {
            return Err(GeolocError::invalid("neighbours", "must be ≥ 1"));
        }
        if self.min_track_length < 2 {
            return Err(GeolocError::invalid("min_track_length", "must be ≥ 2"));
        }
        let finite = [
            ("max_distance_m", self.max_distance_m),
            ("min_distance_m", self.min_distance_m),
            ("max_angle_rad", self.max_angle_rad),
            ("baseline_m", self.baseline_m),
        ];
        if let Some((name, v)) = finite.into_iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
            return Err(GeolocError::invalid(name, format!("must be finite and ≥ 0, got {v}")));
        }
        if self.max_distance_m <= self.min_distance_m {
            return Err(GeolocError::invalid("max_distance_m", "must be larger than min_distance_m"));
        }
        if !(self.epipolar_px.is_finite() && self.epipolar_px > 0.0) {
            return Err(GeolocError::invalid(
                "epipolar_px",
                format!("must be finite and > 0, got {}", self.epipolar_px),
            ));
        }
        Ok(())
    }
}

/// The map-level 3D model (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneModel {
    /// Point positions (world).
    pub points: Vec<Vector3<f64>>,
    /// Σ_X of each point (m², world axes).
    pub covariances: Vec<Matrix3<f64>>,
    /// One representative descriptor per point (the medoid of its observations).
    pub descriptors: DescriptorSet,
    /// Per keyframe, per keypoint: the point it observes, if any.
    pub point_ids: Vec<Vec<Option<usize>>>,
    /// Per point: the keyframes observing it (sorted, derived from `point_ids`).
    observers: Vec<Vec<usize>>,
    /// Per keyframe: the points it observes, in keypoint order (derived from `point_ids`).
    observed: Vec<Vec<usize>>,
}

impl SceneModel {
    /// A model from its stored parts; derives the observers of every point.
    ///
    /// # Errors
    /// `InvalidInput` when the counts disagree, a point id is out of range, a point is not
    /// finite, or a point has no observation.
    pub fn from_parts(
        points: Vec<Vector3<f64>>,
        covariances: Vec<Matrix3<f64>>,
        descriptors: DescriptorSet,
        point_ids: Vec<Vec<Option<usize>>>,
    ) -> Result<Self> {
        let n = points.len();
        if covariances.len() != n || descriptors.len() != n {
            return Err(GeolocError::invalid(
                "model",
                format!("{n} points, {} covariances, {} descriptors", covariances.len(), descriptors.len()),
            ));
        }
        if let Some(i) = points
            .iter()
            .zip(&covariances)
            .position(|(p, c)| !(p.iter().all(|v| v.is_finite()) && c.iter().all(|v| v.is_finite())))
        {
            return Err(GeolocError::NonFinite { name: "model.points".into(), index: i });
        }
        let mut observers = vec![Vec::new(); n];
        for (k, ids) in point_ids.iter().enumerate() {
            for id in ids.iter().flatten() {
                let list = observers.get_mut(*id).ok_or_else(|| {
                    GeolocError::invalid("model.point_ids", format!("keyframe {k} refers to point {id} of {n}"))
                })?;
                if list.last() != Some(&k) {
                    list.push(k);
                }
            }
        }
        if let Some(i) = observers.iter().position(Vec::is_empty) {
            return Err(GeolocError::invalid("model.point_ids", format!("point {i} has no observation")));
        }
        let observed = point_ids.iter().map(|ids| ids.iter().flatten().copied().collect()).collect();
        Ok(Self { points, covariances, descriptors, point_ids, observers, observed })
    }

    /// Every observation of a point: (keyframe, point, the keypoint's pixel in `keyframes`,
    /// the keyframes the model was built from), keyframe by keyframe in keypoint order.
    pub fn observations<'a>(
        &'a self,
        keyframes: &'a [Keyframe],
    ) -> impl Iterator<Item = (usize, usize, Vector2<f64>)> + 'a {
        self.point_ids.iter().zip(keyframes).enumerate().flat_map(|(k, (ids, kf))| {
            ids.iter().zip(&kf.keypoints).filter_map(move |(id, px)| id.map(|point| (k, point, *px)))
        })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether the model has no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The keyframes observing point `i` (sorted).
    pub fn observers(&self, i: usize) -> &[usize] {
        &self.observers[i]
    }

    /// The points keyframe `k` observes, in keypoint order (the `Some` entries of
    /// `point_ids[k]`).
    pub fn observed(&self, k: usize) -> &[usize] {
        &self.observed[k]
    }

    /// Builds the model from `keyframes` (with their known poses); see the module doc.
    ///
    /// # Errors
    /// Bad options; errors of matching or triangulation (descriptors the map already checked).
    pub fn build(
        camera: &Camera,
        keyframes: &[Keyframe],
        pose_covariances: Option<&[nalgebra::Matrix6<f64>]>,
        options: &ModelOptions,
    ) -> Result<Self> {
        options.check()?;
        let pair_matches = PairMatches::compute(keyframes, options)?;
        Self::assemble(camera, keyframes, pose_covariances, options, &pair_matches)
    }

    /// [`SceneModel::build`] from steps 1 and 2's descriptor matches computed before
    /// ([`PairMatches::compute`] on the same keyframes' poses and descriptors); the result is
    /// the same, bit for bit. The keypoints (and so the camera correction) may have changed
    /// since: they enter from the epipolar check on.
    ///
    /// # Errors
    /// As [`SceneModel::build`]; `InvalidInput` (`pair_matches`) when they were computed with
    /// other pair or matching options, or for keyframes of other sizes.
    pub fn from_pair_matches(
        camera: &Camera,
        keyframes: &[Keyframe],
        pose_covariances: Option<&[nalgebra::Matrix6<f64>]>,
        options: &ModelOptions,
        pair_matches: &PairMatches,
    ) -> Result<Self> {
        options.check()?;
        if !pair_matches.serves(options) || pair_matches.sizes != sizes_of(keyframes) {
            return Err(GeolocError::invalid(
                "pair_matches",
                "computed for other keyframes or with other pair or matching options",
            ));
        }
        Self::assemble(camera, keyframes, pose_covariances, options, pair_matches)
    }

    /// Steps 2 (epipolar check) to 5 from pair matches computed for these keyframes with
    /// these options (by the caller itself: nothing is checked).
    pub(crate) fn assemble(
        camera: &Camera,
        keyframes: &[Keyframe],
        pose_covariances: Option<&[nalgebra::Matrix6<f64>]>,
        options: &ModelOptions,
        pair_matches: &PairMatches,
    ) -> Result<Self> {
        Ok(Self::assemble_with_rejected(camera, keyframes, pose_covariances, options, pair_matches)?.0)
    }

    /// [`SceneModel::assemble`], and the views of its points that the triangulation rejected
    /// ([`RejectedView`], keyframe by keyframe in track order): what the poses say does not
    /// fit — an adjustment that moves the poses may find that it does.
    pub(crate) fn assemble_with_rejected(
        camera: &Camera,
        keyframes: &[Keyframe],
        pose_covariances: Option<&[nalgebra::Matrix6<f64>]>,
        options: &ModelOptions,
        pair_matches: &PairMatches,
    ) -> Result<(Self, Vec<RejectedView>)> {
        let poses: Vec<SE3> = keyframes.iter().map(|k| k.world_from_cam).collect();
        let pairs = &pair_matches.pairs;
        let matches = epipolar_matches(camera, keyframes, pair_matches, options)?;
        let tracks = tracks(keyframes, pairs, &matches);
        let (mut cam_ids, mut track_ids, mut pixels) = (Vec::new(), Vec::new(), Vec::new());
        for (t, track) in tracks.iter().enumerate() {
            for &(k, i) in track {
                cam_ids.push(k);
                track_ids.push(t);
                pixels.push(keyframes[k].keypoints[i]);
            }
        }
        let tri = triangulate(camera, &poses, pose_covariances, &cam_ids, &track_ids, &pixels, &options.triangulation)?;
        let mut point_ids: Vec<Vec<Option<usize>>> = keyframes.iter().map(|k| vec![None; k.keypoints.len()]).collect();
        let (mut points, mut covariances, mut members) = (Vec::new(), Vec::new(), Vec::new());
        let mut rejected = Vec::new();
        let mut o = 0;
        for (t, track) in tracks.iter().enumerate() {
            let inliers = &tri.observation_inliers[o..o + track.len()];
            o += track.len();
            let kept: Vec<(usize, usize)> =
                track.iter().zip(inliers).filter(|(_, inlier)| **inlier).map(|(obs, _)| *obs).collect();
            let Some(p) = tri.point(t) else { continue };
            if p.status != TrackStatus::Valid || kept.len() < options.min_track_length {
                continue;
            }
            for &(k, i) in &kept {
                point_ids[k][i] = Some(points.len());
            }
            let outliers = track.iter().zip(inliers).filter(|(_, inlier)| !**inlier);
            rejected.extend(outliers.map(|(&(keyframe, keypoint), _)| RejectedView {
                keyframe,
                keypoint,
                point: points.len(),
            }));
            points.push(p.point);
            covariances.push(p.covariance);
            members.push(kept);
        }
        let descriptors = representative_descriptors(keyframes, &members);
        Ok((Self::from_parts(points, covariances, descriptors, point_ids)?, rejected))
    }
}

/// A view of a point that its triangulation rejected: keyframe `keyframe`'s keypoint
/// `keypoint`, matched into the track of point `point`, lies beyond the reprojection limit
/// of the point the other views agree on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct RejectedView {
    pub(crate) keyframe: usize,
    pub(crate) keypoint: usize,
    pub(crate) point: usize,
}

/// Step 1: the pose-neighbour pairs (a, b), a < b, sorted (see the module doc).
fn neighbour_pairs(poses: &[SE3], options: &ModelOptions) -> Vec<(usize, usize)> {
    let per_keyframe = map_indices(poses.len(), 64, |a| {
        let mut candidates: Vec<(f64, usize)> = poses
            .iter()
            .enumerate()
            .filter(|&(b, _)| b != a)
            .filter_map(|(b, pb)| {
                let d = (poses[a].translation - pb.translation).norm();
                let angle = poses[a].rotation.distance(&pb.rotation);
                let ok = d > options.min_distance_m && d < options.max_distance_m && angle < options.max_angle_rad;
                ok.then_some(((d - options.baseline_m).abs(), b))
            })
            .collect();
        candidates.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        let nearest = candidates.iter().take(options.neighbours);
        let revisits = candidates
            .iter()
            .skip(options.neighbours)
            .filter(|&&(_, b)| a.abs_diff(b) >= options.revisit_gap)
            .take(options.revisit_neighbours);
        nearest.chain(revisits).map(|&(_, b)| (a.min(b), a.max(b))).collect::<Vec<_>>()
    });
    let mut pairs: Vec<(usize, usize)> = per_keyframe.into_iter().flatten().collect();
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Steps 1 and the first half of 2 of the build: the pose-neighbour pairs and each pair's
/// descriptor matches, before the epipolar check. They depend on the keyframes' poses and
/// descriptors only, so a map that corrects its keypoints ([`crate::map::Map::with_refined_intrinsics`])
/// computes them once for the calibration's tracks and its 3D model.
#[derive(Clone, Debug, PartialEq)]
pub struct PairMatches {
    /// The options they were computed with (only the pair and matching ones matter).
    options: ModelOptions,
    /// (keypoints, descriptors) per keyframe (the matches index them).
    sizes: Vec<(usize, usize)>,
    /// The pairs (a, b), a < b, sorted.
    pairs: Vec<(usize, usize)>,
    /// Per pair: the mutual ratio matches of a's and b's descriptors.
    matches: Vec<Vec<Match>>,
}

impl PairMatches {
    /// The pairs of `keyframes` and their descriptor matches (see the module doc).
    ///
    /// # Errors
    /// Bad options; errors of matching (descriptors the map already checked).
    pub fn compute(keyframes: &[Keyframe], options: &ModelOptions) -> Result<Self> {
        options.check()?;
        let poses: Vec<SE3> = keyframes.iter().map(|k| k.world_from_cam).collect();
        let pairs = neighbour_pairs(&poses, options);
        let matches = map_slice(&pairs, 2, |&(a, b)| {
            match_descriptors(&keyframes[a].descriptors.view(), &keyframes[b].descriptors.view(), &options.matching)
        })
        .into_iter()
        .collect::<Result<Vec<_>>>()?;
        Ok(Self { options: *options, sizes: sizes_of(keyframes), pairs, matches })
    }

    /// Whether a build with `options` pairs and matches keyframes as these were computed.
    pub fn serves(&self, options: &ModelOptions) -> bool {
        let pairing =
            |o: &ModelOptions| (o.neighbours, o.max_distance_m, o.min_distance_m, o.max_angle_rad, o.baseline_m);
        let revisits = |o: &ModelOptions| (o.revisit_neighbours, o.revisit_gap);
        pairing(&self.options) == pairing(options)
            && revisits(&self.options) == revisits(options)
            && self.options.matching == options.matching
    }
}

/// (keypoints, descriptors) of each keyframe.
fn sizes_of(keyframes: &[Keyframe]) -> Vec<(usize, usize)> {
    keyframes.iter().map(|k| (k.keypoints.len(), k.descriptors.len())).collect()
}

/// Step 2: per pair, the (keypoint in a, keypoint in b) matches that pass the epipolar check.
fn epipolar_matches(
    camera: &Camera,
    keyframes: &[Keyframe],
    pair_matches: &PairMatches,
    options: &ModelOptions,
) -> Result<Vec<Vec<(usize, usize)>>> {
    let jobs: Vec<(&(usize, usize), &Vec<Match>)> = pair_matches.pairs.iter().zip(&pair_matches.matches).collect();
    map_slice(&jobs, 2, |&(&(a, b), matches)| {
        epipolar_checked(camera, &keyframes[a], &keyframes[b], matches, options.epipolar_px)
    })
    .into_iter()
    .collect()
}

/// Union-find over 0..n with path halving; the larger root joins the smaller, so every
/// root is the smallest element of its set whatever the order of the unions' arguments.
struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        Self { parent: (0..n).collect() }
    }

    fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }

    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb);
        }
    }
}

/// Step 3: the tracks, each a list of (keyframe, keypoint) in keyframe order, numbered by
/// their smallest global keypoint index; tracks with < 2 observations or two in one
/// keyframe are dropped.
fn tracks(
    keyframes: &[Keyframe],
    pairs: &[(usize, usize)],
    matches: &[Vec<(usize, usize)>],
) -> Vec<Vec<(usize, usize)>> {
    let mut offsets = vec![0usize];
    for k in keyframes {
        offsets.push(offsets[offsets.len() - 1] + k.keypoints.len());
    }
    let mut uf = UnionFind::new(offsets[keyframes.len()]);
    for (&(a, b), m) in pairs.iter().zip(matches) {
        for &(i, j) in m {
            uf.union(offsets[a] + i, offsets[b] + j);
        }
    }
    let roots: Vec<usize> = (0..offsets[keyframes.len()]).map(|g| uf.find(g)).collect();
    let mut size = vec![0usize; roots.len()];
    for &r in &roots {
        size[r] += 1;
    }
    // g increases with (keyframe, keypoint) and a root is its set's smallest g, so tracks
    // come out numbered by root and their members in keyframe order.
    let mut by_root: Vec<Vec<(usize, usize)>> = Vec::new();
    let mut slot = vec![usize::MAX; roots.len()];
    for k in 0..keyframes.len() {
        for i in 0..keyframes[k].keypoints.len() {
            let r = roots[offsets[k] + i];
            if size[r] < 2 {
                continue;
            }
            if slot[r] == usize::MAX {
                slot[r] = by_root.len();
                by_root.push(Vec::new());
            }
            by_root[slot[r]].push((k, i));
        }
    }
    by_root.retain(|t| t.len() >= 2 && t.windows(2).all(|w| w[0].0 != w[1].0));
    by_root
}

/// Step 5: the medoid descriptor of each point's observations.
fn representative_descriptors(keyframes: &[Keyframe], members: &[Vec<(usize, usize)>]) -> DescriptorSet {
    let chosen: Vec<(usize, usize)> = map_slice(members, 256, |obs| {
        let row = |&(k, i): &(usize, usize)| keyframes[k].descriptors.view().row(i);
        let cost = |a: &(usize, usize)| obs.iter().map(|b| f64::from(row(a).distance(&row(b)))).sum::<f64>();
        let mut best = (f64::INFINITY, obs[0]);
        for a in obs {
            let c = cost(a);
            if c < best.0 {
                best = (c, *a);
            }
        }
        best.1
    });
    let parts: Vec<DescriptorSet> = chosen.iter().map(|&(k, i)| keyframes[k].descriptors.select(&[i])).collect();
    if parts.is_empty() {
        // no point: an empty set of the keyframes' kind and width
        return keyframes
            .first()
            .map_or(DescriptorSet::Float { data: Vec::new(), width: 0 }, |k| k.descriptors.select(&[]));
    }
    DescriptorSet::stack(parts.iter())
}

/// Projects `x` into a camera at `pose`: the pixel when the point is in front (z > 0.1 m).
pub(crate) fn project_in_front(camera: &Camera, pose_inverse: &SE3, x: &Vector3<f64>) -> Option<Vector2<f64>> {
    let p = pose_inverse.rotation.matrix() * x + pose_inverse.translation;
    (p.z > 0.1).then(|| camera.project_cam(&p))
}

/// A synthetic scene for the tests: [`crate::testing::LandmarkScene`] seen by keyframes along
/// [`crate::testing::walk`], with the landmark behind every keypoint.
#[cfg(test)]
pub(crate) mod fixture {
    use super::*;
    use crate::map::{Map, RetrievalKind};
    use crate::testing::{LANDMARK_DESCRIPTOR_BYTES, LandmarkScene, SplitMix64, walk};

    /// The landmarks [`LandmarkScene::observe`] reports at `pose`, in its order.
    pub fn visible(world: &LandmarkScene, pose: &SE3) -> Vec<usize> {
        (0..world.landmarks.len())
            .filter(|&i| {
                let p = crate::camera::project(&world.camera, pose, &world.landmarks[i]);
                p.p_cam.z > 0.5 && (0.0..640.0).contains(&p.uv.x) && (0.0..480.0).contains(&p.uv.y)
            })
            .collect()
    }

    /// The scene, a BoW map of `n` keyframes 6 cm apart (and, with `second_pass`, `n` more
    /// along a path 0.5 m beside the first), and each keyframe's landmark ids.
    pub fn scene(n: usize, second_pass: bool) -> (LandmarkScene, Map, Vec<Vec<usize>>) {
        let mut rng = SplitMix64::new(7);
        let world = LandmarkScene::new(&mut rng, 1500, 8.0);
        let mut ids = Vec::new();
        let passes = if second_pass { 2 } else { 1 };
        let keyframes = (0..passes * n)
            .map(|j| {
                let (i, offset) = (j % n, 0.5 * (j / n) as f64);
                let pose = walk(i as f64 * 0.1, offset, -1.5);
                let (keypoints, data) = world.observe(&mut rng, &pose, 3);
                ids.push(visible(&world, &pose));
                Keyframe {
                    world_from_cam: pose,
                    keypoints,
                    descriptors: DescriptorSet::Binary { data, width: LANDMARK_DESCRIPTOR_BYTES },
                    global: None,
                }
            })
            .collect();
        let kind = RetrievalKind::Bow { branching: 8, depth: 3 };
        let map = Map::build(world.camera, keyframes, None, kind, 1).expect("valid map");
        (world, map, ids)
    }
}

#[cfg(test)]
mod tests {
    use std::num::NonZero;

    use super::*;
    use crate::parallel::{Parallelism, with_parallelism};

    /// Every point is one landmark (all its observations see the same one) and lies within
    /// 5 cm of it (0.5 px noise, depth 3–6 m, baselines ≥ 3 cm); most landmarks seen by two
    /// keyframes become points.
    #[test]
    fn points_are_the_true_landmarks() {
        let (world, map, ids) = fixture::scene(30, false);
        let model = SceneModel::build(&map.camera, &map.keyframes, None, &ModelOptions::default()).expect("builds");
        assert!(model.len() > 300, "{} points", model.len());
        let mut landmark_of = vec![None; model.len()];
        for (k, row) in model.point_ids.iter().enumerate() {
            for (i, id) in row.iter().enumerate() {
                if let Some(p) = id {
                    let l = ids[k][i];
                    assert_eq!(*landmark_of[*p].get_or_insert(l), l, "point {p} mixes landmarks");
                }
            }
        }
        let truth: Vec<Vector3<f64>> = landmark_of.iter().map(|l| world.landmarks[l.expect("observed")]).collect();
        let mut errors: Vec<f64> = truth.iter().zip(&model.points).map(|(t, x)| (t - x).norm()).collect();
        errors.sort_by(f64::total_cmp);
        assert!(errors[errors.len() / 2] < 0.01, "median {}", errors[errors.len() / 2]);
        // Σ_X covers the error: (X − X_true)ᵀ Σ_X⁻¹ (X − X_true) below the χ²₃ 99.9 % quantile
        // for ≥ 98 % of points (σ = 1 px assumed, 0.5 px simulated).
        let covered = (0..model.len())
            .filter(|&p| {
                let e = model.points[p] - truth[p];
                model.covariances[p]
                    .try_inverse()
                    .is_some_and(|i| (e.transpose() * i * e)[0] < crate::stats::chi2::CHI2_3_999)
            })
            .count();
        assert!(covered as f64 >= 0.98 * model.len() as f64, "{covered} of {}", model.len());
        for p in 0..model.len() {
            assert!(model.observers(p).len() >= 2);
            assert!(model.covariances[p].trace() > 0.0);
        }
        let seen_twice = (0..world.landmarks.len()).filter(|l| ids.iter().filter(|v| v.contains(l)).count() >= 2);
        assert!(model.len() as f64 > 0.8 * seen_twice.count() as f64);
    }

    /// Inconsistent tracks (two keypoints of one keyframe) and single observations are dropped;
    /// members come in keyframe order; tracks are numbered by their smallest keypoint.
    #[test]
    fn tracks_by_union_find() {
        let kf = |n: usize| Keyframe {
            world_from_cam: SE3::identity(),
            keypoints: vec![Vector2::zeros(); n],
            descriptors: DescriptorSet::Binary { data: vec![0; n], width: 1 },
            global: None,
        };
        let keyframes = vec![kf(3), kf(3), kf(3)];
        let pairs = [(0, 1), (0, 2), (1, 2)];
        // (keyframe:keypoint) 0:0–1:1–2:2 one track; 0:1–1:0 another; 0:2–2:0, 1:2–2:0 and
        // 1:2–2:1 put 2:0 and 2:1 in one set: dropped whole.
        let matches = vec![vec![(0, 1), (1, 0)], vec![(2, 0)], vec![(1, 2), (2, 0), (2, 1)]];
        let got = tracks(&keyframes, &pairs, &matches);
        assert_eq!(got, vec![vec![(0, 0), (1, 1), (2, 2)], vec![(0, 1), (1, 0)]]);
    }

    /// Two passes 0.4 m apart along a line, keyframes 2.5 cm apart: the nearest baselines
    /// (0.2 m preferred) all lie on a keyframe's own pass, so without revisits the passes share
    /// no pair; with them every keyframe of the first pass pairs with the second, each revisit
    /// pair is within the pair limits and `revisit_gap` apart in capture order, and the
    /// nearest-baseline pairs stay as they were. Checked against a brute-force selection.
    #[test]
    fn revisit_pairs_join_the_passes_of_a_trajectory() {
        let n = 40;
        let poses: Vec<SE3> = (0..2 * n)
            .map(|k| {
                let (i, pass) = (k % n, k / n);
                SE3::new(crate::lie::SO3::identity(), Vector3::new(0.025 * i as f64, 0.4 * pass as f64, 0.0))
            })
            .collect();
        let crossing = |pairs: &[(usize, usize)]| pairs.iter().filter(|&&(a, b)| (a < n) != (b < n)).count();
        let plain = ModelOptions::default();
        let without = neighbour_pairs(&poses, &plain);
        assert_eq!(crossing(&without), 0);
        let options = ModelOptions { revisit_neighbours: 3, revisit_gap: 20, ..plain };
        let with = neighbour_pairs(&poses, &options);
        assert!(without.iter().all(|p| with.contains(p)), "the nearest pairs are kept");
        for a in 0..n {
            assert!(
                with.iter().filter(|&&(x, y)| (x == a && y >= n) || (y == a && x >= n)).count() >= 3,
                "keyframe {a}"
            );
        }
        // brute force: per keyframe, candidates by |d − baseline|, the first `neighbours`, then
        // the next three at least 20 apart
        let mut expected = Vec::new();
        for a in 0..poses.len() {
            let mut c: Vec<(f64, usize)> = (0..poses.len())
                .filter(|&b| b != a)
                .map(|b| ((poses[a].translation - poses[b].translation).norm(), b))
                .filter(|&(d, _)| d > plain.min_distance_m && d < plain.max_distance_m)
                .map(|(d, b)| ((d - plain.baseline_m).abs(), b))
                .collect();
            c.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
            let far = c[plain.neighbours..].iter().filter(|&&(_, b)| a.abs_diff(b) >= 20).take(3);
            expected.extend(c[..plain.neighbours].iter().chain(far).map(|&(_, b)| (a.min(b), a.max(b))));
        }
        expected.sort_unstable();
        expected.dedup();
        assert_eq!(with, expected);
        assert!(with.iter().all(|&(a, b)| (a < n) == (b < n) || a.abs_diff(b) >= 20));
    }

    #[test]
    fn same_model_with_any_thread_count() {
        let (_, map, _) = fixture::scene(20, false);
        let build = || SceneModel::build(&map.camera, &map.keyframes, None, &ModelOptions::default()).expect("builds");
        let one = with_parallelism(&Parallelism::Threads(NonZero::new(1).expect("1")), build);
        let two = with_parallelism(&Parallelism::Threads(NonZero::new(2).expect("2")), build);
        assert_eq!(one, two);
        let bits = |m: &SceneModel| m.points.iter().flat_map(|p| p.iter().map(|v| v.to_bits())).collect::<Vec<_>>();
        assert_eq!(bits(&one), bits(&two));
    }

    #[test]
    fn bad_options_and_parts_are_refused_by_name() {
        let bad = ModelOptions { neighbours: 0, ..ModelOptions::default() };
        assert!(bad.check().expect_err("0").to_string().contains("neighbours"));
        let bad = ModelOptions { min_track_length: 1, ..ModelOptions::default() };
        assert!(bad.check().expect_err("1").to_string().contains("min_track_length"));
        let d = DescriptorSet::Binary { data: vec![0; 2], width: 1 };
        let err = SceneModel::from_parts(vec![Vector3::zeros(); 2], vec![Matrix3::zeros(); 2], d, vec![vec![Some(0)]])
            .expect_err("point 1 unobserved");
        assert!(err.to_string().contains("point 1 has no observation"), "{err}");
    }
}
