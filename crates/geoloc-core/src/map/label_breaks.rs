//! Jumps in the labels, found from the images and repaired before the labels' adjustment.
//!
//! The adjustment ([`crate::map::Map::with_adjusted_labels`]) refines: its tracks are matched
//! between keyframes the labels place near each other, checked against the labels' epipolar
//! geometry (12 px), and triangulated from the labels. A run of labels displaced by more than
//! that tolerates — a SLAM system's relocalization jump, a glitch of the motion capture — is an
//! island: its keyframes match among themselves only, and the adjustment sees no conflict (a
//! synthetic run of 12 of 160 labels moved by 0.39 m / 10° stayed 0.45 m / 10° off, no run in
//! the label report, answers beside it 0.40 m off).
//!
//! A **break** is a pair of consecutive keyframes (capture order) whose descriptor matches an
//! essential matrix explains — RANSAC from the images alone ([`verify_two_view`], 2 px), at
//! least [`BREAK_MIN_INLIERS`] inliers — while the labels' epipolar geometry keeps fewer than
//! 1/[`BREAK_RATIO`] as many at the adjustment's 12 px. (On 7-Scenes the labels keep at least
//! as many as the essential matrix between every pair of consecutive frames of 0–699: no
//! break. At 2 px they would not: 68 colour frames repeat their predecessor while the labels
//! move.) Two views cannot check the length of the labels' step: a jump along the epipolar
//! geometry passes.
//!
//! The breaks cut the keyframes into segments; the longest is held and the others are placed
//! from it outwards ([`repaired_start`]). A segment's keyframes, from its placed side, up to
//! [`REPLACE_WINDOW`] of them, are located by PnP (RANSAC, [`solve_pnp`]) against the points
//! triangulated from the placed keyframes within [`REPLACE_WINDOW`] of the boundary, each
//! answer P_k giving a correction C_k = P_k L_k⁻¹ in the world frame. The nearest
//! [`MIN_AGREEING`] must agree (within [`AGREE_M`] / [`AGREE_DEG`]) on a correction larger than
//! that agreement (smaller, it is the adjustment's work); the keyframes up to the first that
//! disagrees form the part re-placed, L'_k = C L_k, with C the correction most of them agree
//! on — when it reconciles the labels with the images across the break (the pair is no break
//! at the new poses). The rest of the segment is tried again from its new placed side: a jump
//! the check missed splits it there. A segment whose pair across the boundary is no break is
//! placed as it is. The re-placed poses are the adjustment's start, and its tracks are matched
//! and triangulated from them; the labels stay its priors, whose robust kernel lets the
//! displaced ones go. A segment the images cannot place keeps its labels; its break stays in
//! the report. Which side of a break is right is decided by length.

use std::ops::Range;

use nalgebra::Vector6;

use super::{ADJUSTMENT_EPIPOLAR_PX, Keyframe, Map, ModelOptions, SceneModel};
use crate::error::{GeolocError, Result};
use crate::essential::{TwoViewOptions, verify_two_view};
use crate::lie::{SE3, se3};
use crate::matching::{MatchOptions, epipolar_filter, match_descriptors};
use crate::parallel::map_indices;
use crate::pnp::{MIN_POINTS_RANSAC, PnpOptions, solve_pnp};

/// Fewest essential-matrix inliers of a break: the images must agree with each other.
pub const BREAK_MIN_INLIERS: usize = 30;
/// A break's labels' epipolar geometry keeps fewer than 1/`BREAK_RATIO` of the essential
/// matrix's inliers.
pub const BREAK_RATIO: f64 = 3.0;
/// Placed keyframes within this many of a segment (capture order) give the points it is
/// located against.
pub const REPLACE_WINDOW: usize = 30;
/// Two corrections agree within this translation (m) …
pub const AGREE_M: f64 = 0.05;
/// … and this rotation (degrees).
pub const AGREE_DEG: f64 = 2.0;
/// Fewest located keyframes that agree on a segment's correction.
pub const MIN_AGREEING: usize = 2;

