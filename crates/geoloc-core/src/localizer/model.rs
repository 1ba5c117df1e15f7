//! The model locator (`Locator::Model`): the query against the map-level 3D model.
//!
//! 1. **Top-k retrieval**: the `top_k` keyframes most similar to the query ([`Map::retrieve_top`],
//!    the ranking the paper's locator takes the first of; the next `top_k` serve step 11).
//! 2. **2D–3D matching**: the query's descriptors matched (ratio test, not mutual) against the
//!    descriptors of each retrieved keyframe's keypoints that observe a model point; each match
//!    names (query keypoint q, point p, distance d). Over the union: one point per query
//!    keypoint (smallest d, then lowest p), then one keypoint per point (smallest d, then
//!    lowest q).
//! 3. **PnP** ([`solve_pnp_with_pixel_sigmas`], P3P-RANSAC then robust LM) on the union, each point with its
//!    model covariance Σ_X (independent per point: the shared pose-label part is not split
//!    out as the paper's group triangulation does).
//! 4. **Guided matching**, `guided_rounds` times: the points observed by the keyframes near
//!    the pose (centre within [`GUIDED_KEYFRAME_DISTANCE_M`], rotation within
//!    [`GUIDED_KEYFRAME_ANGLE_DEG`]) are projected into the query with the current pose; each
//!    takes the query keypoint within `guided_radius_px` whose descriptor is closest to the
//!    point's representative descriptor, if that distance is at most τ, the largest
//!    descriptor distance among the first PnP's inlier matches (so the threshold adapts to
//!    the descriptor kind); one point per keypoint (smallest distance); PnP from the current
//!    pose (no RANSAC) on them. A round that succeeds becomes the current pose of the next;
//!    it replaces the reported pose when it has at least as many inliers (the reported
//!    covariance is the one of the final inlier set).
//! 5. **Confirmation by the map** (with `guided_rounds` > 0): the pose is reported only if a
//!    guided round found at least as many inliers as it could find again of the retrieval's
//!    (those whose point is among its candidates and whose representative descriptor is
//!    within τ: a guided round sees the map only through them). At the true
//!    pose the points of the keyframes near it project onto their keypoints and guided
//!    matching finds more than retrieval did; a pose fitted to matches of similar structure
//!    elsewhere finds fewer (7-Scenes 0–599 map, test frames 672–698: 157 retrieval inliers,
//!    73 guided, 1.0 m / 26° off — where correct neighbours go from 94 to 295).
//!
//!    **5b. The pose with the keyframe errors shared** ([`Localizer::shared_refinement`]):
//!    the answer of steps 1–10 is solved once more on the inliers of the hypothesis it came
//!    from ([`Localizer::refined_answer`]; the decisions between hypotheses are made
//!    before, as without it), each point weighted by its own
//!    pixel-noise covariance and the map's keyframe-pose errors shared by the points those
//!    keyframes see, as triangulation made them; the pose is taken when it lies inside the
//!    first solve's 95 % region — the same inliers re-weighted, not a jump: on the 7-Scenes
//!    folds the move's NEES under C_G is below 10.3 for every one of 1 269 solves (median
//!    1.0), while an out-of-map frame of a 30-keyframe map with 21 inliers moved by NEES 15.7,
//!    from 0.42 to 0.78 m off (`benchmarks/honesty.py`); C_G stays the independent points'
//!    one (the shared part is map error: C_map's). Σ_X holds each
//!    point's keyframe-pose errors as if they were its own and weights the far points down
//!    for an error all points share. Seven 7-Scenes folds, single image against the SfM
//!    reference (`benchmarks/calibration.py`): median 100–199 1.98 → 1.49 cm and 0.76 → 0.62°,
//!    400–499 2.10 → 1.88 cm and 0.69 → 0.63°, 300–399 1.40 → 1.39 cm, 500–599 0.97 → 0.95 cm;
//!    0–99 1.72 → 1.80 cm, 600–699 1.04 → 1.12 cm, 200–299 2.11 → 2.15 cm; recall within
//!    5 cm / 5° unchanged but 100–199 92 → 93 %. Refining every hypothesis before the
//!    decisions between them turned two 400–499 frames into refusals and cost a quarter of a
//!    frame's time.
//!
//! 6. **A second hypothesis**: steps 3–5 on the best-ranked keyframe's matches alone (with
//!    more than one retrieved keyframe). Look-alike structure seen by the other retrieved
//!    keyframes can outvote the right matches in the union; the best-ranked keyframe alone
//!    is not outvoted by them. Of the accepted poses the one with more inliers is kept — but
//!    when both are accepted and lie apart, grossly and beyond their covariances, the image
//!    supports two places and the frame is refused ([`choose_hypothesis`]). The two
//!    hypotheses share nothing they write, so they run side by side when the process has
//!    threads ([`crate::parallel`]; the same bits with any thread count).
//!
//! 7. **The other retrieved keyframes**, only when neither hypothesis is accepted (two
//!    accepted places: step 8): steps 3–5 on each other retrieved keyframe's matches alone, best-ranked
//!    first, and the first accepted pose is the answer. At a viewpoint far from every
//!    keyframe the right one may rank fourth and its matches drown in the union (7-Scenes map
//!    of 0–599, frames 686–699, 21–28° from every keyframe: refused with the first two
//!    hypotheses, 1 cm off from a lower-ranked keyframe's). On the seven folds and the
//!    paper's split, single-image recall within 5 cm / 5° against the reference is 2–3 points
//!    higher on three of them and unchanged elsewhere, with no gross answer
//!    (`benchmarks/calibration.py`, `benchmarks/honesty.py`). The step runs on failing frames
//!    only, [`OTHER_KEYFRAMES_AT_A_TIME`] keyframes at a time, side by side, in rank order.
//!    The batch is a constant, not the thread count: every accepted solve of a batch joins
//!    step 12's mean at the answer's place, so a batch as wide as the threads would make
//!    the answer depend on how many there are.
//!
//! 8. **A third opinion on two places**, only when both hypotheses are accepted and lie apart
//!    (step 6): steps 3–5 on each other retrieved keyframe's matches alone; if some of the
//!    accepted poses lie at one of the two places and none at the other, that place is the
//!    answer ([`vote_between`]), its covariance widened by δδᵀ (δ the separation) so that its
//!    region holds the other place too — the vote makes one place likelier, it does not rule
//!    out the other. The widened covariance must pass the acceptance rule's σ caps
//!    ([`super::acceptance::too_uncertain`]): places so far apart that the answer could be a
//!    gross error stay refused. Otherwise, too, the frame stays refused. The two hypotheses
//!    share most matches; another keyframe's matches alone are a view of the place neither
//!    was fitted to (7-Scenes, the seven folds, single image against the SfM reference: of
//!    the 23 frames refused as two places that a vote decides, 7 pass the caps — 6 within
//!    5 cm / 5° of the reference, one 20 cm off inside its covariance; without the caps the
//!    other 16 were answered too, 13 of them within 5 cm, three 10–42 cm off with σ up to
//!    60 cm). The other keyframes' solves run side by side when threads are available.
//!
//! 9. **The keyframes nearest the answer**: an answer of steps 1–8 is solved again (steps
//!    2–8) from the `top_k` keyframes nearest its pose ([`nearest_keyframes`]: 10 cm count as
//!    5°) when they are not the retrieved ones, and the better supported of the two is kept
//!    ([`choose_at_pose`]): the one with more inliers when they are one place; when they are
//!    two, the first unless the second has more inliers, which is then answered with C + δδᵀ
//!    within the σ caps, or refused. The bag of words may rank keyframes a metre and 30° away
//!    above ones 20 cm and 15° away; their points, seen from far, leave the pose free to slide
//!    along the translation–rotation valley, and guided matching (6 px around the projection)
//!    confirms the slide rather than escaping it (7-Scenes 100–199: frames 122–157 retrieved
//!    keyframes of frames 508–551, 1 m / 25–30° away, and were 7–10 cm off; keyframes of 81–84
//!    and 645–652 are 20–28 cm / 13–20° away). Single image against the SfM reference, the
//!    seven folds: recall within 5 cm / 5° 100–199 89 → 91 %, 300–399 84 → 93 %, 400–499
//!    79 → 83 %, 0–99 94 → 93 %, the paper's split 95 → 97 %, no gross answer. It costs a
//!    second solve on every answered frame.
//!
//!    **9b. Confirmation of an answer the best-ranked keyframe refused**: when the
//!    best-ranked keyframe's own matches were refused (step 6) and the answer rests on the
//!    union's or a lower-ranked keyframe's (step 7), it stands only if the keyframes nearest
//!    it confirm it — their solve accepted and one place with it ([`unconfirmed`]); otherwise
//!    the frame is refused, saying which (no second view when the nearest keyframes are the
//!    retrieved ones). The union can be outvoted by look-alike structure, and a lower-ranked
//!    keyframe is a weaker view than the best-ranked: out of a small map's reach their
//!    matches fit a wrong place with consistent inliers that guided matching, seeing the map
//!    only near that place, confirms. Honesty benchmark (`benchmarks/honesty.py`, maps of 100
//!    consecutive frames at 300 and 500, frames from elsewhere in the kitchen): 8 of 60
//!    answers 0.45–1.56 m off with σ of 5–12 cm became 3 of 55, all of them on the first map
//!    (the nearest keyframes confirm the wrong place there too); the 30-keyframe map answers
//!    12 of its 61 out-of-map frames, not 19, all correct either way. The seven folds, single
//!    image against the SfM reference (`benchmarks/calibration.py`): recall within 5 cm / 5°
//!    0–99 96 → 95 %, 100–199 96 → 98 %, the rest unchanged; with the vocabulary of seed 1,
//!    whose rankings refuse more, 0–99 92 → 87 % and 300–399 99 → 97 % (sequential 100–199
//!    97 → 93 %): refusals, none of them wrong. Held-out keyframes take the
//!    step too: 296 of the fold maps' held-out keyframes are placed, not 334, and C_map is
//!    smaller on every fold (σ_x 100–199 8.3 → 4.5 cm, 300–399 6.0 → 4.7 cm, 0–99 4.9 → 4.0 cm)
//!    with coverage against the reference unchanged.
//!
//! 10. **The keyframes nearest each of two places**, only when steps 6–8 leave the frame
//!     refused as two places: each place is solved again (steps 2–8) from the `top_k`
//!     keyframes nearest it ([`confirmed_place`](Localizer::confirmed_place)); a place is
//!     confirmed when that answer is accepted and one place with it. Exactly one confirmed:
//!     the better supported of the place and its confirmation is the answer
//!     ([`choose_at_pose`], one place: more inliers); none or both: still refused, saying
//!     which ([`one_confirmed`]). The retrieved keyframes saw the scene from where both places
//!     fit; the keyframes nearest the right place see the points as the query does, those
//!     nearest the wrong one do not. Single image against the SfM reference, the seven folds
//!     and the paper's split: 19 refused frames answered, 17 within 5 cm / 5°, two 15 and
//!     20 cm off outside their 99.9 % region (the seven folds: 3 of 694 answers outside it,
//!     was 1 of 677); recall 300–399 93 → 99 %, 400–499 83 → 87 %, 500–599 97 → 99 %, 0–99,
//!     100–199, 600–699 and the paper's split +1 to +2 points. It costs two solves, side by
//!     side when threads are available, on such frames only.
//!
//! 11. **The next keyframes of the ranking**, only when steps 1–10 give no accepted pose:
//!     steps 1–10 again from the next `top_k` keyframes of the retrieval's ranking
//!     ([`ranked_model_pose`](Localizer::ranked_model_pose)); their answer is taken only if
//!     it is accepted (the reason says it came from them), otherwise the frame keeps the first
//!     refusal. Where the query sees the scene from far off the mapped path, the bag of words
//!     may rank keyframes that see other parts of the room first, and the right ones sixth to
//!     tenth: no correspondence set of the first five then beats chance. How often depends on
//!     the vocabulary — a nuisance parameter: on the seven 7-Scenes folds (single image,
//!     against the SfM reference, `benchmarks/calibration.py`, each fold's map as built)
//!     it answers three of the five frames the first keyframes refused, all three within
//!     5 cm / 5° (recall 0–99 94 → 96 %, 400–499 87 → 88 %); with another vocabulary, whose
//!     rankings refuse more, it answers more (`--seed 1`: docs/design.md, step 11). The
//!     honesty benchmark (`benchmarks/honesty.py`) answers more frames, none of them grossly
//!     wrong or outside its 99.9 % region. Held-out keyframes take the step too (C_map is
//!     measured with the locator the queries use). It costs steps 1–10 once more, on refused
//!     frames only.
//!
//! 12. **The answer's place from every solve that found it**: the frame's accepted solves
//!     that are not [`apart`] from the answer's own — the union's and the best-ranked
//!     keyframe's, those of steps 7–11 — each refined by step 5b (side by side when threads
//!     are available), and the answer's pose is their information-weighted mean under their
//!     C_G ([`crate::fusion::weighted_mean`], once per pose and per match set:
//!     [`solves_at_place`]). The solves share most of their inliers (80–100 % on the 7-Scenes
//!     folds), but each weighs them from its own start and keyframes, and far from the map
//!     the one with the most inliers is not the best placed of them: on fold 400–499, frames
//!     456–466, a frame's accepted solves lie up to 10 cm apart, and on 8 of the 10 answered
//!     frames the answer (most inliers) was not the solve nearest the SfM reference. The
//!     covariance stays the answer's own (shared inliers: the mean is no better known than
//!     one solve). Single image against the SfM reference, the seven folds
//!     (`benchmarks/calibration.py`, maps rebuilt with it: C_map's held-out keyframes take it
//!     too): median 0–99 1.80 → 1.78 cm, 100–199 1.49 → 1.42 cm, 200–299 2.15 → 2.12 cm,
//!     500–599 0.95 → 0.91 cm, 600–699 1.12 → 1.07 cm, 300–399 1.39 → 1.41 cm, 400–499
//!     1.90 cm either way; recall
//!     within 5 cm / 5° 100–199 93 → 96 %, 400–499 88 → 90 %, the rest unchanged; one answer
//!     outside its 99.9 % region where there were two. With the vocabulary of seed 1: recall
//!     100–199 91 → 93 %, 300–399 98 → 99 %, 400–499 83 → 89 %. It costs a step-5b solve per
//!     other solve at the place (two to three on most frames).
//!
//! Held-out keyframes (`excluded`, for the map's noise estimate): retrieval and guided
//! matching skip the excluded keyframes, and a point observed by any excluded keyframe is
//! not used at all (its position carries the held-out keyframe's own observation). Step 8
//! does not decide a held-out keyframe's two places: the estimate takes E[δδᵀ] = C_G + C_map
//! with C_G the measurement's covariance, and a decided answer's C + δδᵀ is a hedge between
//! places, not that (with it, the folds' held-out keyframes that it decided moved C_map's
//! x-axis σ by −2.0 to +1.6 cm). Step 9 runs for them with the nearest keyframes outside
//! `excluded`, and two places it finds stay refused, for the same reason.

