//! The paper locator's keyframe-pair matches, prepared when the map is built.
//!
//! The paper's locator triangulates the group of keyframes around the keyframe a query
//! retrieves (its *seed*) from tracks of the seed's keypoints: the seed's descriptors matched
//! into every other keyframe g of the group ([`select_keyframes`]) and kept where they pass
//! the epipolar check with the known poses ([`pair_matches`]). That matching is most of the
//! cost of a new group (≈ 25 ms of ≈ 30 ms for 7 keyframes of 1000 ORB features on 2 cores)
//! and it fell on whichever frame first retrieved the seed: a p90 of 30–40 ms against a 5 ms
//! median. Here it is done once per (seed, g) for every keyframe as a seed, at build time,
//! and stored in the map; the localizer takes a pair's matches from here when the map has
//! them for the options it runs with, and matches the pair itself otherwise (another
//! group, other options) — the same [`pair_matches`] either way, so the tracks, the points
//! and every pose are identical.

use super::{Keyframe, Map};
use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::keyframes::{KeyframeOptions, select_keyframes};
use crate::lie::SE3;
use crate::matching::{Match, MatchOptions, epipolar_filter, match_descriptors};

/// Seeds below which the preparation stays on the calling thread.
const PARALLEL_MIN_SEEDS: usize = 8;

/// The options a pair's matches depend on, as text (compared, never parsed): a localizer
/// whose options give another text matches its pairs itself.
pub fn fingerprint(matching: &MatchOptions, epipolar_px: f64, keyframes: &KeyframeOptions) -> String {
    format!("{matching:?}; epipolar_px {epipolar_px:?}; {keyframes:?}")
}

/// (seed keypoint, g keypoint) of the seed's descriptors matched into keyframe `g`
/// ([`match_descriptors`]) that pass the epipolar check with the two poses
/// ([`epipolar_filter`], Sampson distance ≤ `epipolar_px`), in the matcher's order.
///
/// # Errors
/// Bad matching options or threshold; descriptors of different kinds.
pub fn pair_matches(
    camera: &Camera,
    seed: &Keyframe,
    g: &Keyframe,
    matching: &MatchOptions,
    epipolar_px: f64,
) -> Result<Vec<(usize, usize)>> {
    let matches = match_descriptors(&seed.descriptors.view(), &g.descriptors.view(), matching)?;
    epipolar_checked(camera, seed, g, &matches, epipolar_px)
}

/// (keypoint in `a`, keypoint in `b`) of the descriptor `matches` between two keyframes that
/// pass the epipolar check with their known poses ([`epipolar_filter`], Sampson distance ≤
/// `epipolar_px`), in the matches' order: the one keyframe-pair check of the paper's locator
/// ([`pair_matches`]) and of the map-level model ([`super::SceneModel`]).
///
/// # Errors
/// A bad threshold; match indices beyond the keypoints.
pub fn epipolar_checked(
    camera: &Camera,
    a: &Keyframe,
    b: &Keyframe,
    matches: &[Match],
    epipolar_px: f64,
) -> Result<Vec<(usize, usize)>> {
    let keep = epipolar_filter(
        camera,
        &a.world_from_cam,
        &b.world_from_cam,
        &a.keypoints,
        &b.keypoints,
        matches,
        epipolar_px,
    )?;
    Ok(matches.iter().zip(keep).filter(|(_, k)| *k).map(|(m, _)| (m.a, m.b)).collect())
}

/// Every keyframe's group and the matches of the seed into each other member.
#[derive(Clone, Debug, PartialEq)]
pub struct GroupMatches {
    /// [`fingerprint`] of the options they were made with.
    pub options: String,
    /// Per seed: the group, in [`select_keyframes`] order (the seed included).
    pub groups: Vec<Vec<usize>>,
    /// Per seed: (g, seed keypoint, g keypoint), by member in group order, then in the
    /// matcher's order.
    pub rows: Vec<Vec<[usize; 3]>>,
}

