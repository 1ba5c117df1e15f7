//! Retrieval that combines a global-descriptor network with bag of words
//! ([`super::Retrieval::Fused`]) so that the network can add candidates but never displace
//! BoW's unless the images clearly say so.
//!
//! For a query and `k`:
//! 1. **Candidates**: BoW's top `k` keyframes, and the network's first min(`k`,
//!    [`MAX_NETWORK_CANDIDATES`]) that BoW did not propose ([`network_candidates`]).
//! 2. **Verification** of BoW's first keyframe and of each network candidate: the query's
//!    local descriptors are matched against the keyframe's (mutual nearest neighbours with the
//!    ratio test, [`MatchOptions::default`]) and the matches verified from the images alone by
//!    essential-matrix RANSAC ([`crate::essential::verify_two_view`] with its defaults:
//!    Sampson distance ≤ 2 px, at least 15 inliers); the score is the inlier count, 0 when
//!    they do not verify ([`verified_inliers`]).
//! 3. **Order** ([`fused_order`]): first the network candidates that clearly beat BoW's
//!    first keyframe — s > [`CLEAR_MARGIN`] × s_BoW, any verified one when BoW's does not
//!    verify — by score (ties by the network's rank); then BoW's top `k` in BoW's order; then
//!    the other network candidates in the network's order. The first `k` are the answer.
//!
//! Why this rule (measured with `benchmarks/retrieval_networks.py --folds` on the shared
//! 7-Scenes frames, every 100-frame block the queries, networks trained on the rest): a
//! network trained from scratch retrieves well in some places and not at all in others
//! (recall@1 0 % on one block, 65 % on another), so a fixed blend of the two rankings that
//! helps one block costs another up to 30 points, and a weight chosen on held-out training
//! frames did not carry over to a different place. Ordering every candidate by its inliers
//! changes BoW's answer wherever a neighbouring keyframe matches a few more points: it lost
//! up to 5 points of recall@1 on a block with k = 1 and 11 with k = 5, and a margin of 1.25
//! still lost 3. With twice the inliers the fused answer was never below BoW's on a block.
//! The pose labels are not used: they may be what is wrong.

use nalgebra::Vector2;

use crate::camera::Camera;
use crate::error::Result;
use crate::essential::{TwoViewOptions, verify_two_view};
use crate::matching::{Descriptors, MatchOptions, match_descriptors};

/// A network candidate displaces BoW's first keyframe when it verifies with more than this
/// many times its inliers.
pub const CLEAR_MARGIN: f64 = 2.0;

/// Most network candidates verified per query: each verification matches and runs RANSAC
/// (about 7 ms on 7-Scenes' 1000 ORB features), and a network whose first two answers are not
/// clearly better than BoW's is not trusted further down its ranking.
pub const MAX_NETWORK_CANDIDATES: usize = 2;

/// The network candidates: the first min(`k`, [`MAX_NETWORK_CANDIDATES`]) of the network's
/// `network` ranking that are not among BoW's first `k` of `bow` (each ranking best first,
/// already without excluded keyframes).
pub fn network_candidates(bow: &[usize], network: &[usize], k: usize) -> Vec<usize> {
    let from_bow = &bow[..bow.len().min(k)];
    network.iter().copied().filter(|i| !from_bow.contains(i)).take(k.min(MAX_NETWORK_CANDIDATES)).collect()
}

/// The fused ranking (step 3 of the module doc), its first `k`: `bow` BoW's ranking,
/// `network` the network candidates with their scores `network_scores`, `bow_score` the score
/// of BoW's first keyframe.
pub fn fused_order(
    bow: &[usize],
    bow_score: usize,
    network: &[usize],
    network_scores: &[usize],
    k: usize,
) -> Vec<usize> {
    let clearly = |s: usize| s > 0 && s as f64 > CLEAR_MARGIN * bow_score as f64;
    let mut promoted: Vec<usize> = (0..network.len()).filter(|&i| clearly(network_scores[i])).collect();
    promoted.sort_by_key(|&i| std::cmp::Reverse(network_scores[i])); // stable: ties by rank
    let first = promoted.iter().map(|&i| network[i]);
    let rest = (0..network.len()).filter(|&i| !clearly(network_scores[i])).map(|i| network[i]);
    first.chain(bow.iter().copied().take(k)).chain(rest).take(k).collect()
}