use std::ops::Range;
use std::time::Instant;

use nalgebra::{Matrix3, Vector2, Vector3};

use super::grid::{PointGrid, bounds};
use super::{Estimate, Frame, GeometricPose, Localizer, Timings, ms};
use crate::adjust::correction;
use crate::error::{GeolocError, Result};
use crate::fusion::weighted_mean;
use crate::lie::SE3;
use crate::map::SceneModel;
use crate::map::model::project_in_front;
use crate::map::noise::pose_distance;
use crate::matching::{MatchOptions, match_descriptors};
use crate::parallel::map_slice;
use crate::pnp::{PnpResult, PointUncertainty, PosePartials, SharedPoseUncertainty, solve_pnp_with_pixel_sigmas};
use crate::stats::chi2::{CHI2_6_95, CHI2_6_999};
use crate::triangulate::{point_covariance_terms, view_weight};

/// Guided matching uses the points of keyframes whose centre is this close to the pose (m).
pub const GUIDED_KEYFRAME_DISTANCE_M: f64 = 1.0;
/// ... and whose orientation is within this angle of it (degrees).
pub const GUIDED_KEYFRAME_ANGLE_DEG: f64 = 45.0;

/// Two accepted hypotheses further apart than this translation (m) ...
pub const AMBIGUOUS_SEPARATION_M: f64 = 0.1;
/// ... or this rotation (degrees), and beyond their covariances, make the frame ambiguous
/// ([`choose_hypothesis`]).
pub const AMBIGUOUS_SEPARATION_DEG: f64 = 3.0;

/// Step 7 tries the other retrieved keyframes this many at a time (see the module doc: a
/// constant, so that the answer is the same with any thread count).
pub const OTHER_KEYFRAMES_AT_A_TIME: usize = 2;

/// An accepted hypothesis of one frame with its inlier matches ([`Localizer::refined_answer`]).
pub(super) struct AcceptedSolve {
    estimate: Estimate,
    matches: Vec<Correspondence>,
}

/// The order the solves of one frame are taken in, whatever order they arrived in: most
/// matches first, then the least (query, point) list, then the pose's bits (the same matches
/// solved from two starts can end a few bits apart).
fn solve_order(s: &AcceptedSolve) -> (std::cmp::Reverse<usize>, Vec<(usize, usize)>, Vec<u64>) {
    let pose = &s.estimate.world_from_cam;
    let bits = pose.translation.iter().chain(pose.rotation.matrix().iter()).map(|v| v.to_bits()).collect();
    (std::cmp::Reverse(s.matches.len()), s.matches.iter().map(|c| (c.query, c.point)).collect(), bits)
}

/// Step 12's solves: `answer` first, then every other of `solves` at its place (not
/// [`apart`] from it) in [`solve_order`], once each: a pose found twice, or the same
/// matches solved twice, is one solve (the first).
fn solves_at_place<'a>(solves: &'a [AcceptedSolve], answer: &'a AcceptedSolve) -> Vec<&'a AcceptedSolve> {
    let same_matches = |a: &AcceptedSolve, b: &AcceptedSolve| {
        a.matches.len() == b.matches.len()
            && a.matches.iter().zip(&b.matches).all(|(x, y)| (x.query, x.point) == (y.query, y.point))
    };
    let mut place: Vec<&AcceptedSolve> = solves
        .iter()
        .filter(|s| s.estimate.world_from_cam != answer.estimate.world_from_cam && !same_matches(s, answer))
        .filter(|s| apart(&s.estimate, &answer.estimate).is_none())
        .collect();
    place.sort_by_key(|s| solve_order(s));
    place.dedup_by(|a, b| a.estimate.world_from_cam == b.estimate.world_from_cam || same_matches(a, b));
    place.insert(0, answer);
    place
}

/// A hypothesis of the model locator: T_G and C_G or why it was refused, and its inlier count.
type Hypothesis = (std::result::Result<Estimate, String>, usize);

/// Two accepted poses that are [`apart`], each with its inlier count.
type Places = [(Estimate, usize); 2];

/// Of the union's hypothesis and the best-ranked keyframe's (step 6): the accepted one with
/// more inliers (ties: the union's), or the union's refusal when neither is accepted — unless
/// both are accepted and the image supports two places: with δ = log(T_u⁻¹ T_f)^∨ (right
/// perturbation, translation first), δᵀ (C_u + C_f)⁻¹ δ above the χ²₆ 99.9 % quantile
/// *and* the poses apart by more than [`AMBIGUOUS_SEPARATION_M`] or
/// [`AMBIGUOUS_SEPARATION_DEG`]. Then the frame is refused, naming the separation: whichever
/// were reported, the inlier counts cannot tell it from the other (7-Scenes folds, single
/// image against the SfM reference: one answer 66 cm / 15° off with 218 inliers and NEES
/// 1456; with this refusal the seven folds have no answer outside the 99.9 % region and none
/// more than 25 cm off, mean recall 90.3 %; the second hypothesis on every frame without it:
/// 92.9 %, 4 and 3 such answers).
/// Both conditions: the two solutions share most matches, so C_u + C_f overstates how far
/// they may drift apart by chance, and poses within a few centimetres of each other are one
/// place however small their covariances. A refused pair may still be decided by the other
/// retrieved keyframes ([`vote_between`], step 8 of the module doc).
fn choose_hypothesis(union: Hypothesis, first: Hypothesis) -> Hypothesis {
    match (&union.0, &first.0) {
        (Ok(u), Ok(f)) => {
            if let Some((metres, degrees)) = apart(u, f) {
                let why = format!(
                    "ambiguous: the retrieved keyframes' matches and the best-ranked keyframe's alone give poses {metres:.2} m / {degrees:.1}° apart ({} and {} inliers)",
                    union.1, first.1
                );
                (Err(why), union.1.max(first.1))
            } else if first.1 > union.1 {
                first
            } else {
                union
            }
        }
        (Err(_), Ok(_)) => first,
        _ => union,
    }
}

/// Whether two accepted poses are two places ([`choose_hypothesis`]): with
/// δ = log(T_a⁻¹ T_b)^∨, δᵀ (C_a + C_b)⁻¹ δ above the χ²₆ 99.9 % quantile and the poses
/// apart by more than [`AMBIGUOUS_SEPARATION_M`] or [`AMBIGUOUS_SEPARATION_DEG`]; then their
/// separation (m, degrees).
fn apart(a: &Estimate, b: &Estimate) -> Option<(f64, f64)> {
    let (delta, nees) = correction(&a.world_from_cam, &b.world_from_cam, &(a.covariance + b.covariance));
    let (metres, degrees) = (delta.fixed_rows::<3>(0).norm(), delta.fixed_rows::<3>(3).norm().to_degrees());
    let far = metres > AMBIGUOUS_SEPARATION_M || degrees > AMBIGUOUS_SEPARATION_DEG;
    (far && nees > CHI2_6_999).then_some((metres, degrees))
}

/// Of two places (accepted hypotheses that are [`apart`], each with its inlier count) the one
/// the other retrieved keyframes' accepted poses `others` side with (step 8): some lie at it
/// and none at the other; None when they do not decide (none accepted, or some at each).
/// The answer's covariance holds both places, C + δδᵀ with δ = log(T⁻¹ T_other)^∨: the vote
/// makes one place likelier, it does not rule out the other.
fn vote_between(places: Places, others: &[Estimate]) -> Option<(Estimate, usize)> {
    let [(a, _), (b, _)] = &places;
    let sides =
        |x: &Estimate, y: &Estimate| others.iter().filter(|o| apart(o, x).is_none() && apart(o, y).is_some()).count();
    let (chosen, other) = match (sides(a, b), sides(b, a)) {
        (1.., 0) => (places[0], &places[1].0),
        (0, 1..) => (places[1], &places[0].0),
        _ => return None,
    };
    let (estimate, inliers) = chosen;
    Some((widened_to_hold(&estimate, other), inliers))
}

