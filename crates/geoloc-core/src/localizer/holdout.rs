//! Held-out re-localization: a keyframe's own features localized against the map without
//! a range of keyframes, by the geometric locator alone (no motion model, no fusion) — what
//! the map's noise estimate ([`crate::map::Map::with_estimated_noise`]) measures C_map with.
//! Retrieval is by the bag of words (a fused map's too): C_map measures the map, and the
//! localizer's own answers are those of BoW's keyframes wherever those are accepted.

use std::sync::Arc;

use super::{Estimate, Frame, Localizer, Locator, Timings};
use crate::error::Result;
use crate::keyframes::select_keyframes;
use crate::lie::SE3;
use crate::map::Ranking;

impl Localizer {
    /// The geometric pose of keyframe `k`'s own features against the map without the
    /// keyframes in `excluded` (retrieval and the keyframe group skip them), with its PnP
    /// inliers; None when the locator fails. The model locator uses no point that an excluded keyframe observes.
    pub(crate) fn localize_held_out(
        &mut self,
        k: usize,
        excluded: std::ops::Range<usize>,
    ) -> Result<Option<(Estimate, usize)>> {
        let map = Arc::clone(&self.map);
        let kf = &map.keyframes[k];
        let descriptors = kf.descriptors.view();
        let frame = Frame {
            timestamp: 0.0,
            keypoints: &kf.keypoints,
            descriptors,
            global: kf.global.as_deref(),
            pixel_sigmas: None,
        };
        let k = self.retrieved_keyframes();
        let top = map.retrieve_ranked(&frame.retrieval_query(), k, excluded.clone(), Ranking::Words)?;
        if self.options.locator == Locator::Model {
            let ((_, pose, inliers), _) = self.ranked_model_pose(&frame, &top, excluded, &mut Timings::default())?;
            return Ok(pose.ok().map(|p| (p, inliers)));
        }
        let seed = top[0];
        let allowed: Vec<usize> = (0..map.keyframes.len()).filter(|i| !excluded.contains(i)).collect();
        let poses: Vec<SE3> = allowed.iter().map(|&i| map.keyframes[i].world_from_cam).collect();
        let local = allowed.iter().position(|&i| i == seed).expect("invariant: retrieval skips the excluded");
        let group: Vec<usize> =
            select_keyframes(&poses, local, &self.options.keyframes)?.into_iter().map(|j| allowed[j]).collect();
        let points = self.map_points(seed, &group)?;
        let (pose, inliers) = self.geometric_pose(&frame, seed, &points, group.len(), &mut Timings::default())?;
        Ok(pose.ok().map(|p| (p, inliers)))
    }
}