/// A break in the labels between keyframes `at − 1` and `at` (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LabelBreak {
    /// The keyframe after the break.
    pub at: usize,
    /// Descriptor matches of the two keyframes.
    pub matches: usize,
    /// Of them, within the labels' epipolar geometry ([`ADJUSTMENT_EPIPOLAR_PX`]).
    pub label_inliers: usize,
    /// Of them, inliers of the essential matrix the images give.
    pub image_inliers: usize,
    /// Angle between the labels' relative rotation and the essential matrix's (degrees),
    /// reported, not tested: between consecutive frames little parallax leaves the essential
    /// matrix's rotation uncertain by degrees (7-Scenes: up to 2° between frames the labels
    /// place correctly).
    pub rotation_deg: f64,
}

/// Keyframes between breaks, outside the held (longest) segment, and how the images re-placed
/// them (see the module doc): a part re-placed by one correction, or the rest of a segment the
/// images could not place.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LabelSegment {
    /// First keyframe.
    pub start: usize,
    /// One past the last keyframe.
    pub end: usize,
    /// log(C)^∨ (world frame, translation first) of the correction that moved its start
    /// poses, L'_k = C L_k; None when the images could not place it (its labels are kept).
    pub correction: Option<[f64; 6]>,
    /// Keyframes located.
    pub localized: usize,
    /// Of them, those that agree on the correction.
    pub agreeing: usize,
}

/// The breaks between consecutive keyframes of `map` whose poses are `poses` (see the module
/// doc), in capture order.
///
/// # Errors
/// `poses` not one per keyframe; as descriptor matching and [`verify_two_view`] (descriptors
/// and keypoints the map checked).
pub fn find_breaks(map: &Map, poses: &[SE3]) -> Result<Vec<LabelBreak>> {
    if poses.len() != map.keyframes.len() {
        return Err(GeolocError::invalid(
            "poses",
            format!("{} poses for {} keyframes", poses.len(), map.keyframes.len()),
        ));
    }
    let found = map_indices(map.keyframes.len().saturating_sub(1), 8, |i| broken_pair(map, poses, i));
    Ok(found.into_iter().collect::<Result<Vec<_>>>()?.into_iter().flatten().collect())
}

/// Whether keyframes `i` and `i + 1` of `map`, at `poses`, make a break (see the module doc).
fn broken_pair(map: &Map, poses: &[SE3], i: usize) -> Result<Option<LabelBreak>> {
    Ok(disagreeing_pair(map, poses, i, i + 1)?.map(|d| LabelBreak {
        at: i + 1,
        matches: d.matches,
        label_inliers: d.label_inliers,
        image_inliers: d.image_inliers,
        rotation_deg: d.rotation_deg,
    }))
}

/// How the images and the poses of two keyframes disagree (see [`disagreeing_pair`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairDisagreement {
    /// Descriptor matches of the two keyframes.
    pub matches: usize,
    /// Of them, within the poses' epipolar geometry ([`ADJUSTMENT_EPIPOLAR_PX`]).
    pub label_inliers: usize,
    /// Of them, inliers of the essential matrix the images give.
    pub image_inliers: usize,
    /// Angle between the poses' relative rotation and the essential matrix's (degrees).
    pub rotation_deg: f64,
}