/// `estimate` with its covariance widened to C + δδᵀ, δ = log(T⁻¹ T_other)^∨ (right
/// perturbation, translation first), so that its region holds `other` too (NEES of `other`
/// m/(1 + m) < 1 with m = δᵀC⁻¹δ): an answer that makes one of two places likelier without
/// ruling out the other (steps 8 and 9).
pub(super) fn widened_to_hold(estimate: &Estimate, other: &Estimate) -> Estimate {
    let (delta, _) = correction(&estimate.world_from_cam, &other.world_from_cam, &estimate.covariance);
    let widening = delta * delta.transpose();
    Estimate {
        covariance: estimate.covariance + widening,
        pixel_covariance: estimate.pixel_covariance + widening,
        ..*estimate
    }
}

/// Of the answer from the retrieved keyframes and the one from the keyframes nearest it (step
/// 9): the first when the second is refused; the one with more inliers (ties: the first) when
/// they are one place (not [`apart`]); when they are two places, the first if it has at least
/// as many inliers — the nearest keyframes' matches were the weaker view — else the second
/// with its covariance widened to C + δδᵀ (δ = log(T⁻¹ T_first)^∨, as in [`vote_between`]),
/// refused when that is beyond the acceptance rule's σ caps — or, without `hedge` (a held-out
/// keyframe: see the module doc), refused as two places. Each is (keyframe, pose or refusal,
/// inliers); the chosen one keeps its keyframe.
fn choose_at_pose(
    first: GeometricPose,
    at_pose: GeometricPose,
    caps: &super::AcceptanceOptions,
    hedge: bool,
) -> GeometricPose {
    let (Ok(f), Ok(n)) = (&first.1, &at_pose.1) else { return first };
    let stronger = at_pose.2 > first.2;
    match apart(f, n) {
        None if stronger => at_pose,
        None => first,
        Some(_) if !stronger => first,
        Some((metres, degrees)) => {
            let widened = widened_to_hold(n, f);
            let beyond = if hedge {
                super::acceptance::too_uncertain(&widened.covariance, caps)
                    .map(|why| format!("widened to hold the first, the second is {why}"))
            } else {
                Some("a held-out keyframe's two places are not widened".to_string())
            };
            let answer = match beyond {
                None => Ok(widened),
                Some(why) => Err(format!(
                    "ambiguous: the retrieved keyframes' matches and those of the keyframes nearest their pose give poses {metres:.2} m / {degrees:.1}° apart ({} and {} inliers); {why}",
                    first.2, at_pose.2
                )),
            };
            (at_pose.0, answer, at_pose.2)
        }
    }
}

/// What steps 2–8 give from the retrieved keyframes ([`Localizer::retrieved_pose`]).
struct RetrievedAnswer {
    /// The answer: keyframe, pose or refusal, inliers.
    answer: GeometricPose,
    /// The two places when the answer is their refusal (step 10 may decide them; None for a
    /// held-out keyframe).
    places: Option<Places>,
    /// The best-ranked keyframe's own matches were refused (step 6): an accepted answer
    /// rests on the union's matches or a lower-ranked keyframe's (step 7), and step 9 must
    /// confirm it ([`unconfirmed`]).
    best_ranked_refused: bool,
}

impl RetrievedAnswer {
    /// `answer` alone: no two places, the best-ranked keyframe's matches not refused.
    fn of(answer: GeometricPose) -> Self {
        Self { answer, places: None, best_ranked_refused: false }
    }
}

/// Why the keyframes nearest `answer` do not confirm it (step 9, for an answer the
/// best-ranked keyframe's own matches refused), or None when they do: their solve `at_pose`
/// is accepted and one place with the answer (not [`apart`]). None for `at_pose` means the
/// nearest keyframes are the retrieved ones, which gave no second view.
fn unconfirmed(answer: &Estimate, at_pose: Option<&GeometricPose>) -> Option<String> {
    const REFUSED: &str = "not confirmed: the best-ranked keyframe's own matches were refused and";
    match at_pose {
        None => Some(format!("{REFUSED} the keyframes nearest the pose are the retrieved ones")),
        Some((_, Err(why), _)) => {
            Some(format!("{REFUSED} the keyframes nearest the pose give no accepted pose ({why})"))
        }
        Some((_, Ok(e), _)) => apart(answer, e).map(|(metres, degrees)| {
            format!("{REFUSED} the keyframes nearest the pose give one {metres:.2} m / {degrees:.1}° away")
        }),
    }
}

/// Step 10's verdict on two places: the one `confirmed` answer, else `refusal` saying that
/// the keyframes nearest each place confirm neither or both.
fn one_confirmed(refusal: GeometricPose, confirmed: Vec<GeometricPose>) -> GeometricPose {
    match <[GeometricPose; 1]>::try_from(confirmed) {
        Ok([answer]) => answer,
        Err(confirmed) => {
            let (keyframe, why, inliers) = refusal;
            let which = if confirmed.is_empty() { "neither" } else { "both" };
            (keyframe, why.map_err(|w| format!("{w}; the keyframes nearest each place confirm {which}")), inliers)
        }
    }
}

/// Adds the matching and PnP times of a solve that ran side by side with others (with its
/// own [`Timings`]) to the frame's: the stage times are sums over every solve, not wall time.
fn add_solve_times(timings: &mut Timings, own: &Timings) {
    timings.matching_ms += own.matching_ms;
    timings.pnp_ms += own.pnp_ms;
}

/// One 2D–3D correspondence: query keypoint, model point, descriptor distance.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Correspondence {
    query: usize,
    point: usize,
    distance: f32,
}

impl Localizer {
    /// The model locator (see the module doc) from the retrieved keyframes `top` (best
    /// first, at least one), skipping the keyframes in `excluded`.
    pub(super) fn model_pose(
        &self,
        frame: &Frame<'_>,
        top: &[usize],
        excluded: Range<usize>,
        timings: &mut Timings,
    ) -> Result<GeometricPose> {
        let model = self.model().ok_or_else(|| GeolocError::invalid("locator", "the map has no 3D model"))?;
        self.accepted.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clear();
        let answer = self.decided_pose(model, frame, top, excluded, timings)?;
        let t = Instant::now();
        let refined = self.refined_answer(frame, model, answer);
        timings.pnp_ms += ms(t);
        refined
    }

    /// Steps 1–11 (see the module doc) from `ranking`, the retrieved keyframes best first:
    /// the model locator from its first `top_k`, and, when that gives no accepted pose, from
    /// the next `top_k` (step 11), whose answer is taken only if accepted, with a note saying
    /// so; otherwise the first answer (its refusal).
    pub(super) fn ranked_model_pose(
        &self,
        frame: &Frame<'_>,
        ranking: &[usize],
        excluded: Range<usize>,
        timings: &mut Timings,
    ) -> Result<(GeometricPose, Option<String>)> {
        let k = self.options.top_k.min(ranking.len());
        let first = self.model_pose(frame, &ranking[..k], excluded.clone(), timings)?;
        let Err(why) = &first.1 else { return Ok((first, None)) };
        if ranking.len() <= k {
            return Ok((first, None));
        }
        let next = &ranking[k..];
        let second = self.model_pose(frame, next, excluded, timings)?;
        if second.1.is_err() {
            return Ok((first, None));
        }
        let note = format!(
            "from the next {} keyframes of the ranking: the first {k} gave no accepted pose ({why})",
            next.len()
        );
        Ok((second, Some(note)))
    }

    /// Steps 1–10 (see the module doc).
    fn decided_pose(
        &self,
        model: &SceneModel,
        frame: &Frame<'_>,
        top: &[usize],
        excluded: Range<usize>,
        timings: &mut Timings,
    ) -> Result<GeometricPose> {
        let retrieved = self.retrieved_pose(model, frame, top, excluded.clone(), timings)?;
        let first = retrieved.answer;
        if let Some(places) = retrieved.places {
            // step 10: the keyframes nearest each of two places
            return self.confirmed_place(model, frame, first, places, top, timings);
        }
        // step 9: the keyframes nearest the answer, retrieved by its pose
        let Ok(answer) = &first.1 else { return Ok(first) };
        let hedge = excluded.is_empty();
        let pose = answer.world_from_cam;
        let at_pose = self.solved_at(model, frame, &pose, top, excluded, timings)?;
        if retrieved.best_ranked_refused
            && let Some(why) = unconfirmed(answer, at_pose.as_ref())
        {
            return Ok((first.0, Err(why), first.2));
        }
        let Some(at_pose) = at_pose else { return Ok(first) };
        Ok(choose_at_pose(first, at_pose, &self.options.acceptance, hedge))
    }

    /// Steps 2–8 from the `top.len()` keyframes nearest `pose` outside `excluded` (steps 9 and
    /// 10), or None when those are the retrieved keyframes `top` — solved already — or none.
    fn solved_at(
        &self,
        model: &SceneModel,
        frame: &Frame<'_>,
        pose: &SE3,
        top: &[usize],
        excluded: Range<usize>,
        timings: &mut Timings,
    ) -> Result<Option<GeometricPose>> {
        let nearest = nearest_keyframes(self, pose, top.len(), &excluded);
        let mut retrieved = top.to_vec();
        retrieved.sort_unstable();
        if nearest.is_empty() || nearest == retrieved {
            return Ok(None);
        }
        Ok(Some(self.retrieved_pose(model, frame, &nearest, excluded, timings)?.answer))
    }

    /// Step 10: each of two `places` (refused as `refusal`) solved again (steps 2–8) from the
    /// keyframes nearest it; a place is confirmed when that answer is accepted and one place
    /// with it. Exactly one confirmed: the better supported of it and its confirmation
    /// ([`choose_at_pose`]: one place, more inliers); else the refusal, saying so.
    fn confirmed_place(
        &self,
        model: &SceneModel,
        frame: &Frame<'_>,
        refusal: GeometricPose,
        places: Places,
        top: &[usize],
        timings: &mut Timings,
    ) -> Result<GeometricPose> {
        // the two places are independent: solved side by side when threads are available,
        // each with its own timings (summed below, as for the two hypotheses)
        let solved = map_slice(&places, 2, |(place, _)| {
            let mut own = Timings::default();
            (self.solved_at(model, frame, &place.world_from_cam, top, 0..0, &mut own), own)
        });
        let mut confirmed = Vec::new();
        for ((place, inliers), (at_place, own)) in places.into_iter().zip(solved) {
            add_solve_times(timings, &own);
            let Some(at_place) = at_place? else { continue };
            if let Ok(e) = &at_place.1
                && apart(&place, e).is_none()
            {
                confirmed.push(choose_at_pose(
                    (at_place.0, Ok(place), inliers),
                    at_place,
                    &self.options.acceptance,
                    true,
                ));
            }
        }
        Ok(one_confirmed(refusal, confirmed))
    }