impl GroupMatches {
    /// The matches for every keyframe of `map` as a seed, with these options (in parallel
    /// over seeds; the result does not depend on the number of threads).
    ///
    /// # Errors
    /// Bad options; errors of [`pair_matches`].
    pub fn compute(
        map: &Map,
        matching: &MatchOptions,
        epipolar_px: f64,
        keyframe_options: &KeyframeOptions,
    ) -> Result<Self> {
        let poses: Vec<SE3> = map.poses();
        let seeds: Vec<usize> = (0..map.keyframes.len()).collect();
        let per_seed = crate::parallel::map_slice(&seeds, PARALLEL_MIN_SEEDS, |&s| -> Result<_> {
            let group = select_keyframes(&poses, s, keyframe_options)?;
            let mut rows = Vec::new();
            for &g in group.iter().filter(|&&g| g != s) {
                let pairs = pair_matches(&map.camera, &map.keyframes[s], &map.keyframes[g], matching, epipolar_px)?;
                rows.extend(pairs.into_iter().map(|(a, b)| [g, a, b]));
            }
            Ok((group, rows))
        });
        let (mut groups, mut rows) = (Vec::with_capacity(seeds.len()), Vec::with_capacity(seeds.len()));
        for result in per_seed {
            let (group, seed_rows) = result?;
            groups.push(group);
            rows.push(seed_rows);
        }
        Ok(Self { options: fingerprint(matching, epipolar_px, keyframe_options), groups, rows })
    }

    /// The stored matches of `seed` into `g`, when `g` is in the seed's stored group (None:
    /// not prepared, match the pair).
    pub fn pair(&self, seed: usize, g: usize) -> Option<Vec<(usize, usize)>> {
        if !self.groups.get(seed)?.contains(&g) {
            return None;
        }
        Some(self.rows[seed].iter().filter(|r| r[0] == g).map(|r| (r[1], r[2])).collect())
    }