/// The verification score of one candidate keyframe (step 2 of the module doc): the
/// two-view inliers of the query's matches to it, 0 when they do not verify.
///
/// # Errors
/// Descriptors the two sides cannot compare (`descriptors`), non-finite keypoints.
pub fn verified_inliers(
    camera: &Camera,
    query_keypoints: &[Vector2<f64>],
    query_descriptors: &Descriptors<'_>,
    keyframe_keypoints: &[Vector2<f64>],
    keyframe_descriptors: &Descriptors<'_>,
) -> Result<usize> {
    let matches = match_descriptors(query_descriptors, keyframe_descriptors, &MatchOptions::default())?;
    let two_view = verify_two_view(camera, query_keypoints, keyframe_keypoints, &matches, &TwoViewOptions::default())?;
    Ok(if two_view.verified { two_view.inliers } else { 0 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    use crate::lie::SE3;
    use crate::localizer::{Frame, Localization, Localizer, LocalizerOptions, Locator, Source};
    use crate::map::{Keyframe, Map, RetrievalKind, RetrievalQuery};
    use crate::matching::DescriptorSet;
    use crate::testing::{LANDMARK_DESCRIPTOR_BYTES, LandmarkScene, SplitMix64, walk};

    /// Keyframes every 0.3 m along a walk through a wide landmark field, each with a
    /// "network" descriptor (its position along the walk), a query between two of them, and
    /// each keyframe's distance to the query (the reference: a right answer is within
    /// [`NEAR_M`], one and a half keyframe spacings).
    struct Scene {
        keyframes: Vec<Keyframe>,
        query: (Vec<nalgebra::Vector2<f64>>, Vec<u8>),
        distance_m: Vec<f64>,
        nearest: usize,
        camera: Camera,
        truth: SE3,
    }

    const NEAR_M: f64 = 0.45;

    fn scene() -> Scene {
        let mut rng = SplitMix64::new(5);
        let world = LandmarkScene::new(&mut rng, 1500, 8.0);
        let keyframes: Vec<Keyframe> = (0..21)
            .map(|i| {
                let pose = walk(i as f64 * 0.5, 0.0, -6.0);
                let (keypoints, data) = world.observe(&mut rng, &pose, 3);
                let global = Some(vec![pose.translation.x as f32 / 10.0, 0.0]);
                Keyframe {
                    world_from_cam: pose,
                    keypoints,
                    descriptors: DescriptorSet::Binary { data, width: LANDMARK_DESCRIPTOR_BYTES },
                    global,
                }
            })
            .collect();
        let truth = walk(7.4, 0.15, -6.0);
        let query = world.observe(&mut rng, &truth, 3);
        let distance_m: Vec<f64> =
            keyframes.iter().map(|k| (k.world_from_cam.translation - truth.translation).norm()).collect();
        let nearest = (0..keyframes.len()).min_by(|&a, &b| distance_m[a].total_cmp(&distance_m[b])).expect("keyframes");
        Scene { keyframes, query, distance_m, nearest, camera: world.camera, truth }
    }

    fn top1(keyframes: Vec<Keyframe>, kind: RetrievalKind, query: &Scene, global: f32) -> usize {
        let map = Map::build(query.camera, keyframes, None, kind, 0).expect("valid map");
        let g = [global, 0.0];
        let descriptors =
            crate::matching::Descriptors::Binary { data: &query.query.1, width: LANDMARK_DESCRIPTOR_BYTES };
        let q = RetrievalQuery { keypoints: &query.query.0, descriptors, global: Some(&g) };
        map.retrieve_top(&q, 1, 0..0).expect("retrieves")[0]
    }

    /// The scene's keyframes behind a decoy (keyframe 0): the query's own descriptors — BoW's
    /// best possible score — on scrambled keypoints that fit no geometry, with a network
    /// descriptor far from every other; and the network's answer for the query, which points
    /// at the keyframe nearest to it.
    fn with_decoy(s: &Scene) -> (Vec<Keyframe>, f32) {
        let mut rng = SplitMix64::new(9);
        let keypoints = s
            .query
            .0
            .iter()
            .map(|_| nalgebra::Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0)))
            .collect();
        let descriptors = DescriptorSet::Binary { data: s.query.1.clone(), width: LANDMARK_DESCRIPTOR_BYTES };
        let decoy =
            Keyframe { world_from_cam: SE3::identity(), keypoints, descriptors, global: Some(vec![100.0, 0.0]) };
        let keyframes = std::iter::once(decoy).chain(s.keyframes.iter().cloned()).collect();
        (keyframes, s.keyframes[s.nearest].global.as_ref().expect("global")[0])
    }

    const BOW: RetrievalKind = RetrievalKind::Bow { branching: 8, depth: 4 };
    const FUSED: RetrievalKind = RetrievalKind::Fused { branching: 8, depth: 4 };

    #[test]
    fn a_misleading_network_cannot_displace_what_bow_finds() {
        let s = scene();
        let far = s.keyframes[0].global.as_ref().expect("global")[0];
        // the network alone answers the far keyframe it was told
        assert_eq!(top1(s.keyframes.clone(), RetrievalKind::Global, &s, far), 0);
        assert!(s.distance_m[0] > 3.0);
        let bow = top1(s.keyframes.clone(), BOW, &s, far);
        assert!(s.distance_m[bow] < NEAR_M, "{}", s.distance_m[bow]);
        assert_eq!(top1(s.keyframes.clone(), FUSED, &s, far), bow);
    }

    #[test]
    fn a_keyframe_only_the_network_proposes_wins_when_the_images_verify_it() {
        let s = scene();
        let (keyframes, honest) = with_decoy(&s);
        assert_eq!(top1(keyframes.clone(), BOW, &s, honest), 0, "BoW alone takes the decoy");
        let fused = top1(keyframes, FUSED, &s, honest);
        assert!(fused > 0 && s.distance_m[fused - 1] < NEAR_M, "{fused}");
    }

    /// The scene's query localized by a fresh localizer (one frame, as a robot that just
    /// started) on a map of `keyframes` retrieving by `kind`, with the network's answer `global`.
    fn localize(
        keyframes: Vec<Keyframe>,
        kind: RetrievalKind,
        s: &Scene,
        global: f32,
        locator: Locator,
    ) -> Localization {
        let map = Arc::new(Map::build(s.camera, keyframes, None, kind, 0).expect("valid map"));
        let options = LocalizerOptions { locator, ..LocalizerOptions::default() };
        let mut localizer = Localizer::new(map, options).expect("localizer");
        let g = [global, 0.0];
        let descriptors = crate::matching::Descriptors::Binary { data: &s.query.1, width: LANDMARK_DESCRIPTOR_BYTES };
        let frame = Frame { timestamp: 0.0, keypoints: &s.query.0, descriptors, global: Some(&g), pixel_sigmas: None };
        localizer.localize(&frame).expect("a valid frame")
    }

    /// A localization's pose and covariance as bits, source, reason, keyframe and inliers.
    type Answer = (Option<(Vec<u64>, Vec<u64>)>, Source, String, usize, usize);

    /// What a localization says, bit for bit.
    fn answer(l: &Localization) -> Answer {
        let estimate = l.estimate.as_ref().map(|e| {
            let pose = e.world_from_cam.matrix();
            (pose.iter().map(|v| v.to_bits()).collect(), e.covariance.iter().map(|v| v.to_bits()).collect())
        });
        (estimate, l.source, l.reason.clone(), l.keyframe, l.inliers)
    }

    /// A frame the bag of words localizes gets the BoW map's answer from a fused map, bit for
    /// bit, whatever the network says — here a network pointing at a keyframe 6 m away — with
    /// either locator.
    #[test]
    fn a_fused_map_localizes_what_bow_localizes_as_the_bow_map_does() {
        let s = scene();
        let far = s.keyframes[0].global.as_ref().expect("global")[0];
        for locator in [Locator::Paper, Locator::Model] {
            let bow = localize(s.keyframes.clone(), BOW, &s, far, locator);
            assert!(bow.estimate.is_some(), "{locator:?}: {}", bow.reason);
            let fused = localize(s.keyframes.clone(), FUSED, &s, far, locator);
            assert_eq!(answer(&fused), answer(&bow), "{locator:?}");
        }
    }

    /// A frame whose BoW keyframe gives no accepted pose (a decoy with the query's own
    /// descriptors on scrambled keypoints: BoW's best score, no geometry) is localized from
    /// the keyframe the network proposes and the images verify, and says so; the BoW map
    /// loses it.
    #[test]
    fn the_network_localizes_a_frame_bows_keyframes_cannot() {
        let s = scene();
        let (keyframes, honest) = with_decoy(&s);
        let bow = localize(keyframes.clone(), BOW, &s, honest, Locator::Paper);
        assert!(bow.estimate.is_none(), "the BoW map localized from its decoy: {}", bow.reason);
        let fused = localize(keyframes, FUSED, &s, honest, Locator::Paper);
        let estimate = fused.estimate.as_ref().unwrap_or_else(|| panic!("lost: {}", fused.reason));
        let error = (estimate.world_from_cam.translation - s.truth.translation).norm();
        assert!(error < 0.05, "{error} m off");
        assert!(fused.keyframe > 0 && s.distance_m[fused.keyframe - 1] < NEAR_M);
        assert!(fused.reason.contains("retrieved with the network"), "{}", fused.reason);
    }

    #[test]
    fn network_candidates_are_the_ones_bow_did_not_propose() {
        assert_eq!(network_candidates(&[4, 2, 9, 1], &[2, 7, 4, 8, 3], 3), vec![7, 8]);
        assert_eq!(network_candidates(&[4], &[2, 7, 4, 8, 3], 1), vec![2]);
        // a keyframe BoW ranks beyond k can still come from the network
        assert_eq!(network_candidates(&[4, 2, 9, 1], &[1, 4], 2), vec![1]);
        assert_eq!(network_candidates(&[], &[5, 6], 1), vec![5]);
        assert!(network_candidates(&[5], &[5], 3).is_empty());
    }

    #[test]
    fn only_a_clearly_better_network_candidate_goes_before_bows() {
        let bow = [4, 2, 9];
        // 61 > 2 × 30 is promoted, 60 is not; promoted ones by score; the rest after BoW's
        assert_eq!(fused_order(&bow, 30, &[7, 8, 3], &[60, 61, 200], 3), vec![3, 8, 4]);
        assert_eq!(fused_order(&bow, 30, &[7, 8, 3], &[60, 61, 200], 6), vec![3, 8, 4, 2, 9, 7]);
        // nothing clearly better: exactly BoW's ranking, then the network's in its order
        assert_eq!(fused_order(&bow, 30, &[7, 8], &[59, 0], 5), vec![4, 2, 9, 7, 8]);
        // BoW's first does not verify: any verified network candidate goes first, ties by rank
        assert_eq!(fused_order(&bow, 0, &[7, 8, 3], &[0, 16, 16], 2), vec![8, 3]);
        assert_eq!(fused_order(&[], 0, &[7], &[0], 2), vec![7]);
    }
}