    /// Steps 2–8 from the keyframes `top` (best first): the answer, the two places when it is
    /// their refusal, and whether an answer rests on others than the best-ranked keyframe,
    /// whose own matches were refused ([`RetrievedAnswer`]).
    fn retrieved_pose(
        &self,
        model: &SceneModel,
        frame: &Frame<'_>,
        top: &[usize],
        excluded: Range<usize>,
        timings: &mut Timings,
    ) -> Result<RetrievedAnswer> {
        let usable = usable_points(model, &excluded);
        let t = Instant::now();
        let per_keyframe = self.retrieved_matches(frame, model, top, usable.as_deref())?;
        timings.matching_ms += ms(t);
        let union = one_to_one(per_keyframe.concat());
        if top.len() == 1 {
            let chosen = self.hypothesis(frame, model, union, usable.as_deref(), &excluded, timings)?;
            return Ok(RetrievedAnswer::of((top[0], chosen.0, chosen.1)));
        }
        // the best-ranked keyframe alone: its matches can be outvoted in the union. The two
        // hypotheses are independent: they run side by side when threads are available, each
        // with its own timings (the stage times below are then summed over both)
        let sets = [union, one_to_one(per_keyframe[0].clone())];
        let mut solved = map_slice(&sets, 2, |set| {
            let mut own = Timings::default();
            let hypothesis = self.hypothesis(frame, model, set.clone(), usable.as_deref(), &excluded, &mut own);
            (hypothesis, own)
        });
        let (alone, alone_timings) = solved.pop().expect("invariant: two hypotheses");
        let (union, union_timings) = solved.pop().expect("invariant: two hypotheses");
        for own in [union_timings, alone_timings] {
            add_solve_times(timings, &own);
        }
        let (union, alone) = (union?, alone?);
        let neither = union.0.is_err() && alone.0.is_err();
        let places = match (&union.0, &alone.0) {
            (Ok(u), Ok(f)) if apart(u, f).is_some() => Some([(*u, union.1), (*f, alone.1)]),
            _ => None,
        };
        let best_ranked_refused = alone.0.is_err();
        let chosen = choose_hypothesis(union, alone);
        // steps 3–5 on the matches of the retrieved keyframe of each rank of `ranks` alone,
        // side by side when threads are available (each with its own timings, summed here)
        let alone_at = |ranks: &[usize], timings: &mut Timings| {
            let solved = map_slice(ranks, 2, |&rank| {
                let mut own = Timings::default();
                let matches = one_to_one(per_keyframe[rank].clone());
                (self.hypothesis(frame, model, matches, usable.as_deref(), &excluded, &mut own), own)
            });
            solved
                .into_iter()
                .map(|(h, own)| {
                    add_solve_times(timings, &own);
                    h
                })
                .collect::<Vec<_>>()
        };
        let others: Vec<usize> = (1..per_keyframe.len()).collect();
        if neither {
            // neither place was accepted: each of the other retrieved keyframes' matches
            // alone, best-ranked first, the first accepted (a batch at a time; the batch's
            // other accepted solves join step 12, so its size is fixed, not the thread count)
            for ranks in others.chunks(OTHER_KEYFRAMES_AT_A_TIME) {
                for (&rank, h) in ranks.iter().zip(alone_at(ranks, timings)) {
                    let h = h?;
                    if h.0.is_ok() {
                        return Ok(RetrievedAnswer {
                            best_ranked_refused,
                            ..RetrievedAnswer::of((top[rank], h.0, h.1))
                        });
                    }
                }
            }
        } else if let Some(places) = places.filter(|_| excluded.is_empty()) {
            // two places: the other retrieved keyframes' matches alone vote between them (not
            // for a held-out keyframe: see the module doc)
            let mut votes = Vec::new();
            for h in alone_at(&others, timings) {
                votes.extend(h?.0.ok());
            }
            // the widened covariance is a claim like any other: within the σ caps or refused
            if let Some((answer, inliers)) = vote_between(places, &votes)
                && super::acceptance::too_uncertain(&answer.covariance, &self.options.acceptance).is_none()
            {
                return Ok(RetrievedAnswer::of((top[0], Ok(answer), inliers)));
            }
            return Ok(RetrievedAnswer { places: Some(places), ..RetrievedAnswer::of((top[0], chosen.0, chosen.1)) });
        }
        Ok(RetrievedAnswer { best_ranked_refused, ..RetrievedAnswer::of((top[0], chosen.0, chosen.1)) })
    }

    /// Steps 3–5 on the one-to-one retrieval matches `first`: T_G and C_G or why not, and the
    /// inlier count.
    #[allow(clippy::too_many_arguments)]
    fn hypothesis(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        first: Vec<Correspondence>,
        usable: Option<&[bool]>,
        excluded: &Range<usize>,
        timings: &mut Timings,
    ) -> Result<Hypothesis> {
        if first.len() < self.options.min_correspondences {
            let why = format!("{} query-model matches < {}", first.len(), self.options.min_correspondences);
            return Ok((Err(why), 0));
        }
        let t = Instant::now();
        let res = self.model_pnp(frame, model, &first, None)?;
        timings.pnp_ms += ms(t);
        if !res.success {
            return Ok((Err(res.reason), 0));
        }
        let tau = first.iter().zip(&res.inliers).filter(|(_, i)| **i).map(|(c, _)| c.distance).fold(0.0, f32::max);
        let first_inliers = count(&res.inliers);
        let retrieved: Vec<Correspondence> =
            first.iter().zip(&res.inliers).filter(|(_, i)| **i).map(|(c, _)| *c).collect();
        // the retrieval inliers a guided round over `candidates` (sorted) could find again:
        // their point is a candidate and its representative descriptor within τ
        let refindable = |candidates: &[usize]| {
            retrieved
                .iter()
                .filter(|c| {
                    candidates.binary_search(&c.point).is_ok()
                        && model.descriptors.view().distance(c.point, &frame.descriptors, c.query) <= tau
                })
                .count()
        };
        let mut confirmed = false;
        // each round projects from the last guided pose (`current`); `best` is the pose with
        // the most inliers; `guided_support` the most inliers a guided round found: a pose
        // the map's points near it confirm has at least the retrieval matches' support
        let mut current = res.world_from_cam;
        let mut best = res;
        let mut best_matches = first;
        let mut guided_support = 0;
        // (near keyframes, their points) of the last round: a pose that moved little keeps them
        let mut nearby: (Vec<usize>, Vec<usize>) = (Vec::new(), Vec::new());
        for round in 0..self.options.guided_rounds {
            let t = Instant::now();
            let near = near_keyframes(self, &current, excluded);
            if round == 0 || near != nearby.0 {
                nearby = (near.clone(), points_seen_by(model, &near, usable));
            }
            let guided = self.guided_matches(frame, model, &current, tau, &nearby.1);
            timings.matching_ms += ms(t);
            let t = Instant::now();
            let next = if guided.len() >= self.options.min_correspondences {
                Some(self.model_pnp(frame, model, &guided, Some(&current))?)
            } else {
                None
            };
            timings.pnp_ms += ms(t);
            match next {
                Some(r) if r.success => {
                    guided_support = guided_support.max(count(&r.inliers));
                    let again = refindable(&nearby.1);
                    confirmed |= count(&r.inliers) >= again;
                    current = r.world_from_cam;
                    if count(&r.inliers) >= count(&best.inliers) {
                        best = r;
                        best_matches = guided;
                    }
                }
                _ => break,
            }
        }
        let inliers = count(&best.inliers);
        if self.options.guided_rounds > 0 && !confirmed {
            let why = format!(
                "not confirmed by the map near the pose: guided matching found {guided_support} inliers, fewer than the retrieved keyframes' matches it could find again (of {first_inliers})"
            );
            return Ok((Err(why), inliers));
        }
        if let Some(why) = self.model_rejection(model, &best, &best_matches) {
            return Ok((Err(why), inliers));
        }
        let matches = best_matches.iter().zip(&best.inliers).filter(|(_, i)| **i).map(|(c, _)| *c).collect();
        let estimate = Estimate {
            world_from_cam: best.world_from_cam,
            covariance: best.covariance,
            pixel_covariance: best.pixel_covariance,
        };
        self.accepted
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(AcceptedSolve { estimate, matches });
        Ok((Ok(estimate), inliers))
    }

    /// Steps 5b and 12 on the answer of steps 1–11. The frame's accepted solves at the
    /// answer's place — its own [`AcceptedSolve`] and every other one not [`apart`] from it,
    /// one per pose — are each re-solved by [`Localizer::shared_refinement`] (step 5b, side
    /// by side when threads are available), and the answer's pose is their information-
    /// weighted mean under the solves' C_G ([`weighted_mean`], step 12). The covariance is
    /// left as it is: the solves share most of their matches, and their mean is no better
    /// known than the answer's own solve.
    fn refined_answer(&self, frame: &Frame<'_>, model: &SceneModel, answer: GeometricPose) -> Result<GeometricPose> {
        let solves = std::mem::take(&mut *self.accepted.lock().unwrap_or_else(std::sync::PoisonError::into_inner));
        let (keyframe, Ok(mut estimate), inliers) = answer else { return Ok(answer) };
        // the solves of one frame run side by side and arrive in any order: of those at the
        // answer's pose, the first in [`solve_order`]
        let at_answer = solves.iter().filter(|s| s.estimate.world_from_cam == estimate.world_from_cam);
        let Some(solve) = at_answer.min_by_key(|s| solve_order(s)) else {
            return Ok((keyframe, Ok(estimate), inliers));
        };
        let place = solves_at_place(&solves, solve);
        let refined = map_slice(&place, 2, |s| self.refined_pose(frame, model, s));
        let members = place
            .iter()
            .zip(refined)
            .map(|(s, pose)| Ok((pose?, s.estimate.covariance)))
            .collect::<Result<Vec<_>>>()?;
        // (a solve's C_G is positive definite, or it would not have been accepted; were it
        // not, the answer keeps its own solve's pose)
        estimate.world_from_cam = match members.as_slice() {
            [(only, _)] => *only,
            _ => weighted_mean(&members).unwrap_or(members[0].0),
        };
        Ok((keyframe, Ok(estimate), inliers))
    }

    /// Step 5b on one accepted solve: its pose re-solved by [`Localizer::shared_refinement`]
    /// when that lies inside the solve's 95 % region (C_G) — the same inliers re-weighted,
    /// not a jump — else its pose as it is.
    fn refined_pose(&self, frame: &Frame<'_>, model: &SceneModel, solve: &AcceptedSolve) -> Result<SE3> {
        let pose = solve.estimate.world_from_cam;
        Ok(match self.shared_refinement(frame, model, &pose, &solve.matches)? {
            Some(refined) if correction(&pose, &refined, &solve.estimate.covariance).1 <= CHI2_6_95 => refined,
            _ => pose,
        })
    }