    /// Checks the record against the map's keyframes (loading a file).
    ///
    /// # Errors
    /// `InvalidInput` naming the seed when a group or row is out of range, a row's keyframe
    /// is not in the seed's group or a keypoint index is beyond the keyframe's keypoints.
    pub fn check(&self, keyframes: &[Keyframe]) -> Result<()> {
        let k = keyframes.len();
        if self.groups.len() != k || self.rows.len() != k {
            return Err(GeolocError::invalid(
                "group_matches",
                format!("{} groups and {} row lists for {k} keyframes", self.groups.len(), self.rows.len()),
            ));
        }
        for (s, (group, rows)) in self.groups.iter().zip(&self.rows).enumerate() {
            if !group.contains(&s) || group.iter().any(|&g| g >= k) {
                return Err(GeolocError::invalid(
                    "group_matches",
                    format!("seed {s}: group {group:?} does not hold the seed or names a keyframe ≥ {k}"),
                ));
            }
            let count = |i: usize| keyframes[i].keypoints.len();
            if let Some(r) =
                rows.iter().find(|r| !group.contains(&r[0]) || r[0] == s || r[1] >= count(s) || r[2] >= count(r[0]))
            {
                return Err(GeolocError::invalid("group_matches", format!("seed {s}: row {r:?} is out of range")));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::localizer::{Frame, Localizer, LocalizerOptions, Locator};
    use crate::map::BuildSteps;
    use crate::map::model::fixture;
    use crate::testing::{SplitMix64, walk};

    fn prepared(map: Map) -> Map {
        map.with_build_steps(&BuildSteps { group_matches: true, ..BuildSteps::default() }).expect("prepared")
    }

    /// Every stored pair equals the pair matched on the spot, and every group the selection.
    #[test]
    fn stored_pairs_are_the_pairs_matched_on_the_spot() {
        let (_, map, _) = fixture::scene(30, false);
        let map = prepared(map);
        let stored = map.group_matches.as_ref().expect("stored");
        let o = LocalizerOptions::default();
        assert_eq!(stored.options, fingerprint(&o.matching, o.epipolar_px, &o.keyframes));
        let poses = map.poses();
        let mut pairs = 0;
        for s in 0..map.keyframes.len() {
            let group = select_keyframes(&poses, s, &o.keyframes).expect("group");
            assert_eq!(stored.groups[s], group);
            for &g in group.iter().filter(|&&g| g != s) {
                let fresh = pair_matches(&map.camera, &map.keyframes[s], &map.keyframes[g], &o.matching, o.epipolar_px)
                    .expect("pair");
                assert_eq!(stored.pair(s, g), Some(fresh));
                pairs += 1;
            }
        }
        assert!(pairs > 30, "{pairs} pairs");
        let outside = (0..map.keyframes.len()).find(|g| !stored.groups[0].contains(g)).expect("a keyframe outside");
        assert_eq!(stored.pair(0, outside), None, "a pair outside the group is matched by the localizer");
        stored.check(&map.keyframes).expect("consistent");
    }

    /// The paper locator gives bit-identical results with and without the prepared pairs.
    #[test]
    fn localizing_with_prepared_pairs_changes_nothing() {
        let (world, map, _) = fixture::scene(30, false);
        let with = Arc::new(prepared(fixture::scene(30, false).1));
        let without = Arc::new(map);
        let options = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
        let mut a = Localizer::new(with, options).expect("localizer");
        let mut b = Localizer::new(without, options).expect("localizer");
        let mut rng = SplitMix64::new(5);
        let mut located = 0;
        for i in 0..10 {
            let truth = walk(0.3 + i as f64 * 0.27, 0.1, -1.5);
            let (keypoints, data) = world.observe(&mut rng, &truth, 5);
            let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
            let frame =
                Frame { timestamp: i as f64, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
            let (ra, rb) = (a.localize(&frame).expect("valid"), b.localize(&frame).expect("valid"));
            assert_eq!((ra.source, &ra.reason, ra.inliers), (rb.source, &rb.reason, rb.inliers), "frame {i}");
            assert_eq!(
                ra.estimate.map(|e| (e.world_from_cam.matrix(), e.covariance)),
                rb.estimate.map(|e| (e.world_from_cam.matrix(), e.covariance))
            );
            located += usize::from(ra.estimate.is_some());
        }
        assert!(located >= 8, "{located} of 10 located");
    }

    /// Saved and loaded, the record is the same; damaged, it is refused with the field named.
    #[test]
    fn the_record_survives_the_file_and_damage_is_refused() {
        let (_, map, _) = fixture::scene(20, false);
        let map = prepared(map);
        let file = map.to_map_file("{}").expect("file");
        let (loaded, _) = Map::from_map_file(&file).expect("loads");
        assert_eq!(loaded.group_matches, map.group_matches);
        let (mut damaged, _) = Map::from_map_file(&file).expect("loads");
        let m = damaged.group_matches.as_mut().expect("stored");
        let s = (0..m.rows.len()).find(|&s| !m.rows[s].is_empty()).expect("a seed with rows");
        m.rows[s][0][1] = 1_000_000; // a seed keypoint beyond the keyframe's
        let err = Map::from_map_file(&damaged.to_map_file("{}").expect("file")).expect_err("out of range");
        assert!(err.to_string().contains("group_matches") && err.to_string().contains(&format!("seed {s}")), "{err}");
        let (mut foreign, _) = Map::from_map_file(&file).expect("loads");
        let m = foreign.group_matches.as_mut().expect("stored");
        let outside = (0..m.groups.len()).find(|g| !m.groups[s].contains(g)).expect("outside");
        m.rows[s][0][0] = outside; // a row for a keyframe not in the seed's group
        assert!(Map::from_map_file(&foreign.to_map_file("{}").expect("file")).is_err());
    }
}