/// Whether keyframes `a` and `b` of `map` disagree with their poses `poses`: an essential
/// matrix explains at least [`BREAK_MIN_INLIERS`] of their descriptor matches (the images
/// agree with each other) while the poses' epipolar geometry keeps fewer than
/// 1/[`BREAK_RATIO`] as many at [`ADJUSTMENT_EPIPOLAR_PX`]. The essential matrix runs only
/// where the poses lose most matches.
pub fn disagreeing_pair(map: &Map, poses: &[SE3], a: usize, b: usize) -> Result<Option<PairDisagreement>> {
    let (ka, kb) = (&map.keyframes[a], &map.keyframes[b]);
    let matches = match_descriptors(&ka.descriptors.view(), &kb.descriptors.view(), &MatchOptions::default())?;
    if matches.len() < BREAK_MIN_INLIERS {
        return Ok(None);
    }
    let (pa, pb) = (&poses[a], &poses[b]);
    let within = epipolar_filter(&map.camera, pa, pb, &ka.keypoints, &kb.keypoints, &matches, ADJUSTMENT_EPIPOLAR_PX)?;
    let label_inliers = within.iter().filter(|w| **w).count();
    // the essential matrix only where the poses lose most matches (never on 7-Scenes)
    if label_inliers as f64 * BREAK_RATIO >= matches.len() as f64 {
        return Ok(None);
    }
    let two_view = verify_two_view(&map.camera, &ka.keypoints, &kb.keypoints, &matches, &TwoViewOptions::default())?;
    let image_inliers = two_view.inliers;
    let disagree = image_inliers >= BREAK_MIN_INLIERS && (label_inliers as f64) * BREAK_RATIO < image_inliers as f64;
    let rotation_deg = two_view.b_from_a.rotation.distance(&(pb.inverse() * *pa).rotation).to_degrees();
    Ok(disagree.then_some(PairDisagreement { matches: matches.len(), label_inliers, image_inliers, rotation_deg }))
}

/// The start poses of the labels' adjustment of `map` (whose keyframes' poses are the labels
/// `labels`): the labels with the keyframes that [`find_breaks`]' breaks cut off re-placed
/// where the images place them (see the module doc); the breaks; and the segments re-placed.
///
/// # Errors
/// As [`find_breaks`] (`labels` not one per keyframe: named `poses`), [`SceneModel::build`]
/// and [`solve_pnp`].
pub fn repaired_start(map: &Map, labels: &[SE3]) -> Result<(Vec<SE3>, Vec<LabelBreak>, Vec<LabelSegment>)> {
    let breaks = find_breaks(map, labels)?;
    let mut start = labels.to_vec();
    if breaks.is_empty() {
        return Ok((start, breaks, Vec::new()));
    }
    let bounds: Vec<usize> = std::iter::once(0).chain(breaks.iter().map(|b| b.at)).chain([labels.len()]).collect();
    let segments: Vec<Range<usize>> = bounds.windows(2).map(|w| w[0]..w[1]).collect();
    // the longest segment is held (ties: the first); the others are placed from it outwards
    let held = (0..segments.len()).fold(0, |best, s| if segments[s].len() > segments[best].len() { s } else { best });
    let mut placed = vec![false; labels.len()];
    placed[segments[held].clone()].iter_mut().for_each(|p| *p = true);
    let mut replaced = Vec::new();
    // towards the end, then towards the beginning: each segment borders a placed one
    let after = segments[held + 1..].iter().map(|s| (s.clone(), Side::Before));
    let before = segments[..held].iter().rev().map(|s| (s.clone(), Side::After));
    for (mut segment, side) in after.chain(before) {
        // a segment may hold keyframes on both sides of a jump the epipolar check missed:
        // each pass places the part next to the placed side, the rest is tried again
        while !segment.is_empty() {
            // the placed keyframe across the boundary, and the pair (pair, pair + 1) it makes
            let (boundary, pair) = match side {
                Side::Before => (segment.start - 1, segment.start - 1),
                Side::After => (segment.end, segment.end - 1),
            };
            if !placed[boundary] {
                // its neighbour could not be placed: neither can it
                replaced.push(LabelSegment::kept(&segment, 0, 0));
                break;
            }
            if broken_pair(map, &start, pair)?.is_none() {
                // consistent with its placed neighbour: placed as it is
                placed[segment.clone()].iter_mut().for_each(|p| *p = true);
                break;
            }
            let Some(PlacedPart { part, correction, localized, agreeing }) =
                placed_part(map, &start, &placed, &segment, side)?
            else {
                replaced.push(LabelSegment::kept(&segment, 0, 0));
                break;
            };
            let moved: Vec<SE3> = start[part.clone()].iter().map(|p| correction * *p).collect();
            let mut trial = start.clone();
            trial[part.clone()].copy_from_slice(&moved);
            if broken_pair(map, &trial, pair)?.is_some() {
                // the correction does not reconcile the labels with the images there
                replaced.push(LabelSegment::kept(&segment, localized, agreeing));
                break;
            }
            start = trial;
            placed[part.clone()].iter_mut().for_each(|p| *p = true);
            replaced.push(LabelSegment {
                start: part.start,
                end: part.end,
                correction: Some(correction.log().into()),
                localized,
                agreeing,
            });
            segment = match side {
                Side::Before => part.end..segment.end,
                Side::After => segment.start..part.start,
            };
        }
    }
    replaced.sort_by_key(|r| r.start);
    Ok((start, breaks, replaced))
}

