//! The localizer on a simulated sequence: synthetic keyframes and features, clean and with
//! 20 % of frames given a gross geometric failure.
//!
//! The scene is wider than any one view (landmarks over 24 m across, each keyframe sees about
//! a third of them) and the vocabulary is fine enough that a word belongs to few landmarks,
//! so words discriminate: idf > 0 and BoW retrieval must find a nearby keyframe
//! (with every word in every keyframe every score was 0 and retrieval always said 0).

use std::sync::Arc;

use geoloc_core::GeolocError;
use geoloc_core::lie::SE3;
use geoloc_core::localizer::{Frame, Localization, Localizer, LocalizerOptions, Locator, Source, Timings};
use geoloc_core::map::{DescriptorSet, Keyframe, Map, MapNoise, RetrievalKind};
use geoloc_core::matching::Descriptors;
use geoloc_core::stats::chi2::CHI2_6_999;
use geoloc_core::testing::{self, LandmarkScene, SplitMix64};
use nalgebra::{Matrix6, Vector2};

const WIDTH: usize = testing::LANDMARK_DESCRIPTOR_BYTES;
/// Landmarks of the scene (about a third in view at a time).
const LANDMARKS: usize = 3000;
/// Retrieval is right when the retrieved keyframe is within this distance of the truth
/// (keyframes are 6 cm apart; the query path runs 15 cm beside theirs; keyframe 0, which
/// uninformative scores would return, is 0.2–2 m away).
const NEARBY_M: f64 = 0.4;
/// ... and the median retrieved keyframe is within this distance.
const NEARBY_MEDIAN_M: f64 = 0.2;

/// The camera path of these tests: [`testing::walk`] (the scene is [`LandmarkScene`]).
fn walk(t: f64, offset: f64) -> SE3 {
    testing::walk(t, offset, -1.5)
}