    /// Step 5b: `pose` solved again from itself on its `inliers` with the
    /// points' uncertainty split as triangulation made it: each point's pixel-noise
    /// covariance Σ_pix, independent between points, and the errors of the keyframe poses it
    /// was triangulated from (D_jk = ∂X_j/∂δ_k with the map's pose covariances C_k), which
    /// every point those keyframes see shares ([`point_covariance_terms`]; the paper
    /// locator's group model applied to the map-level points). The joint solve weights each
    /// point by its own Σ_pix: Σ_X, which holds the keyframes' C_k as if each point had its
    /// own, weights a point down for an error it shares with the others, most the far points
    /// that pin the rotation. None when the map has no pose covariances (Σ_X is Σ_pix) or the
    /// solve fails.
    ///
    /// Only the pose is taken. The covariance that goes with it would add the shared part,
    /// Σ_k M_k C_k M_kᵀ, to the one of independent points; that part is map error, which
    /// the map noise C_map carries — measured as the held-out keyframes' error beyond C_G,
    /// the independent-points covariance, so C_G stays that one (the sequential mode's
    /// fusion weighs only its pixel part, [`super::Estimate::pixel_covariance`]).
    fn shared_refinement(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        pose: &SE3,
        inliers: &[Correspondence],
    ) -> Result<Option<SE3>> {
        let Some(pose_covariances) = self.map.pose_covariances.as_deref() else { return Ok(None) };
        if inliers.len() < self.options.min_correspondences {
            return Ok(None);
        }
        let (camera, poses) = (&self.map.camera, self.map.poses());
        let sigma = self.options.triangulation.pixel_sigma;
        // the keyframes whose pose errors the inlier points share, increasing
        let mut keyframes: Vec<usize> = inliers.iter().flat_map(|c| model.observers(c.point).iter().copied()).collect();
        keyframes.sort_unstable();
        keyframes.dedup();
        let mut pixel = Vec::with_capacity(inliers.len());
        let mut partials: Vec<PosePartials> = Vec::with_capacity(inliers.len());
        for c in inliers {
            let x = &model.points[c.point];
            let views = model
                .observers(c.point)
                .iter()
                .map(|&k| (k, view_weight(camera, &poses, Some(pose_covariances), sigma, k, x)));
            let Some(terms) = point_covariance_terms(camera, &poses, Some(pose_covariances), sigma, x, views) else {
                return Ok(None);
            };
            pixel.push(terms.pixel);
            let mut row: PosePartials = terms
                .pose_jacobians
                .into_iter()
                .map(|(k, d)| (keyframes.binary_search(&k).expect("invariant: an observer of an inlier point"), d))
                .collect();
            row.sort_unstable_by_key(|(k, _)| *k);
            partials.push(row);
        }
        let shared_covariances: Vec<_> = keyframes.iter().map(|&k| pose_covariances[k]).collect();
        let shared = SharedPoseUncertainty { jacobians: &partials, pose_covariances: &shared_covariances };
        let uncertainty = PointUncertainty { covariances: &pixel, shared: Some(shared) };
        let res = self.pnp_on(frame, model, inliers, Some(pose), &uncertainty)?;
        Ok(res.success.then_some(res.world_from_cam))
    }

    /// The acceptance rule ([`super::acceptance`]) for the model locator's pose: each inlier
    /// point with the centres of every keyframe that observes it.
    fn model_rejection(&self, model: &SceneModel, res: &PnpResult, matches: &[Correspondence]) -> Option<String> {
        let kf = &self.map.keyframes;
        let (points, observers): (Vec<Vector3<f64>>, Vec<Vec<Vector3<f64>>>) = matches
            .iter()
            .zip(&res.inliers)
            .filter(|(_, i)| **i)
            .map(|(c, _)| {
                let seen = model.observers(c.point).iter().map(|&k| kf[k].world_from_cam.translation).collect();
                (model.points[c.point], seen)
            })
            .unzip();
        let center = res.world_from_cam.translation;
        super::acceptance::rejection(&center, &res.covariance, &points, &observers, &self.options.acceptance)
    }

    /// Step 2: the query matched against the model points of each retrieved keyframe, one
    /// list per keyframe of `top` (empty when it observes no usable point); [`one_to_one`]
    /// makes a set of them a correspondence set (see the module doc).
    fn retrieved_matches(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        top: &[usize],
        usable: Option<&[bool]>,
    ) -> Result<Vec<Vec<Correspondence>>> {
        let options = MatchOptions { mutual: false, ..self.options.matching };
        top.iter()
            .map(|&k| {
                let (rows, ids): (Vec<usize>, Vec<usize>) = model.point_ids[k]
                    .iter()
                    .enumerate()
                    .filter_map(|(i, id)| id.filter(|&p| usable.is_none_or(|u| u[p])).map(|p| (i, p)))
                    .unzip();
                if rows.is_empty() {
                    return Ok(Vec::new());
                }
                let descriptors = self.map.keyframes[k].descriptors.select(&rows);
                let matches = match_descriptors(&frame.descriptors, &descriptors.view(), &options)?;
                Ok(matches
                    .iter()
                    .map(|m| Correspondence { query: m.a, point: ids[m.b], distance: m.distance })
                    .collect())
            })
            .collect()
    }

    /// Step 4: the guided correspondences of the `candidates` points at `pose` (see the
    /// module doc): per point, the query keypoint within `guided_radius_px` of its projection
    /// with the smallest (descriptor distance, keypoint) at most τ, then [`one_to_one`].
    ///
    /// Searched from the keypoints' side: the projections that can be within r of a keypoint
    /// (inside the keypoints' bounding box widened by 2r) go into a grid, and each keypoint
    /// takes the projections within r of it ([`PointGrid::within`], whose test
    /// ‖u − k‖² ≤ r² is symmetric in its two points to the bit). The pairs are those of a
    /// search from each point's projection, and the per-point minimum does not depend on the
    /// order they come in; a thousand keypoint queries replace tens of thousands of point
    /// queries (which were most of a guided round).
    fn guided_matches(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        pose: &SE3,
        tau: f32,
        candidates: &[usize],
    ) -> Vec<Correspondence> {
        let inverse = pose.inverse();
        let (r, camera) = (self.options.guided_radius_px, &self.map.camera);
        let Some((lo, hi)) = bounds(frame.keypoints) else { return Vec::new() };
        let (lo, hi) = (lo.add_scalar(-2.0 * r), hi.add_scalar(2.0 * r));
        let (points, projections): (Vec<usize>, Vec<Vector2<f64>>) = candidates
            .iter()
            .filter_map(|&p| {
                let uv = project_in_front(camera, &inverse, &model.points[p])?;
                (uv.x >= lo.x && uv.x <= hi.x && uv.y >= lo.y && uv.y <= hi.y).then_some((p, uv))
            })
            .unzip();
        let grid = PointGrid::new(&projections, r);
        let mut best: Vec<Option<(f32, usize)>> = vec![None; points.len()];
        for (q, keypoint) in frame.keypoints.iter().enumerate() {
            for i in grid.within(keypoint, r) {
                let d = model.descriptors.view().distance(points[i], &frame.descriptors, q);
                if d <= tau && best[i].is_none_or(|b| (d, q) < b) {
                    best[i] = Some((d, q));
                }
            }
        }
        let found = points
            .iter()
            .zip(best)
            .filter_map(|(&point, b)| b.map(|(distance, query)| Correspondence { query, point, distance }))
            .collect();
        one_to_one(found)
    }

    /// PnP on `matches` with the points' model covariances, from `init` when given.
    fn model_pnp(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        matches: &[Correspondence],
        init: Option<&SE3>,
    ) -> Result<PnpResult> {
        let covs: Vec<Matrix3<f64>> = matches.iter().map(|c| model.covariances[c.point]).collect();
        let uncertainty = PointUncertainty { covariances: &covs, shared: None };
        self.pnp_on(frame, model, matches, init, &uncertainty)
    }

    /// PnP on `matches` (the model points and the frame's keypoints, with their pixel σ
    /// scales) with the points' `uncertainty`, from `init` when given.
    fn pnp_on(
        &self,
        frame: &Frame<'_>,
        model: &SceneModel,
        matches: &[Correspondence],
        init: Option<&SE3>,
        uncertainty: &PointUncertainty<'_>,
    ) -> Result<PnpResult> {
        let pts: Vec<Vector3<f64>> = matches.iter().map(|c| model.points[c.point]).collect();
        let px: Vec<Vector2<f64>> = matches.iter().map(|c| frame.keypoints[c.query]).collect();
        let sigmas: Option<Vec<f64>> = frame.pixel_sigmas.map(|s| matches.iter().map(|c| s[c.query]).collect());
        let (camera, options) = (&self.map.camera, &self.options.pnp);
        solve_pnp_with_pixel_sigmas(camera, &pts, &px, sigmas.as_deref(), init, Some(uncertainty), options)
    }
}

fn count(mask: &[bool]) -> usize {
    mask.iter().filter(|b| **b).count()
}

/// Which points may be used when `excluded` keyframes are held out: those none of them
/// observes (None: no keyframe excluded, every point).
fn usable_points(model: &SceneModel, excluded: &Range<usize>) -> Option<Vec<bool>> {
    if excluded.is_empty() {
        return None;
    }
    Some((0..model.len()).map(|p| !model.observers(p).iter().any(|k| excluded.contains(k))).collect())
}

/// The keyframes near `pose` (centre within [`GUIDED_KEYFRAME_DISTANCE_M`], rotation within
/// [`GUIDED_KEYFRAME_ANGLE_DEG`]) and not excluded, increasing.
fn near_keyframes(loc: &Localizer, pose: &SE3, excluded: &Range<usize>) -> Vec<usize> {
    let max_angle = GUIDED_KEYFRAME_ANGLE_DEG.to_radians();
    (0..loc.map.keyframes.len())
        .filter(|k| !excluded.contains(k))
        .filter(|&k| {
            let kf = &loc.map.keyframes[k].world_from_cam;
            (kf.translation - pose.translation).norm() < GUIDED_KEYFRAME_DISTANCE_M
                && kf.rotation.distance(&pose.rotation) < max_angle
        })
        .collect()
}

/// Step 9: the `n` keyframes nearest `pose`, not excluded, increasing: nearest by
/// [`pose_distance`] (10 cm or 5° count 1; ties: the lower index).
fn nearest_keyframes(loc: &Localizer, pose: &SE3, n: usize, excluded: &Range<usize>) -> Vec<usize> {
    let mut by_distance: Vec<(f64, usize)> = (0..loc.map.keyframes.len())
        .filter(|k| !excluded.contains(k))
        .map(|k| (pose_distance(&loc.map.keyframes[k].world_from_cam, pose), k))
        .collect();
    by_distance.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut nearest: Vec<usize> = by_distance.into_iter().take(n).map(|(_, k)| k).collect();
    nearest.sort_unstable();
    nearest
}

/// The usable points observed by `keyframes`, increasing.
fn points_seen_by(model: &SceneModel, keyframes: &[usize], usable: Option<&[bool]>) -> Vec<usize> {
    let mut seen = vec![false; model.len()];
    for &k in keyframes {
        for &p in model.observed(k) {
            seen[p] = usable.is_none_or(|u| u[p]);
        }
    }
    seen.iter().enumerate().filter(|(_, s)| **s).map(|(p, _)| p).collect()
}