/// Which side of a segment its placed neighbour lies on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    /// The keyframe before the segment is placed.
    Before,
    /// The keyframe after it.
    After,
}

impl LabelSegment {
    /// Keyframes `segment` left at their labels, after `localized` were located and `agreeing`
    /// agreed.
    fn kept(segment: &Range<usize>, localized: usize, agreeing: usize) -> Self {
        Self { start: segment.start, end: segment.end, correction: None, localized, agreeing }
    }
}

/// What [`placed_part`] found: the keyframes `part` that `correction` re-places, and how many
/// keyframes were located and agreed on it.
struct PlacedPart {
    part: Range<usize>,
    correction: SE3,
    localized: usize,
    agreeing: usize,
}

/// The part of `segment` next to its placed neighbour (on `side`) that one correction
/// places, that correction, and how many keyframes were located and agreed: the segment's
/// keyframes from that side, up to [`REPLACE_WINDOW`] of them, located by PnP against the
/// points of the placed keyframes within [`REPLACE_WINDOW`] of the boundary (at their `start`
/// poses); the part runs from the boundary to the last keyframe before the first located one
/// that disagrees with the correction the nearest [`MIN_AGREEING`] agree on — the whole
/// segment if none does. None when fewer than [`MIN_AGREEING`] agree, or the correction is
/// within the agreement (no jump: the adjustment's work).
fn placed_part(
    map: &Map,
    start: &[SE3],
    placed: &[bool],
    segment: &Range<usize>,
    side: Side,
) -> Result<Option<PlacedPart>> {
    let n = start.len();
    let (window, order): (Vec<usize>, Vec<usize>) = match side {
        Side::Before => (
            (segment.start.saturating_sub(REPLACE_WINDOW)..segment.start).filter(|&k| placed[k]).collect(),
            segment.clone().take(REPLACE_WINDOW).collect(),
        ),
        Side::After => (
            (segment.end..(segment.end + REPLACE_WINDOW).min(n)).filter(|&k| placed[k]).collect(),
            segment.clone().rev().take(REPLACE_WINDOW).collect(),
        ),
    };
    if window.len() < 2 {
        return Ok(None);
    }
    let keyframes: Vec<Keyframe> =
        window.iter().map(|&k| Keyframe { world_from_cam: start[k], ..map.keyframes[k].clone() }).collect();
    let model = SceneModel::build(&map.camera, &keyframes, None, &ModelOptions::default())?;
    if model.len() < MIN_POINTS_RANSAC {
        return Ok(None);
    }
    let mut located: Vec<(usize, SE3)> = Vec::new();
    for &k in &order {
        if let Some(c) = located_correction(map, &model, start, k)? {
            located.push((k, c));
        }
    }
    let first: Vec<SE3> = located.iter().take(MIN_AGREEING).map(|(_, c)| *c).collect();
    let (Some(reference), agreeing) = agreed_correction(&first) else {
        return Ok(None);
    };
    if agreeing < MIN_AGREEING || agree(&reference, &SE3::identity()) {
        return Ok(None);
    }
    let last = located.iter().position(|(_, c)| !agree(c, &reference));
    let inside: Vec<SE3> = located[..last.unwrap_or(located.len())].iter().map(|(_, c)| *c).collect();
    let (Some(correction), agreeing) = agreed_correction(&inside) else {
        return Ok(None);
    };
    let part = match (last.map(|l| located[l].0), side) {
        (None, _) => segment.clone(),
        (Some(k), Side::Before) => segment.start..k,
        (Some(k), Side::After) => k + 1..segment.end,
    };
    Ok((!part.is_empty()).then_some(PlacedPart { part, correction, localized: located.len(), agreeing }))
}