/// Keyframes every 0.1 s of the walk.
fn keyframes(world: &LandmarkScene, rng: &mut SplitMix64) -> Vec<Keyframe> {
    (0..60)
        .map(|i| {
            let pose = walk(i as f64 * 0.1, 0.0);
            let (keypoints, data) = world.observe(rng, &pose, 3);
            Keyframe {
                world_from_cam: pose,
                keypoints,
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect()
}

/// Per frame: the position error (∞ when lost), the source, the distance from the
/// retrieved keyframe to the truth, the bits of the pose and covariance, and the localization.
struct Run {
    errors: Vec<f64>,
    sources: Vec<Source>,
    retrieval_m: Vec<f64>,
    bits: Vec<u64>,
    results: Vec<Localization>,
}

fn run(corrupt_fraction: f64) -> Run {
    run_frames(corrupt_fraction, 90)
}

fn run_frames(corrupt_fraction: f64, frames: usize) -> Run {
    run_with_noise(corrupt_fraction, frames, MapNoise::default(), false)
}

/// The run on a map with `noise`; `single`: the motion history is forgotten before every frame.
fn run_with_noise(corrupt_fraction: f64, frames: usize, noise: MapNoise, single: bool) -> Run {
    run_with_jump(corrupt_fraction, frames, noise, single, usize::MAX)
}

/// ... and from frame `jump` on, the camera path 10 cm further to the side (a jump the motion
/// model does not predict).
fn run_with_jump(corrupt_fraction: f64, frames: usize, noise: MapNoise, single: bool, jump: usize) -> Run {
    let mut rng = SplitMix64::new(11);
    let world = LandmarkScene::new(&mut rng, LANDMARKS, 12.0);
    let keyframes = keyframes(&world, &mut rng);
    let kf_poses: Vec<SE3> = keyframes.iter().map(|k| k.world_from_cam).collect();
    let mut map =
        Map::build(world.camera, keyframes, None, RetrievalKind::Bow { branching: 8, depth: 4 }, 0).expect("valid map");
    map.noise = noise;
    let mut localizer = Localizer::new(Arc::new(map), LocalizerOptions::default()).expect("valid options");
    let mut out =
        Run { errors: Vec::new(), sources: Vec::new(), retrieval_m: Vec::new(), bits: Vec::new(), results: Vec::new() };
    let mut corrupt_rng = SplitMix64::new(5);
    for f in 0..frames {
        let t = 0.3 + f as f64 / 30.0;
        let truth = walk(t, if f >= jump { 0.25 } else { 0.15 });
        let (keypoints, mut data) = world.observe(&mut rng, &truth, 3);
        if f >= 5 && corrupt_rng.uniform() < corrupt_fraction {
            // a gross failure: descriptors shuffled between keypoints, so every match is wrong
            let n = keypoints.len();
            let mut shuffled = data.clone();
            for i in 0..n {
                let j = (corrupt_rng.next_u64() % n as u64) as usize;
                shuffled[i * WIDTH..(i + 1) * WIDTH].copy_from_slice(&data[j * WIDTH..(j + 1) * WIDTH]);
            }
            data = shuffled;
        }
        let frame = testing::landmark_frame(t, &keypoints, &data);
        if single {
            localizer.reset();
        }
        let r = localizer.localize(&frame).expect("valid frame");
        out.sources.push(r.source);
        out.errors
            .push(r.estimate.map_or(f64::INFINITY, |e| (e.world_from_cam.translation - truth.translation).norm()));
        out.retrieval_m.push((kf_poses[r.keyframe].translation - truth.translation).norm());
        if let Some(e) = r.estimate {
            out.bits.extend(e.world_from_cam.matrix().iter().chain(e.covariance.iter()).map(|v| v.to_bits()));
        }
        out.results.push(r);
    }
    out
}

/// The map noise a pose gets is C_map·max(1, n̄/n) at its support n: the frame's own PnP
/// inliers (single images: the covariance differs from the unscaled map's by exactly
/// (scale − 1)·C_map), and for a motion-only frame the last measurement's; the motion gate
/// keeps C_map unscaled (same decisions, same poses).
#[test]
#[allow(clippy::float_cmp)] // the factor is the same division either way: exact equality is the claim
fn the_map_noise_is_scaled_by_the_support_of_each_pose() {
    let c_map = Matrix6::from_diagonal(&nalgebra::Vector6::new(4e-4, 1e-4, 9e-4, 1e-5, 4e-5, 1e-5));
    let noise = |n_bar: f64| MapNoise { pose_covariance: c_map, holdout_inliers: n_bar, ..MapNoise::default() };
    let plain = run_with_noise(0.0, 20, noise(0.0), true);
    let supports: Vec<usize> = plain.results.iter().map(|r| r.inliers).collect();
    let mut sorted = supports.clone();
    sorted.sort_unstable();
    // n̄ between the frames' supports: some frames are scaled, some are not
    let n_bar = sorted[sorted.len() / 2] as f64 + 0.5;
    let scaled = run_with_noise(0.0, 20, noise(n_bar), true);
    let (mut up, mut same) = (0, 0);
    for (a, b) in plain.results.iter().zip(&scaled.results) {
        assert_eq!(a.source, Source::Geometric);
        assert_eq!(a.map_noise_scale, 1.0);
        let want = if (a.inliers as f64) < n_bar { n_bar / a.inliers as f64 } else { 1.0 };
        assert_eq!(b.map_noise_scale, want, "{} inliers", a.inliers);
        let (ca, cb) = (a.estimate.expect("localized").covariance, b.estimate.expect("localized").covariance);
        assert!((cb - ca - c_map * (want - 1.0)).amax() < 1e-15, "{} inliers: {}", a.inliers, cb - ca);
        if want > 1.0 { up += 1 } else { same += 1 }
    }
    assert!(up > 0 && same > 0, "{up} scaled, {same} not");
    // sequential, with gross failures: a motion-only frame keeps the last measurement's support
    let run = run_with_noise(0.2, 60, noise(1e5), false);
    let mut last = None;
    let mut motion = 0;
    for r in &run.results {
        match r.source {
            Source::Geometric | Source::Fused => last = Some(r.inliers),
            Source::Motion => motion += 1,
            Source::Lost => last = None,
        }
        let want = last.map_or(1.0, |n| 1e5 / n as f64);
        let got = if r.source == Source::Lost { 1.0 } else { want };
        assert_eq!(r.map_noise_scale, got, "{:?} {}", r.source, r.inliers);
    }
    assert!(motion > 0, "no motion-only frame");
    // the gate keeps C_map as it is: after a 10 cm jump the gate refuses the new poses, and a
    // support factor that would widen it 10¹⁰-fold changes nothing
    let tiny = |n_bar: f64| MapNoise { pose_covariance: c_map * 1e-9, holdout_inliers: n_bar, ..MapNoise::default() };
    let strict = run_with_jump(0.0, 40, tiny(0.0), false, 20);
    let gated = strict.results.iter().filter(|r| r.reason.contains("outside the motion gate")).count();
    let widened = run_with_jump(0.0, 40, tiny(1e12), false, 20);
    assert_eq!(strict.sources, widened.sources, "{gated} frames outside the gate");
    for (a, b) in strict.results.iter().zip(&widened.results) {
        assert_eq!(a.estimate.map(|e| e.world_from_cam.matrix()), b.estimate.map(|e| e.world_from_cam.matrix()));
    }
    assert!(gated > 0, "no frame outside the gate: the comparison shows nothing");
}

/// After a jump the motion model did not predict (10 cm to the side), the images' poses lie
/// outside the motion gate until they re-initialize the history; the prediction answered in
/// the meantime is the wrong one, and its covariance must hold the image's pose — here the
/// truth: every such answer covers it at 99.9 % (NEES of the true pose), where the
/// prediction's own covariance (centimetres) did not.
#[test]
fn a_prediction_the_images_contradict_is_answered_with_a_covariance_that_holds_both() {
    let run = run_with_jump(0.0, 40, MapNoise::default(), false, 20);
    let mut contradicted = 0;
    for (f, r) in run.results.iter().enumerate() {
        if !r.reason.contains("outside the motion gate") {
            continue;
        }
        contradicted += 1;
        let e = r.estimate.expect("the prediction is answered");
        let truth = walk(0.3 + f as f64 / 30.0, if f >= 20 { 0.25 } else { 0.15 });
        let delta = (e.world_from_cam.inverse() * truth).log();
        let nees = delta.dot(&(e.covariance.try_inverse().expect("invertible") * delta));
        assert!(nees < CHI2_6_999, "frame {f}: NEES {nees} of the true pose ({})", r.reason);
        assert!(r.reason.contains("holds both"), "{}", r.reason);
    }
    assert!(contradicted > 0, "no frame outside the gate: the test shows nothing");
}

fn median(v: &[f64]) -> f64 {
    geoloc_core::stats::median(&mut v.to_vec(), geoloc_core::stats::EvenMedian::Upper).expect("not empty")
}

#[test]
fn clean_sequence_is_localized_and_fused() {
    let Run { errors, sources, retrieval_m, .. } = run(0.0);
    eprintln!("clean median {:.2} mm, retrieval median {:.3} m", 1e3 * median(&errors), median(&retrieval_m));
    assert!(median(&errors) < 0.02, "median error {} m", median(&errors));
    assert!(sources[..2].iter().all(|s| *s == Source::Geometric));
    let fused = sources.iter().filter(|s| **s == Source::Fused).count();
    assert!(fused > 70, "{fused} fused of {}", sources.len());
    assert!(!sources.contains(&Source::Lost));
    // BoW retrieval finds a nearby keyframe for every clean frame
    let far = retrieval_m.iter().filter(|d| **d > NEARBY_M).count();
    assert_eq!(far, 0, "{far} frames retrieved a keyframe over {NEARBY_M} m away: {retrieval_m:?}");
    assert!(median(&retrieval_m) < NEARBY_MEDIAN_M, "median retrieval distance {}", median(&retrieval_m));
}

/// 20 % of frames with a gross failure of the geometric locator; the median error
/// stays within 1.2× of the clean run's (the motion model and the gate absorb them).
#[test]
fn gross_failures_are_absorbed_by_the_motion_model() {
    let clean = run(0.0);
    let corrupt = run(0.2);
    let motion = corrupt.sources.iter().filter(|s| **s == Source::Motion).count();
    eprintln!(
        "clean median {:.2} mm, 20 % corrupted median {:.2} mm, {motion} motion-only frames of {}",
        1e3 * median(&clean.errors),
        1e3 * median(&corrupt.errors),
        corrupt.sources.len()
    );
    assert!(motion >= 8, "{motion} frames fell back to the motion model");
    assert!(
        median(&corrupt.errors) <= 1.2 * median(&clean.errors),
        "{} vs clean {}",
        median(&corrupt.errors),
        median(&clean.errors)
    );
    assert!(corrupt.errors.iter().all(|e| e.is_finite()));
}

/// Same input, same bits: parallelism off, and on 1 and 2 threads (the map build's
/// vocabulary, the matching and the triangulation all run through parallel.rs).
#[test]
fn results_are_identical_for_any_parallelism() {
    use geoloc_core::parallel::{Parallelism, with_parallelism};
    use std::num::NonZero;
    let bits = |p: Parallelism| {
        with_parallelism(&p, || {
            let r = run_frames(0.2, 20);
            (r.bits, r.sources)
        })
    };
    let reference = bits(Parallelism::Off);
    assert!(!reference.0.is_empty());
    for n in [1, 2] {
        assert!(bits(Parallelism::Threads(NonZero::new(n).expect("n > 0"))) == reference, "{n} threads differ");
    }
}

/// The name of a named error.
fn name_of<T>(r: Result<T, GeolocError>) -> String {
    match r {
        Err(GeolocError::InvalidInput { name, .. } | GeolocError::NonFinite { name, .. }) => name,
        Err(other) => panic!("expected a named error, got {other:?}"),
        Ok(_) => panic!("expected a named error, got Ok"),
    }
}

/// The core refuses bad maps and frames with the argument's name.
#[test]
fn bad_maps_and_frames_are_refused_by_name() {
    let mut rng = SplitMix64::new(3);
    let world = LandmarkScene::new(&mut rng, LANDMARKS, 12.0);
    let kfs: Vec<Keyframe> = keyframes(&world, &mut rng).into_iter().take(5).collect();
    let bow = RetrievalKind::Bow { branching: 2, depth: 2 };
    let build =
        |kfs: Vec<Keyframe>, covs: Option<Vec<Matrix6<f64>>>, kind| Map::build(world.camera, kfs, covs, kind, 0);
    // a negative and a non-symmetric pose covariance
    let mut covs = vec![Matrix6::identity() * 1e-4; 5];
    covs[3][(2, 2)] = -1e-4;
    assert_eq!(name_of(build(kfs.clone(), Some(covs), bow)), "pose_covariances[3]");
    let mut covs = vec![Matrix6::identity() * 1e-4; 5];
    covs[1][(0, 1)] = 1e-5;
    assert_eq!(name_of(build(kfs.clone(), Some(covs), bow)), "pose_covariances[1]");
    assert_eq!(name_of(build(kfs.clone(), Some(vec![Matrix6::identity(); 4]), bow)), "pose_covariances");
    assert_eq!(name_of(build(kfs.clone(), None, RetrievalKind::Bow { branching: 2, depth: 100_000 })), "depth");
    assert_eq!(name_of(build(kfs.clone(), None, RetrievalKind::Global)), "global_descriptors");
    let mut bad = kfs.clone();
    bad[2].keypoints[0].x = f64::NAN;
    assert_eq!(name_of(build(bad, None, bow)), "keypoints[2]");
    let mut float = kfs.clone();
    for kf in &mut float {
        kf.descriptors = DescriptorSet::Float { data: vec![1.0; kf.keypoints.len() * 4], width: 4 };
        kf.global = Some(vec![1.0, 2.0]);
    }
    if let DescriptorSet::Float { data, .. } = &mut float[4].descriptors {
        data[5] = f32::INFINITY; // e.g. a float64 value beyond float32's range
    }
    assert_eq!(name_of(build(float.clone(), None, RetrievalKind::Global)), "descriptors[4]");
    float[4].descriptors = float[0].descriptors.clone();
    float[4].keypoints = float[0].keypoints.clone();
    let map = Arc::new(build(float, None, RetrievalKind::Global).expect("valid"));
    // keyframes of one repeated keypoint give the model locator no point to place a frame with
    assert_eq!(name_of(Localizer::new(Arc::clone(&map), LocalizerOptions::default())), "locator");
    let paper = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
    let mut loc = Localizer::new(Arc::clone(&map), paper).expect("valid");
    let kp = [Vector2::new(1.0, 2.0)];
    let d = [0.5f32; 4];
    let frame = |global| Frame {
        timestamp: 1.0,
        keypoints: &kp,
        descriptors: Descriptors::Float { data: &d, width: 4 },
        global,
        pixel_sigmas: None,
    };
    assert_eq!(name_of(loc.localize(&frame(Some(&[1.0, 2.0, 3.0])))), "global_descriptor");
    assert_eq!(name_of(loc.localize(&frame(None))), "global_descriptor");
    let history = LocalizerOptions { history: 1, ..LocalizerOptions::default() };
    assert_eq!(name_of(Localizer::new(map, history)), "history");
}

/// Tracking in the sequential mode (the paper's locator): every 7th frame retrieves a keyframe from the far end of
/// the walk (global descriptors are keyframe positions, the query's is replaced by the far
/// keyframe's), 3 m away, whose group sees only a corner of the view. Alone, the frame gets
/// its pose from that group's few points; in sequence the last frame's group is tried too
/// (the far group gives under half its inliers) and the frame gets a pose as good as its
/// neighbours' from it.
#[test]
fn a_wrong_retrieval_is_tracked_through_the_last_frames_group() {
    let mut rng = SplitMix64::new(17);
    let world = LandmarkScene::new(&mut rng, LANDMARKS, 12.0);
    let mut kfs = keyframes(&world, &mut rng);
    let position = |p: &SE3| p.translation.iter().map(|v| *v as f32).collect::<Vec<f32>>();
    for kf in &mut kfs {
        kf.global = Some(position(&kf.world_from_cam));
    }
    let far = position(&kfs[59].world_from_cam);
    let map = Arc::new(Map::build(world.camera, kfs, None, RetrievalKind::Global, 0).expect("valid map"));
    // tracking is the paper locator's
    let paper = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
    let mut sequential = Localizer::new(Arc::clone(&map), paper).expect("valid options");
    let mut single = Localizer::new(map, paper).expect("valid options");
    let (mut wrong, mut good) = (Vec::new(), Vec::new());
    for f in 0..40 {
        let t = 0.3 + f as f64 / 30.0;
        let truth = walk(t, 0.15);
        let (keypoints, data) = world.observe(&mut rng, &truth, 3);
        let misled = f >= 5 && f % 7 == 0;
        let global = if misled { far.clone() } else { position(&truth) };
        let frame = Frame {
            timestamp: t,
            keypoints: &keypoints,
            descriptors: Descriptors::Binary { data: &data, width: WIDTH },
            global: Some(&global),
            pixel_sigmas: None,
        };
        let r = sequential.localize(&frame).expect("valid frame");
        let error = r.estimate.map_or(f64::INFINITY, |e| (e.world_from_cam.translation - truth.translation).norm());
        single.reset();
        let alone = single.localize(&frame).expect("valid frame");
        if misled {
            // alone: the far keyframe's group, which sees a corner of the view
            assert_eq!(alone.keyframe, 59, "frame {f}: the far keyframe is retrieved");
            assert!(2 * alone.inliers < r.inliers, "frame {f}: {} inliers alone, {} tracked", alone.inliers, r.inliers);
            assert!(r.keyframe < 20, "frame {f}: tracked through keyframe {}", r.keyframe);
            assert_eq!(r.source, Source::Fused, "frame {f}: {}", r.reason);
            assert!(r.reason.contains("tracked through the last frame's keyframe"), "frame {f}: {}", r.reason);
            wrong.push(error);
        } else {
            good.push(error);
        }
    }
    let worst = wrong.iter().copied().fold(0.0, f64::max);
    eprintln!("misled frames: worst {:.2} mm; others: median {:.2} mm", 1e3 * worst, 1e3 * median(&good));
    assert_eq!(wrong.len(), 5);
    assert!(worst < 3.0 * median(&good), "misled frames up to {worst} m, others {} m", median(&good));
}

/// One pixel-noise model for query and map: the defaults of PnP and triangulation agree, and
/// `with_pixel_noise` sets both solvers' σ and residual bound and nothing else.
#[test]
#[allow(clippy::float_cmp)] // settings are copied, not computed: exact equality is the claim
fn pixel_noise_is_one_setting_for_pnp_and_triangulation() {
    let defaults = LocalizerOptions::default();
    assert_eq!(defaults.pnp.pixel_sigma, defaults.triangulation.pixel_sigma);
    assert_eq!(defaults.pnp.max_residual_px, defaults.triangulation.max_residual_px);
    let set = defaults.with_pixel_noise(0.7, 3.5);
    assert_eq!((set.pixel_sigma(), set.max_residual_px()), (0.7, 3.5));
    assert_eq!((set.triangulation.pixel_sigma, set.triangulation.max_residual_px), (0.7, 3.5));
    let mut back = set;
    back.pnp = defaults.pnp;
    back.triangulation = defaults.triangulation;
    assert_eq!(back, defaults);
}

/// The stage names come in pipeline order with their values.
#[test]
#[allow(clippy::float_cmp)] // values are copied, not computed
fn timings_stages_name_each_field_once() {
    let t = Timings {
        retrieval_ms: 1.0,
        keyframes_ms: 2.0,
        map_points_ms: 3.0,
        matching_ms: 4.0,
        pnp_ms: 5.0,
        motion_fusion_ms: 6.0,
        total_ms: 7.0,
    };
    let stages = t.stages();
    assert_eq!(stages.map(|(name, _)| name), Timings::STAGES);
    assert_eq!(stages.map(|(_, ms)| ms), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
}