/// One point per query keypoint (smallest distance, then lowest point), then one query
/// keypoint per point (smallest distance, then lowest keypoint); sorted by query keypoint.
fn one_to_one(mut all: Vec<Correspondence>) -> Vec<Correspondence> {
    all.sort_by(|a, b| a.query.cmp(&b.query).then(a.distance.total_cmp(&b.distance)).then(a.point.cmp(&b.point)));
    all.dedup_by_key(|c| c.query);
    all.sort_by(|a, b| a.point.cmp(&b.point).then(a.distance.total_cmp(&b.distance)).then(a.query.cmp(&b.query)));
    all.dedup_by_key(|c| c.point);
    all.sort_by_key(|c| c.query);
    all
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_to_one_keeps_the_closest_each_way() {
        let c = |query, point, distance| Correspondence { query, point, distance };
        let got = one_to_one(vec![c(0, 5, 3.0), c(0, 6, 2.0), c(1, 6, 1.0), c(2, 7, 4.0), c(3, 7, 4.0)]);
        // q0 → p6 (2) loses p6 to q1 (1); p7 ties at 4 → lower query 2.
        assert_eq!(got, vec![c(1, 6, 1.0), c(2, 7, 4.0)]);
    }

    fn accepted(translation: [f64; 3], rotation_deg: f64, sigma: f64, inliers: usize) -> Hypothesis {
        let rotation = crate::lie::SO3::exp(&Vector3::new(0.0, rotation_deg.to_radians(), 0.0));
        let pose = SE3::new(rotation, Vector3::from(translation));
        let covariance = nalgebra::Matrix6::identity() * sigma * sigma;
        (Ok(Estimate { world_from_cam: pose, covariance, pixel_covariance: covariance }), inliers)
    }

    fn refused(why: &str) -> Hypothesis {
        (Err(why.into()), 0)
    }

    fn solve(translation: [f64; 3], sigma: f64, matches: &[(usize, usize)]) -> AcceptedSolve {
        let (Ok(estimate), _) = accepted(translation, 0.0, sigma, 0) else { unreachable!("accepted") };
        let matches = matches.iter().map(|&(query, point)| Correspondence { query, point, distance: 1.0 }).collect();
        AcceptedSolve { estimate, matches }
    }

    /// Step 12's solves: the answer first; a solve 30 cm off with σ = 1 cm (apart: NEES 450,
    /// beyond 10 cm) left out; one 3 cm off (one place) and one 0.5 cm off kept, most matches
    /// first; the answer's own pose or matches found again and a pose found twice counted
    /// once; the same list whatever order the solves arrived in.
    #[test]
    fn the_solves_at_the_answers_place_are_the_other_solves_not_apart_from_it_once_each() {
        let answer = solve([0.0; 3], 0.01, &[(0, 0), (1, 1), (2, 2)]);
        let solves = vec![
            solve([0.3, 0.0, 0.0], 0.01, &[(0, 9), (1, 8), (2, 7), (3, 6)]),
            solve([0.03, 0.0, 0.0], 0.01, &[(0, 0), (1, 1)]),
            solve([0.0, 0.005, 0.0], 0.01, &[(0, 0), (1, 1), (2, 2), (4, 4)]),
            solve([0.03, 0.0, 0.0], 0.01, &[(0, 0), (5, 5)]),
            solve([0.0; 3], 0.01, &[(0, 0)]),
            solve([0.0, 0.0, 1e-9], 0.01, &[(0, 0), (1, 1), (2, 2)]),
        ];
        let got = |solves: &[AcceptedSolve]| -> Vec<[f64; 3]> {
            solves_at_place(solves, &answer).iter().map(|s| s.estimate.world_from_cam.translation.into()).collect()
        };
        let want = vec![[0.0; 3], [0.0, 0.005, 0.0], [0.03, 0.0, 0.0]];
        assert_eq!(got(&solves), want);
        let mut reversed = solves;
        reversed.reverse();
        assert_eq!(got(&reversed), want);
        // of the two solves at 3 cm the one with the lesser (query, point) list stands for both
        let place = solves_at_place(&reversed, &answer);
        assert_eq!(place[2].matches[1].query, 1);
    }

    /// Closed-form NEES δᵀ(C_u + C_f)⁻¹δ with C = σ²I: 30 cm apart with σ = 1 cm gives
    /// 0.3² / (2·0.01²) = 450 > χ²₆ 99.9 % (22.46), and far → refused, naming the
    /// separation; 5° apart with σ = 1 mm / 1 mrad gives ≈ 3800 → refused; 30 cm apart with
    /// σ = 0.5 gives 0.18 → the one with more inliers; 5 cm apart with σ = 1 mm gives 1250
    /// but is one place → the one with more inliers (ties: the union's).
    #[test]
    fn two_places_are_refused_one_place_keeps_the_better_supported() {
        let union = accepted([0.0, 0.0, 0.0], 0.0, 0.01, 200);
        let (pose, n) = choose_hypothesis(union.clone(), accepted([0.3, 0.0, 0.0], 0.0, 0.01, 150));
        let why = pose.expect_err("two places");
        assert!(why.contains("ambiguous") && why.contains("0.30 m"), "{why}");
        assert_eq!(n, 200);
        let (pose, _) = choose_hypothesis(union.clone(), accepted([0.0, 0.0, 0.0], 5.0, 0.001, 250));
        assert!(pose.expect_err("turned 5°").contains("5.0°"));
        let wide = choose_hypothesis(accepted([0.0; 3], 0.0, 0.5, 200), accepted([0.3, 0.0, 0.0], 0.0, 0.5, 250));
        assert_eq!(wide.1, 250);
        assert!(wide.0.is_ok());
        let close = choose_hypothesis(accepted([0.0; 3], 0.0, 0.001, 200), accepted([0.05, 0.0, 0.0], 0.0, 0.001, 250));
        assert_eq!(close.1, 250);
        let tie = choose_hypothesis(accepted([0.0; 3], 0.0, 0.001, 200), accepted([0.05, 0.0, 0.0], 0.0, 0.001, 200));
        assert!(tie.0.expect("kept").world_from_cam.translation.norm() < 1e-12, "ties go to the union");
    }

    /// The vote between two places 30 cm apart (σ = 1 cm, so apart): a third pose at one of
    /// them (2 cm off, within its covariances) decides for it; one at each, one at neither or
    /// none leaves the frame refused. The answer keeps its pose and inliers, and its
    /// covariance is C + δδᵀ with δ = log(T⁻¹ T_other)^∨ (here (∓0.3, 0, 0, 0, 0, 0)): the other
    /// place has NEES δᵀ(C + δδᵀ)⁻¹δ = m/(1 + m) < 1, m = δᵀC⁻¹δ = 900 (Sherman–Morrison).
    #[test]
    fn the_other_keyframes_vote_between_two_places() {
        let estimate = |h: Hypothesis| h.0.expect("accepted");
        let (a, b) =
            (estimate(accepted([0.0; 3], 0.0, 0.01, 200)), estimate(accepted([0.3, 0.0, 0.0], 0.0, 0.01, 150)));
        let near_a = estimate(accepted([0.02, 0.0, 0.0], 0.0, 0.01, 90));
        let near_b = estimate(accepted([0.28, 0.0, 0.0], 0.0, 0.01, 90));
        let neither = estimate(accepted([1.0, 0.0, 0.0], 0.0, 0.01, 90));
        assert!(apart(&a, &b).is_some() && apart(&near_a, &a).is_none() && apart(&near_a, &b).is_some());
        let (answer, inliers) = vote_between([(a, 200), (b, 150)], &[near_a, neither]).expect("decided");
        assert_eq!((answer.world_from_cam, inliers), (a.world_from_cam, 200));
        let mut want = a.covariance;
        want[(0, 0)] += 0.09;
        assert!((answer.covariance - want).abs().max() < 1e-12, "{}", answer.covariance);
        let (_, m) = correction(&answer.world_from_cam, &b.world_from_cam, &answer.covariance);
        assert!((m - 900.0 / 901.0).abs() < 1e-9, "{m}");
        let (answer, inliers) = vote_between([(a, 200), (b, 150)], &[near_b]).expect("decided");
        assert_eq!((answer.world_from_cam, inliers), (b.world_from_cam, 150));
        for others in [vec![near_a, near_b], vec![neither], vec![]] {
            assert!(vote_between([(a, 200), (b, 150)], &others).is_none(), "{} others", others.len());
        }
        // the widened covariance meets the σ caps (0.152 m) only for places close enough:
        // 30 cm apart, σ_x = √(0.01² + 0.3²) ≈ 0.30 m is refused; 12 cm apart, ≈ 0.12 m is not
        let caps = crate::localizer::AcceptanceOptions::default();
        let (wide, _) = vote_between([(a, 200), (b, 150)], &[near_a]).expect("decided");
        assert!(super::super::acceptance::too_uncertain(&wide.covariance, &caps).is_some());
        let c = estimate(accepted([0.12, 0.0, 0.0], 0.0, 0.01, 150));
        let beside_a = estimate(accepted([-0.02, 0.0, 0.0], 0.0, 0.01, 90));
        let (close, _) = vote_between([(a, 200), (c, 150)], &[beside_a]).expect("decided");
        assert!(super::super::acceptance::too_uncertain(&close.covariance, &caps).is_none(), "{}", close.covariance);
    }

    /// Step 9 in closed form (C = σ²I, σ = 1 cm): the second refused → the first; one place
    /// (3 cm apart) → the one with more inliers, ties the first; two places (12 cm apart,
    /// NEES 0.12²/(2·0.01²) = 72 > 22.46) → the first when the second has no more inliers,
    /// else the second widened by δδᵀ (σ_x = √(0.01² + 0.12²) ≈ 0.120 m, within the 0.152 m
    /// cap); 30 cm apart the widened σ_x ≈ 0.300 m is beyond the cap → refused, naming both.
    #[test]
    fn the_keyframes_nearest_the_answer_replace_it_only_with_more_support() {
        let caps = crate::localizer::AcceptanceOptions::default();
        // the first answer from keyframe 1, the second from keyframe 2
        let on = |k: usize, h: Hypothesis| (k, h.0, h.1);
        let first = on(1, accepted([0.0; 3], 0.0, 0.01, 200));
        let pick = |a: GeometricPose, b: Hypothesis| choose_at_pose(a, on(2, b), &caps, true);
        let (keyframe, pose, inliers) = pick(first.clone(), refused("n"));
        assert_eq!((pose.expect("first").world_from_cam, inliers, keyframe), (SE3::identity(), 200, 1));
        let same_place = |n| accepted([0.03, 0.0, 0.0], 0.0, 0.01, n);
        assert_eq!(pick(first.clone(), same_place(201)).2, 201);
        assert_eq!(pick(first.clone(), same_place(201)).0, 2);
        assert_eq!(pick(first.clone(), same_place(200)).2, 200);
        assert_eq!(pick(first.clone(), same_place(200)).0, 1, "ties: the first");
        let near = |x: f64, n| accepted([x, 0.0, 0.0], 0.0, 0.01, n);
        let (keyframe, weaker, _) = pick(first.clone(), near(0.12, 150));
        assert!(keyframe == 1 && weaker.expect("first").world_from_cam == SE3::identity());
        let (keyframe, widened, inliers) = pick(first.clone(), near(0.12, 250));
        let widened = widened.expect("within the caps");
        assert!(keyframe == 2 && inliers == 250);
        assert!((widened.world_from_cam.translation.x - 0.12).abs() < 1e-12);
        let mut want = nalgebra::Matrix6::identity() * 1e-4;
        want[(0, 0)] += 0.12 * 0.12;
        assert!((widened.covariance - want).abs().max() < 1e-12, "{}", widened.covariance);
        let (_, refusal, _) = pick(first.clone(), near(0.30, 250));
        let why = refusal.expect_err("beyond the caps");
        assert!(
            why.contains("0.30 m") && why.contains("200 and 250 inliers") && why.contains("too uncertain"),
            "{why}"
        );
        // a held-out keyframe is not hedged: two places stay refused, one place is decided as above
        let (_, held_out, _) = choose_at_pose(first.clone(), on(2, near(0.12, 250)), &caps, false);
        assert!(held_out.expect_err("two places").contains("held-out"));
        assert_eq!(choose_at_pose(first, on(2, same_place(201)), &caps, false).2, 201);
    }

    /// Step 9's confirmation of an answer the best-ranked keyframe's own matches refused, in
    /// closed form (C = σ²I, σ = 1 cm): an accepted pose 3 cm away confirms it (one place);
    /// no second view (the nearest keyframes are the retrieved ones), a refusal (its reason
    /// kept) and a pose 12 cm away (NEES 0.12²/(2·0.01²) = 72 > 22.46: two places, whatever
    /// its support) do not, each saying why.
    #[test]
    fn an_answer_the_best_ranked_keyframe_refused_stands_only_where_the_nearest_keyframes_confirm_it() {
        let (Ok(answer), _) = accepted([0.0; 3], 0.0, 0.01, 100) else { unreachable!("accepted") };
        let at = |h: Hypothesis| -> GeometricPose { (2, h.0, h.1) };
        assert_eq!(unconfirmed(&answer, Some(&at(accepted([0.03, 0.0, 0.0], 0.0, 0.01, 80)))), None);
        let none = unconfirmed(&answer, None).expect("no second view");
        assert!(none.ends_with("the keyframes nearest the pose are the retrieved ones"), "{none}");
        let refusal = unconfirmed(&answer, Some(&at(refused("9 query-model matches < 12")))).expect("refused");
        assert!(refusal.ends_with("no accepted pose (9 query-model matches < 12)"), "{refusal}");
        let two = unconfirmed(&answer, Some(&at(accepted([0.12, 0.0, 0.0], 0.0, 0.01, 300)))).expect("two places");
        assert!(two.ends_with("give one 0.12 m / 0.0° away"), "{two}");
        assert!([none, refusal, two].iter().all(|w| w.starts_with("not confirmed: the best-ranked keyframe's")));
    }

    /// Step 10 in closed form: one confirmed place is the answer; none or both leave the
    /// refusal, which says which.
    #[test]
    fn two_places_are_decided_only_when_the_keyframes_nearest_one_confirm_it() {
        let refusal: GeometricPose = (3, Err("ambiguous: 0.30 m apart".to_string()), 120);
        let at =
            |x: f64, inliers: usize| -> GeometricPose { (7, accepted([x, 0.0, 0.0], 0.0, 0.01, inliers).0, inliers) };
        let answer = one_confirmed(refusal.clone(), vec![at(0.3, 150)]);
        assert_eq!(answer.0, 7);
        assert_eq!(answer.2, 150);
        assert!((answer.1.expect("decided").world_from_cam.translation.x - 0.3).abs() < 1e-12);
        for (confirmed, which) in [(vec![], "neither"), (vec![at(0.0, 90), at(0.3, 150)], "both")] {
            let (keyframe, why, inliers) = one_confirmed(refusal.clone(), confirmed);
            assert_eq!((keyframe, inliers), (3, 120));
            let why = why.expect_err("still refused");
            assert!(why.starts_with("ambiguous: 0.30 m apart; "), "{why}");
            assert!(why.ends_with(&format!("the keyframes nearest each place confirm {which}")), "{why}");
        }
    }

    /// One refused: the other; both refused: the union's reason.
    #[test]
    fn a_refused_hypothesis_leaves_the_other() {
        let ok = accepted([1.0, 0.0, 0.0], 0.0, 0.01, 90);
        assert_eq!(choose_hypothesis(refused("u"), ok.clone()).1, 90);
        assert_eq!(choose_hypothesis(ok.clone(), refused("f")).1, 90);
        assert_eq!(choose_hypothesis(refused("u"), refused("f")).0.expect_err("both"), "u");
    }
}