/// The correction P_k start_k⁻¹ of keyframe `k` that its PnP pose P_k against `model` gives
/// (its descriptors matched to the points'), None when PnP does not accept a pose.
pub(super) fn located_correction(map: &Map, model: &SceneModel, start: &[SE3], k: usize) -> Result<Option<SE3>> {
    let kf = &map.keyframes[k];
    let matches = match_descriptors(&kf.descriptors.view(), &model.descriptors.view(), &MatchOptions::default())?;
    if matches.len() < MIN_POINTS_RANSAC {
        return Ok(None);
    }
    let points: Vec<_> = matches.iter().map(|m| model.points[m.b]).collect();
    let pixels: Vec<_> = matches.iter().map(|m| kf.keypoints[m.a]).collect();
    let pose = solve_pnp(&map.camera, &points, &pixels, None, None, &PnpOptions::default())?;
    Ok(pose.success.then(|| pose.world_from_cam * start[k].inverse()))
}

/// Whether two corrections agree (within [`AGREE_M`] / [`AGREE_DEG`]).
pub(super) fn agree(a: &SE3, b: &SE3) -> bool {
    let d: Vector6<f64> = (a.inverse() * *b).log();
    se3::rho(&d).norm() <= AGREE_M && se3::phi(&d).norm() <= AGREE_DEG.to_radians()
}

/// The correction most of `corrections` agree with (ties: the first), if at least
/// [`MIN_AGREEING`] and half of them do, and how many agree with it.
fn agreed_correction(corrections: &[SE3]) -> (Option<SE3>, usize) {
    let votes: Vec<usize> = corrections.iter().map(|a| corrections.iter().filter(|b| agree(a, b)).count()).collect();
    let Some((best, count)) =
        votes.iter().copied().enumerate().fold(None, |best: Option<(usize, usize)>, (i, v)| match best {
            Some((_, b)) if b >= v => best,
            _ => Some((i, v)),
        })
    else {
        return (None, 0);
    };
    let enough = count >= MIN_AGREEING && 2 * count >= corrections.len();
    (enough.then_some(corrections[best]), count)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::model::fixture;
    use crate::testing::SplitMix64;

    /// The labels of a scene with keyframes 15–21 displaced by `bump`.
    fn displaced(map: &Map, bump: &SE3) -> Vec<SE3> {
        map.poses().iter().enumerate().map(|(k, p)| if (15..22).contains(&k) { *bump * *p } else { *p }).collect()
    }

    /// Exact labels have no break and start where they are, bit for bit; a run of 7 of 60
    /// labels displaced by 0.3 m / 8° breaks where the images contradict its labels (at its end: where it begins
    /// the jump lies along the epipolar geometry in this scene), and is re-placed — the run
    /// alone, within 2 cm / 0.5° of the truth (PnP against the next keyframes' points).
    #[test]
    fn a_displaced_run_is_found_and_re_placed_and_exact_labels_are_left_alone() {
        let (_, map, _) = fixture::scene(60, false);
        let truth = map.poses();
        assert!(find_breaks(&map, &truth).expect("checks").is_empty());
        let err = repaired_start(&map, &truth[1..]).expect_err("one pose short");
        assert!(
            matches!(err, crate::error::GeolocError::InvalidInput { .. }) && err.to_string().contains("poses"),
            "{err}"
        );
        let (start, breaks, replaced) = repaired_start(&map, &truth).expect("repairs");
        assert!(breaks.is_empty() && replaced.is_empty());
        assert_eq!(start, truth);
        let bump = SE3::exp(&se3::twist(
            &nalgebra::Vector3::new(0.2, -0.15, 0.15),
            &nalgebra::Vector3::new(0.05, 0.12, -0.05),
        ));
        let labels = displaced(&map, &bump);
        let breaks = find_breaks(&map, &labels).expect("checks");
        assert!(!breaks.is_empty() && breaks.iter().all(|b| b.at == 15 || b.at == 22), "{breaks:?}");
        assert!(breaks.iter().all(|b| b.image_inliers >= BREAK_MIN_INLIERS && 3 * b.label_inliers < b.image_inliers));
        let (start, _, replaced) = repaired_start(&map, &labels).expect("repairs");
        let [part] = replaced.as_slice() else { panic!("{replaced:?}") };
        assert_eq!((part.start, part.end), (15, 22), "{part:?}");
        for (k, (s, t)) in start.iter().zip(&truth).enumerate() {
            let d = (t.inverse() * *s).log();
            if (15..22).contains(&k) {
                assert!(se3::rho(&d).norm() < 0.02 && se3::phi(&d).norm() < 0.5f64.to_radians(), "{k}: {d}");
            } else {
                assert_eq!(*s, labels[k], "keyframe {k} outside the run is left as labelled");
            }
        }
    }

    /// A map built on those labels and adjusted keeps the breaks and the re-placed part in
    /// its label report, through its file; the run is adjusted to the truth.
    #[test]
    fn the_map_reports_the_breaks_and_keeps_them_in_its_file() {
        let (_, truth_map, _) = fixture::scene(60, false);
        let truth = truth_map.poses();
        let bump = SE3::exp(&se3::twist(
            &nalgebra::Vector3::new(0.2, -0.15, 0.15),
            &nalgebra::Vector3::new(0.05, 0.12, -0.05),
        ));
        let labels = displaced(&truth_map, &bump);
        let keyframes = truth_map
            .keyframes
            .iter()
            .zip(&labels)
            .map(|(kf, l)| Keyframe { world_from_cam: *l, ..kf.clone() })
            .collect();
        let kind = crate::map::RetrievalKind::Bow { branching: 8, depth: 3 };
        let map = Map::build(truth_map.camera, keyframes, None, kind, 1).expect("valid map");
        let adjusted = map.with_adjusted_labels(&crate::adjust::AdjustmentOptions::default()).expect("adjusts");
        let record = adjusted.labels.as_ref().expect("adjusted");
        assert!(!record.breaks.is_empty() && record.replaced.len() == 1, "{:?} {:?}", record.breaks, record.replaced);
        let poses = adjusted.poses();
        let worst = poses.iter().zip(&truth).map(|(a, t)| (a.inverse() * *t).translation.norm()).fold(0.0, f64::max);
        assert!(worst < 0.04, "the run is adjusted to the truth: {worst} m");
        let report = record.report_json();
        assert_eq!(report["breaks"].as_array().expect("breaks").len(), record.breaks.len());
        assert_eq!(report["replaced"][0]["start"], 15);
        let summary = record.summary();
        assert!(summary.contains("jump(s) in the labels the images show, re-placed: 15-21 by"), "{summary}");
        let back = Map::from_map_file(&adjusted.to_map_file("{}").expect("file")).expect("loads").0;
        assert_eq!(back.labels, adjusted.labels);
    }

    /// The agreed correction is the one with the most others within 5 cm / 2° (brute force),
    /// and none when fewer than two, or fewer than half, agree.
    #[test]
    fn the_agreed_correction_is_the_most_agreed_with() {
        let mut rng = SplitMix64::new(3);
        let centre = SE3::exp(&rng.twist(0.3, 0.2));
        let near: Vec<SE3> = (0..5).map(|_| centre * SE3::exp(&rng.twist(0.005, 0.002))).collect();
        let far: Vec<SE3> = (0..3).map(|_| SE3::exp(&rng.twist(0.5, 0.5))).collect();
        let all: Vec<SE3> = far.iter().chain(&near).copied().collect();
        let (chosen, count) = agreed_correction(&all);
        let chosen = chosen.expect("five agree");
        assert_eq!(count, all.iter().filter(|b| agree(&chosen, b)).count());
        assert!(all.iter().all(|a| all.iter().filter(|b| agree(a, b)).count() <= count));
        assert!(near.contains(&chosen));
        assert_eq!(agreed_correction(&far).0, None, "no two agree");
        let split: Vec<SE3> = near[..2].iter().chain(&far).copied().collect();
        assert_eq!(agreed_correction(&split).0, None, "two of five is not half");
        assert_eq!(agreed_correction(&[]), (None, 0));
    }
}