#[cfg(test)]
mod scene_tests {
    use std::num::NonZero;
    use std::sync::Arc;

    use super::*;
    use crate::localizer::{LocalizerOptions, Locator, Source};
    use crate::map::model::fixture;
    use crate::parallel::{Parallelism, with_parallelism};
    use crate::pnp::MIN_ACCEPTED_INLIERS;
    use crate::testing::{SplitMix64, walk};

    /// Queries 15 cm beside the keyframes' path: (position error, inliers) per frame.
    fn run(locator: Locator, with_model: bool) -> Vec<(f64, usize)> {
        let (world, map, _) = fixture::scene(40, false);
        let map = if with_model { map.with_model(&crate::map::ModelOptions::default()).expect("model") } else { map };
        let options = LocalizerOptions { locator, ..LocalizerOptions::default() };
        let mut loc = Localizer::new(Arc::new(map), options).expect("localizer");
        let mut rng = SplitMix64::new(99);
        (0..12)
            .map(|i| {
                let truth = walk(0.3 + i as f64 * 0.27, 0.15, -1.5);
                let (keypoints, data) = world.observe(&mut rng, &truth, 5);
                let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
                let frame =
                    Frame { timestamp: i as f64, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
                loc.reset();
                let out = loc.localize(&frame).expect("valid frame");
                let err =
                    out.estimate.map_or(f64::INFINITY, |e| (e.world_from_cam.translation - truth.translation).norm());
                assert!(out.source == Source::Geometric || out.source == Source::Lost);
                (err, out.inliers)
            })
            .collect()
    }

    /// Step 5b on exact keyframes that the map believes uncertain (1 cm / 0.5° per axis): Σ_X
    /// then holds errors the points do not have, shared in truth by none and by all in the
    /// model; the re-weighted answer (each point by its pixel noise, the keyframe errors
    /// shared) is closer to the truth than the answer of steps 1–10 on average, and every
    /// refined pose stays inside the 95 % region of the solve it refines.
    #[test]
    fn shared_keyframe_errors_refine_the_answer() {
        let (world, mut map, _) = fixture::scene(40, false);
        let c = crate::testing::isotropic_pose_covariance(0.01, 0.5f64.to_radians());
        map.pose_covariances = Some(vec![c; map.keyframes.len()]);
        let map = Arc::new(map.with_model(&crate::map::ModelOptions::default()).expect("model"));
        let options = LocalizerOptions { locator: Locator::Model, ..LocalizerOptions::default() };
        let loc = Localizer::new(Arc::clone(&map), options).expect("localizer");
        let model = loc.model().expect("a model");
        let mut rng = SplitMix64::new(99);
        let (mut before, mut after, mut moved) = (Vec::new(), Vec::new(), 0);
        for i in 0..12 {
            let truth = walk(0.3 + i as f64 * 0.27, 0.15, -1.5);
            let (keypoints, data) = world.observe(&mut rng, &truth, 5);
            let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
            let frame = Frame { timestamp: 0.0, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
            let top = map.retrieve_ranked(&frame.retrieval_query(), 5, 0..0, crate::map::Ranking::Words).expect("top");
            let refined = loc.model_pose(&frame, &top, 0..0, &mut Timings::default()).expect("valid");
            let decided = loc.decided_pose(model, &frame, &top, 0..0, &mut Timings::default()).expect("valid");
            loc.accepted.lock().expect("not poisoned").clear();
            let (Ok(r), Ok(d)) = (refined.1, decided.1) else { continue };
            let error = |e: &Estimate| (truth.inverse() * e.world_from_cam).log().norm();
            before.push(error(&d));
            after.push(error(&r));
            assert!(correction(&d.world_from_cam, &r.world_from_cam, &d.covariance).1 <= CHI2_6_95, "frame {i}");
            assert_eq!(r.covariance, d.covariance, "frame {i}: the covariance is the solve's");
            moved += usize::from(r.world_from_cam != d.world_from_cam);
        }
        assert!(before.len() >= 10 && moved >= before.len() / 2, "{} answered, {moved} refined", before.len());
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean(&after) < mean(&before), "refined {:.5} against {:.5}", mean(&after), mean(&before));
    }

    fn median(mut v: Vec<f64>) -> f64 {
        crate::stats::median(&mut v, crate::stats::EvenMedian::Upper).expect("not empty")
    }

    /// Keyframes too close together to triangulate from give a model of no points: a model
    /// localizer is refused at once, naming the locator, instead of losing every frame; the
    /// paper's locator still serves the map (it triangulates nothing either, but localizes a
    /// keyframe's own view against its group).
    #[test]
    fn a_model_too_small_to_place_a_frame_refuses_the_model_locator() {
        let (_, map, _) = fixture::scene(40, false);
        let still: Vec<crate::map::Keyframe> = map
            .keyframes
            .iter()
            .take(6)
            .map(|k| crate::map::Keyframe { world_from_cam: map.keyframes[0].world_from_cam, ..k.clone() })
            .collect();
        let kind = crate::map::RetrievalKind::Bow { branching: 4, depth: 2 };
        let still = crate::map::Map::build(map.camera, still, None, kind, 0).expect("valid map");
        let still = still.with_model(&crate::map::ModelOptions::default()).expect("builds");
        assert!(still.model.as_ref().is_some_and(|m| m.len() < LocalizerOptions::default().min_correspondences));
        let still = Arc::new(still);
        let err = Localizer::new(Arc::clone(&still), LocalizerOptions::default()).err().expect("refused");
        assert!(err.to_string().starts_with("locator: the map's 3D model has"), "{err}");
        let paper = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
        assert!(Localizer::new(still, paper).is_ok());
    }

    /// On the synthetic scene the model locator is at least as accurate as the paper's, with
    /// more inliers; the map's stored model and one built by the localizer give the same poses.
    #[test]
    fn model_locator_matches_or_beats_the_paper() {
        let paper = run(Locator::Paper, false);
        let model = run(Locator::Model, true);
        let (pe, me) = (median(paper.iter().map(|r| r.0).collect()), median(model.iter().map(|r| r.0).collect()));
        let (pi, mi) =
            (median(paper.iter().map(|r| r.1 as f64).collect()), median(model.iter().map(|r| r.1 as f64).collect()));
        assert!(model.iter().all(|r| r.0 < 0.05), "{model:?}");
        assert!(me <= pe.max(0.005) && mi >= pi, "paper {pe} m / {pi}, model {me} m / {mi}");
        assert_eq!(run(Locator::Model, false), model);
    }

    /// A frame whose best-ranked keyframe's matches are all wrong (clutter: copies of that
    /// keyframe's descriptors at random pixels) and swamp the union (a RANSAC budget too small
    /// for its inlier ratio): neither hypothesis is accepted, and the next retrieved
    /// keyframe's matches alone localize it.
    const CLUTTER_COPIES: usize = 1;

    #[test]
    fn a_lower_ranked_keyframe_localizes_what_the_union_and_the_best_ranked_cannot() {
        let (world, map, _) = fixture::scene(40, false);
        let map = map.with_model(&crate::map::ModelOptions::default()).expect("model");
        let (wrong, right) = (39, 10);
        let truth = walk(1.0, 0.05, -1.5);
        let mut rng = SplitMix64::new(5);
        let (mut keypoints, mut data) = world.observe(&mut rng, &truth, 3);
        let true_keypoints = keypoints.len();
        let model = map.model.as_ref().expect("model");
        for _ in 0..CLUTTER_COPIES {
            let kf = &map.keyframes[wrong];
            let crate::map::DescriptorSet::Binary { data: kf_data, .. } = &kf.descriptors else { panic!("binary") };
            for (i, id) in model.point_ids[wrong].iter().enumerate() {
                if id.is_some() {
                    keypoints.push(nalgebra::Vector2::new(640.0 * rng.uniform(), 480.0 * rng.uniform()));
                    data.extend_from_slice(&kf_data[i * 32..(i + 1) * 32]);
                }
            }
        }
        eprintln!("{} keypoints, {true_keypoints} true", keypoints.len());
        let mut options = LocalizerOptions { locator: Locator::Model, ..LocalizerOptions::default() };
        options.pnp.ransac.min_iterations = 20;
        options.pnp.ransac.max_iterations = 20;
        let loc = Localizer::new(Arc::new(map), options).expect("localizer");
        let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
        let frame = Frame { timestamp: 0.0, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
        let (keyframe, pose, inliers) =
            loc.model_pose(&frame, &[wrong, right], 0..0, &mut crate::localizer::Timings::default()).expect("valid");
        let pose = pose.expect("localized");
        assert_eq!(keyframe, right);
        assert!((pose.world_from_cam.translation - truth.translation).norm() < 0.05, "{inliers} inliers");
    }

    /// Step 11: keyframes that see another part of the scene ranked first (refused), the
    /// right ones next: the answer is the next keyframes' own, bit for bit, with a note; the
    /// right ones first: their answer, no note; both sets refused: the first refusal; a
    /// ranking no longer than `top_k`: the model locator on it.
    #[test]
    fn the_next_keyframes_of_the_ranking_answer_what_the_first_refuse() {
        let (world, map, seen) = fixture::scene(40, false);
        let map = map.with_model(&crate::map::ModelOptions::default()).expect("model");
        let truth = walk(1.0, 0.05, -1.5);
        let mut rng = SplitMix64::new(5);
        let (all_keypoints, all_data) = world.observe(&mut rng, &truth, 3);
        // the query sees only landmarks that the keyframes ranked first (29–33, 35–39) do not
        let (far, also_far, right): (Vec<usize>, Vec<usize>, Vec<usize>) =
            ((35..40).collect(), (29..34).collect(), (8..13).collect());
        let hidden: std::collections::HashSet<usize> =
            far.iter().chain(&also_far).flat_map(|&j| seen[j].iter().copied()).collect();
        let (mut keypoints, mut data) = (Vec::new(), Vec::new());
        for (i, landmark) in fixture::visible(&world, &truth).into_iter().enumerate() {
            if !hidden.contains(&landmark) {
                keypoints.push(all_keypoints[i]);
                data.extend_from_slice(&all_data[i * 32..(i + 1) * 32]);
            }
        }
        assert!(keypoints.len() >= 40, "{} keypoints", keypoints.len());
        let options = LocalizerOptions { locator: Locator::Model, ..LocalizerOptions::default() };
        let k = options.top_k;
        let loc = Localizer::new(Arc::new(map), options).expect("localizer");
        let descriptors = crate::matching::Descriptors::Binary { data: &data, width: 32 };
        let frame = Frame { timestamp: 0.0, keypoints: &keypoints, descriptors, global: None, pixel_sigmas: None };
        let timings = &mut crate::localizer::Timings::default();
        assert_eq!(k, far.len());
        let alone = |top: &[usize]| loc.model_pose(&frame, top, 0..0, &mut crate::localizer::Timings::default());
        let (refusal, answer) = (alone(&far).expect("valid"), alone(&right).expect("valid"));
        assert!(refusal.1.is_err() && alone(&also_far).expect("valid").1.is_err(), "the far keyframes must refuse");
        let pose = answer.1.as_ref().expect("the right keyframes localize");
        assert!((pose.world_from_cam.translation - truth.translation).norm() < 0.05);

        let (found, note) =
            loc.ranked_model_pose(&frame, &[far.clone(), right.clone()].concat(), 0..0, timings).expect("valid");
        assert_eq!(found, answer);
        let note = note.expect("a note");
        assert!(note.contains(&format!("the first {k} gave no accepted pose")), "{note}");

        let first =
            loc.ranked_model_pose(&frame, &[right.clone(), far.clone()].concat(), 0..0, timings).expect("valid");
        assert_eq!(first, (answer, None));
        let both = loc.ranked_model_pose(&frame, &[far.clone(), also_far].concat(), 0..0, timings).expect("valid");
        assert_eq!(both, (refusal, None));
        let short = loc.ranked_model_pose(&frame, &right[..3], 0..0, timings).expect("valid");
        assert_eq!(short, (alone(&right[..3]).expect("valid"), None));
    }

    #[test]
    fn model_locator_is_identical_with_one_or_two_threads() {
        let one = with_parallelism(&Parallelism::Threads(NonZero::new(1).expect("1")), || run(Locator::Model, true));
        let two = with_parallelism(&Parallelism::Threads(NonZero::new(2).expect("2")), || run(Locator::Model, true));
        let bits = |v: &[(f64, usize)]| v.iter().map(|r| (r.0.to_bits(), r.1)).collect::<Vec<_>>();
        assert_eq!(bits(&one), bits(&two));
    }

    /// The fixture's two passes of 30 keyframes 0.5 m apart with a 3D model whose pairs reach
    /// 0.3 m (so the passes share no point), and a model localizer on it.
    fn two_passes_with_model() -> (Arc<crate::map::Map>, Localizer) {
        let (_, map, _) = fixture::scene(30, true);
        let model_options = crate::map::ModelOptions { max_distance_m: 0.3, ..Default::default() };
        let map = Arc::new(map.with_model(&model_options).expect("model"));
        let options = LocalizerOptions { locator: Locator::Model, ..LocalizerOptions::default() };
        let loc = Localizer::new(Arc::clone(&map), options).expect("localizer");
        (map, loc)
    }

    /// Guided matching searched from the keypoints' side gives the correspondences of a
    /// brute-force search from each point's side (every keypoint within r of its projection,
    /// the smallest (distance, keypoint) at most τ), at poses on and off the keyframes, with
    /// keypoints moved onto the circle of radius r and beyond the image.
    #[test]
    fn guided_matches_equal_a_search_from_every_point() {
        let (map, loc) = two_passes_with_model();
        let model = map.model.as_ref().expect("model");
        let r = loc.options.guided_radius_px;
        let mut rng = SplitMix64::new(8);
        let mut compared = 0;
        for k in [3, 15, 27, 40] {
            let kf = &map.keyframes[k];
            let inverse = kf.world_from_cam.inverse();
            // keypoints: the keyframe's, some moved r from a point's projection (the boundary,
            // up to rounding), one far outside the image
            let mut keypoints = kf.keypoints.clone();
            for (j, kp) in keypoints.iter_mut().enumerate().take(40) {
                if let Some(uv) = project_in_front(&map.camera, &inverse, &model.points[j % model.len()]) {
                    *kp = uv + Vector2::new(r, 0.0);
                }
            }
            keypoints[41] = Vector2::new(-1e4, 3e4);
            // keypoints 50..70 copy 70..90 a pixel away, with their descriptors: points with
            // two keypoints at the same distance (ties broken by the lower keypoint)
            let crate::matching::Descriptors::Binary { data, width } = kf.descriptors.view() else {
                panic!("binary fixture")
            };
            let mut data = data.to_vec();
            for j in 50..70 {
                keypoints[j] = keypoints[j + 20] + Vector2::new(1.0, 0.0);
                data.copy_within((j + 20) * width..(j + 21) * width, j * width);
            }
            let frame = Frame {
                timestamp: 0.0,
                keypoints: &keypoints,
                descriptors: crate::matching::Descriptors::Binary { data: &data, width },
                global: None,
                pixel_sigmas: None,
            };
            let candidates = points_seen_by(model, &near_keyframes(&loc, &kf.world_from_cam, &(0..0)), None);
            for (shift, tau) in [(0.0, 64.0), (0.0, 256.0), (0.02, 64.0), (0.05, 40.0)] {
                let step = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * shift;
                let pose =
                    SE3 { rotation: kf.world_from_cam.rotation, translation: kf.world_from_cam.translation + step };
                let inverse = pose.inverse();
                let brute: Vec<Correspondence> = candidates
                    .iter()
                    .filter_map(|&p| {
                        let uv = project_in_front(&map.camera, &inverse, &model.points[p])?;
                        (0..keypoints.len())
                            .filter(|&q| (keypoints[q] - uv).norm() <= r)
                            .map(|q| (model.descriptors.view().distance(p, &frame.descriptors, q), q))
                            .filter(|&(d, _)| d <= tau)
                            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                            .map(|(distance, query)| Correspondence { query, point: p, distance })
                    })
                    .collect();
                let expected = one_to_one(brute);
                assert!(!expected.is_empty());
                assert_eq!(loc.guided_matches(&frame, model, &pose, tau, &candidates), expected, "keyframe {k}");
                compared += expected.len();
            }
        }
        assert!(compared > 100, "{compared}");
    }

    /// Held out: no correspondence (retrieved or guided) uses a point that an excluded
    /// keyframe observes. Two passes whose keyframes are not paired (0.5 m apart, pairs up
    /// to 0.3 m), so the second pass's points stay usable when the first pass's block around
    /// the held-out keyframe is excluded: it is localized from them; with every keyframe but
    /// one excluded no point is usable and it is not.
    #[test]
    fn held_out_keyframes_do_not_leak() {
        let (map, mut loc) = two_passes_with_model();
        let model = map.model.as_ref().expect("model");
        let (k, excluded) = (15, 9..22);
        let kf = &map.keyframes[k];
        let frame = Frame {
            timestamp: 0.0,
            keypoints: &kf.keypoints,
            descriptors: kf.descriptors.view(),
            global: None,
            pixel_sigmas: None,
        };
        let usable = usable_points(model, &excluded).expect("some excluded");
        assert!(usable.iter().any(|u| !u) && usable.iter().any(|u| *u));
        let top = map.retrieve_top(&frame.retrieval_query(), 5, excluded.clone()).expect("retrieves");
        assert!(top.iter().all(|t| !excluded.contains(t)));
        let first = one_to_one(loc.retrieved_matches(&frame, model, &top, Some(&usable)).expect("matches").concat());
        let nearby = points_seen_by(model, &near_keyframes(&loc, &kf.world_from_cam, &excluded), Some(&usable));
        let guided = loc.guided_matches(&frame, model, &kf.world_from_cam, 64.0, &nearby);
        assert!(!first.is_empty() && !guided.is_empty(), "{} {}", first.len(), guided.len());
        for c in first.iter().chain(&guided) {
            assert!(model.observers(c.point).iter().all(|o| !excluded.contains(o)), "point {} leaks", c.point);
        }
        let (pose, inliers) = loc.localize_held_out(k, excluded).expect("valid").expect("localized");
        assert!((pose.world_from_cam.translation - kf.world_from_cam.translation).norm() < 0.05);
        assert!((MIN_ACCEPTED_INLIERS..=kf.keypoints.len()).contains(&inliers), "{inliers}");
        assert!(loc.localize_held_out(35, 1..60).expect("valid").is_none());
    }
}
