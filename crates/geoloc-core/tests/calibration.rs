//! On a simulated map: the map-frame covariance C_map estimated from held-out
//! keyframes covers injected pose-label noise (NEES of new queries against their noisy
//! labels), and the sequential localizer never locks out (a jump re-initializes the motion
//! history within N frames; a long failure is reported lost, then recovers).

use std::sync::Arc;

use geoloc_core::lie::SE3;
use geoloc_core::localizer::{Localizer, LocalizerOptions, Locator, NoiseOptions, Source};
use geoloc_core::map::{DescriptorSet, Keyframe, Map, RetrievalKind};
use geoloc_core::stats::chi2::CHI2_6_95;
use geoloc_core::testing::{self, LandmarkScene, SplitMix64};

const WIDTH: usize = testing::LANDMARK_DESCRIPTOR_BYTES;
/// Landmarks of the scene (about a third in view at a time).
const LANDMARKS: usize = 3000;

/// The camera path of these tests: [`testing::walk`] (the scene is [`LandmarkScene`]).
fn walk(t: f64, offset: f64) -> SE3 {
    testing::walk(t, offset, -1.5)
}

/// Injected pose-label noise per axis: 1 cm, 0.4°.
const LABEL_SIGMA_M: f64 = 0.01;
const LABEL_SIGMA_RAD: f64 = 0.4 * std::f64::consts::PI / 180.0;
/// NEES coverage band of the queries (88–99 %, widened by the binomial σ of
/// 120 frames, ≈ 2 %).
const COVERAGE_BAND: (f64, f64) = (0.85, 0.995);

/// Keyframes every `dt` s of the walk; labels with the injected noise when `noisy`.
fn keyframes(world: &LandmarkScene, rng: &mut SplitMix64, n: usize, dt: f64, noisy: bool) -> Vec<Keyframe> {
    (0..n)
        .map(|i| {
            let truth = walk(i as f64 * dt, 0.0);
            let (keypoints, data) = world.observe(rng, &truth, 3);
            let label = if noisy { truth * SE3::exp(&rng.pose_noise(LABEL_SIGMA_M, LABEL_SIGMA_RAD)) } else { truth };
            Keyframe {
                world_from_cam: label,
                keypoints,
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect()
}

fn bow() -> RetrievalKind {
    RetrievalKind::Bow { branching: 8, depth: 4 }
}

#[test]
fn map_noise_covers_injected_label_noise() {
    let mut rng = SplitMix64::new(31);
    let world = LandmarkScene::new(&mut rng, LANDMARKS, 12.0);
    let kfs = keyframes(&world, &mut rng, 120, 0.05, true);
    let times: Vec<f64> = (0..120).map(|i| i as f64 * 0.05).collect();
    let map = Map::build(world.camera, kfs, None, bow(), 0).expect("valid map");
    let options = NoiseOptions { holdout_step: 2, block: 20, margin: 2, ..NoiseOptions::default() };
    let map = map.with_estimated_noise(Some(&times), &options).expect("estimated");
    let c = map.noise.pose_covariance;
    let ratios: Vec<f64> =
        (0..6).map(|a| c[(a, a)].sqrt() / if a < 3 { LABEL_SIGMA_M } else { LABEL_SIGMA_RAD }).collect();
    eprintln!("held-out samples {}, √diag C_map / injected σ = {ratios:.2?}", map.noise.holdout_samples);
    assert!(map.noise.holdout_samples >= 40);
    // C_map holds the held-out label's own noise plus what the neighbours' labels do to
    // the estimate: at least the injected σ (minus the sampling error of ~50 samples).
    assert!(ratios.iter().all(|r| *r > 0.75 && *r < 3.0), "{ratios:?}");
    // the independent check: new queries beside the path, against labels with the same noise,
    // with the locator C_map was measured with (the paper's: the map has no 3D model)
    let options = LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() };
    let mut loc = Localizer::new(Arc::new(map), options).expect("valid");
    let (mut inside, mut total) = (0, 0);
    for f in 0..120 {
        let t = 0.2 + f as f64 * 0.045;
        let truth = walk(t, 0.05);
        let label = truth * SE3::exp(&rng.pose_noise(LABEL_SIGMA_M, LABEL_SIGMA_RAD));
        let (keypoints, data) = world.observe(&mut rng, &truth, 3);
        loc.reset();
        let frame = testing::landmark_frame(t, &keypoints, &data);
        let Some(e) = loc.localize(&frame).expect("valid").estimate else { continue };
        let d = (label.inverse() * e.world_from_cam).log();
        let nees = (d.transpose() * e.covariance.try_inverse().expect("spd") * d)[0];
        total += 1;
        inside += usize::from(nees <= CHI2_6_95);
    }
    let coverage = inside as f64 / total as f64;
    eprintln!("query NEES coverage {coverage:.3} of {total}");
    assert!(total >= 110);
    assert!(coverage > COVERAGE_BAND.0 && coverage < COVERAGE_BAND.1, "coverage {coverage}");
}

/// A sequence whose camera jumps 0.4 m sideways at frame 30 (the prediction is pushed off):
/// the motion history is re-initialized within N = 3 frames and the rest is localized; then
/// 15 frames of garbage features: motion-only, then lost, then geometric again.
#[test]
fn a_jump_reinitializes_and_a_long_failure_is_lost_then_recovers() {
    let mut rng = SplitMix64::new(41);
    let world = LandmarkScene::new(&mut rng, LANDMARKS, 12.0);
    let kfs = keyframes(&world, &mut rng, 60, 0.1, false);
    let map = Map::build(world.camera, kfs, None, bow(), 0).expect("valid map");
    let options = LocalizerOptions::default();
    let mut loc = Localizer::new(Arc::new(map), options).expect("valid");
    let (mut sources, mut reasons, mut errors) = (Vec::new(), Vec::new(), Vec::new());
    for f in 0..110 {
        let t = 0.3 + f as f64 / 30.0;
        let truth = walk(t, if f >= 30 { 0.4 } else { 0.0 });
        let (keypoints, mut data) = world.observe(&mut rng, &truth, 3);
        if (60..75).contains(&f) {
            data.iter_mut().for_each(|b| *b = (rng.next_u64() & 0xff) as u8);
        }
        let frame = testing::landmark_frame(t, &keypoints, &data);
        let r = loc.localize(&frame).expect("valid");
        errors.push(r.estimate.map_or(f64::INFINITY, |e| (e.world_from_cam.translation - truth.translation).norm()));
        sources.push(r.source);
        reasons.push(r.reason);
    }
    let reinit = (30..=32).find(|&f| reasons[f].contains("re-initialized"));
    eprintln!("sources after the jump {:?}, re-init at {reinit:?}", &sources[28..36]);
    assert!(reinit.is_some(), "no re-initialization in frames 30–32: {:?}", &reasons[30..33]);
    assert!(errors[33..60].iter().all(|e| *e < 0.02), "{:?}", &errors[33..60]);
    assert!(sources[60..75].contains(&Source::Lost), "{:?}", &sources[60..75]);
    assert!(sources[60] == Source::Motion);
    // the frame after the failure is localized afresh, not poisoned by the lost ones
    assert!(matches!(sources[75], Source::Geometric), "{:?}: {}", sources[75], reasons[75]);
    assert!(errors[76..].iter().all(|e| *e < 0.02), "{:?}", &errors[76..]);
}

/// Keyframes per pass of [`two_passes`].
const KEYFRAMES_PER_PASS: usize = 80;

/// The label-to-camera offset X = label_from_cam of the sensor-offset scenes: 3° and 5 cm.
fn sensor_offset() -> SE3 {
    use geoloc_core::lie::SO3;
    use nalgebra::Vector3;
    let axis = Vector3::new(0.3, -1.0, 0.5).normalize();
    SE3::new(SO3::exp(&(axis * 3f64.to_radians())), Vector3::new(0.04, -0.02, 0.02))
}

/// What `world` shows a camera at `cam`, with the keypoints' noise made the 1 px the localizer
/// assumes (the scene's 0.5 px, and another 0.75 px²).
fn observe_1px(world: &LandmarkScene, rng: &mut SplitMix64, cam: &SE3) -> (Vec<nalgebra::Vector2<f64>>, Vec<u8>) {
    let (mut keypoints, data) = world.observe(rng, cam, 3);
    for k in &mut keypoints {
        *k += nalgebra::Vector2::new(rng.normal(), rng.normal()) * 0.75f64.sqrt();
    }
    (keypoints, data)
}

/// Two passes of [`KEYFRAMES_PER_PASS`] keyframes along [`testing::walk`] 0.5 m apart, every
/// 0.2 s, seen by [`observe_1px`] in a new [`LandmarkScene`]: keyframe j's label is
/// `label(j, L)` of L = T [`sensor_offset`]⁻¹ with 3 mm / 0.11° of noise. Returns the scene,
/// the keyframes, their times and the true camera poses T.
fn two_passes(
    rng: &mut SplitMix64,
    label: impl Fn(usize, &SE3) -> SE3,
) -> (LandmarkScene, Vec<Keyframe>, Vec<f64>, Vec<SE3>) {
    let offset = sensor_offset();
    let world = LandmarkScene::new(rng, LANDMARKS, 8.0);
    let (mut keyframes, mut times, mut cameras) = (Vec::new(), Vec::new(), Vec::new());
    for j in 0..2 * KEYFRAMES_PER_PASS {
        let (i, side) = (j % KEYFRAMES_PER_PASS, 0.5 * (j / KEYFRAMES_PER_PASS) as f64);
        let cam = testing::walk(i as f64 * 0.1, side, -2.5);
        let (keypoints, data) = observe_1px(&world, rng, &cam);
        let labelled = cam * offset.inverse() * SE3::exp(&rng.pose_noise(0.003, 0.002));
        keyframes.push(Keyframe {
            world_from_cam: label(j, &labelled),
            keypoints,
            descriptors: DescriptorSet::Binary { data, width: WIDTH },
            global: None,
        });
        times.push(j as f64 * 0.2);
        cameras.push(cam);
    }
    (world, keyframes, times, cameras)
}

/// Labels that sit on another sensor and a run of them displaced: two passes of 80 keyframes
/// along [`testing::walk`] 0.5 m apart, every label on a sensor 3° and 5 cm from the camera
/// (X = label_from_cam) with 3 mm / 0.11° of noise, and the labels of 12 keyframes moved by a
/// further 20 cm / 5°; keypoints with the 1 px noise the localizer assumes (the paper's). The
/// default map (labels adjusted, map noise estimated; the synthetic camera is exact, so the
/// camera is not re-estimated) and localizer, single image: 40 queries per scene, on the
/// path and 3 cm, 10 cm and 50 cm beside it. Against the truth in the labels' convention
/// (T X⁻¹, what the results are given in), the adjusted poses of the displaced run are within
/// 1 cm / 0.2° of the truth (the views that tie the run to the rest, which the triangulation
/// from the labels rejects, join the adjustment once its first pass has moved the run: without
/// them the run stayed 1–3.5 cm / 0.1–0.55° off; the images' break where the run ends also
/// re-places it before the adjustment, [`geoloc_core::map::label_breaks`]). Returns each
/// answer's NEES against the truth.
fn sensor_offset_scene_nees(seed: u64) -> Vec<f64> {
    sensor_offset_scene(seed, 1.0).0
}

/// [`sensor_offset_scene_nees`] with the run displaced `scale` times as far (translation and
/// rotation), and the map's label report.
fn sensor_offset_scene(seed: u64, scale: f64) -> (Vec<f64>, geoloc_core::map::LabelAdjustment) {
    use geoloc_core::lie::se3;
    use geoloc_core::map::BuildOptions;
    use nalgebra::Vector3;
    let axis = Vector3::new(0.3, -1.0, 0.5).normalize();
    let offset = sensor_offset();
    let bump = SE3::exp(&se3::twist(&(Vector3::new(0.12, 0.1, -0.12) * scale), &(axis * (5.0 * scale).to_radians())));
    let mut rng = SplitMix64::new(seed);
    let (world, keyframes, times, _) =
        two_passes(&mut rng, |j, label| if (30..42).contains(&j) { bump * *label } else { *label });
    let options = BuildOptions { refine_intrinsics: false, ..BuildOptions::default() };
    let map = Map::build_with_options(world.camera, keyframes, None, Some(&times), &options).expect("builds");
    let record = map.labels.clone().expect("adjusted");
    assert!(record.applied, "seed {seed}: the adjustment is applied");
    for k in 30..42 {
        let truth = testing::walk(k as f64 * 0.1, 0.0, -2.5) * offset.inverse();
        let d = (record.to_label(&map.keyframes[k].world_from_cam).inverse() * truth).log();
        let (t, r) = (se3::rho(&d).norm(), se3::phi(&d).norm());
        assert!(t < 0.01 && r < 0.2f64.to_radians(), "seed {seed} keyframe {k}: {t} m, {} deg", r.to_degrees());
    }
    let map = Arc::new(map);
    let mut loc = Localizer::new(Arc::clone(&map), LocalizerOptions::default()).expect("valid");
    let mut nees = Vec::new();
    for q in 0..40 {
        let t = (q as f64 * 2.0 + 0.5) * 0.1;
        let cam = testing::walk(t, [0.0, 0.03, 0.1, 0.5][q % 4], -2.5);
        let (keypoints, data) = observe_1px(&world, &mut rng, &cam);
        loc.reset();
        let frame = testing::landmark_frame(t, &keypoints, &data);
        let result = map.to_label_convention(loc.localize(&frame).expect("valid"));
        let Some(e) = result.estimate else { continue };
        let d = (e.world_from_cam.inverse() * (cam * offset.inverse())).log();
        nees.push((d.transpose() * e.covariance.try_inverse().expect("spd") * d)[0]);
    }
    (nees, record)
}

/// The fraction of `nees` inside the χ²₆ 95 % region, and their median.
fn coverage_and_median(mut nees: Vec<f64>) -> (f64, f64) {
    let inside = nees.iter().filter(|&&n| n <= CHI2_6_95).count();
    nees.sort_by(f64::total_cmp);
    (inside as f64 / nees.len() as f64, nees[nees.len() / 2])
}

/// [`sensor_offset_scene_nees`] over the scenes `seeds`: the answers, their coverage and
/// median NEES (printed).
fn sensor_offset_coverage(seeds: std::ops::RangeInclusive<u64>) -> (usize, f64, f64) {
    let nees: Vec<f64> = seeds.flat_map(sensor_offset_scene_nees).collect();
    let total = nees.len();
    let (coverage, median) = coverage_and_median(nees);
    eprintln!("NEES coverage {coverage:.3} of {total}, median NEES {median:.2}");
    (total, coverage, median)
}

/// [`sensor_offset_scene_nees`] in three scenes: 114 or more of the 120 answered, at least 91 %
/// of them inside the χ²₆ 95 % region (93–97 % asked, widened by the binomial σ of 120), and
/// a median NEES of at least 3.5 (χ²₆'s is 5.35; a covariance 1.5 times too wide in σ gives
/// 2.4): with 120 answers the coverage cannot tell 97 % from 100 %, the median can (118
/// inside, median 3.95 — ten scenes put 97.25 % of 400 inside at 4.6:
/// `sensor_offset_coverage_over_ten_scenes`; with the adjustment's covariances taken from
/// its kernels' IRLS weights alone, which overstate the map's common error, all 120 at 3.3). Both halves of the map noise beside the path
/// matter here: it is the keyframes' common error, not one keyframe's marginal variance (whose
/// own part an answer resting on many keyframes' points does not share), and τ does not count
/// the displaced run as drift (counted, τ ≈ 11 and the labels' σ 1.05 cm for the true 3 mm);
/// with the marginal variance and τ over all corrections all 120 fell inside at a median NEES
/// of 1.2, with the common error but that τ at 1.5.
#[test]
fn the_localizer_covers_the_truth_when_labels_sit_on_another_sensor_and_a_run_is_displaced() {
    let (total, coverage, median) = sensor_offset_coverage(1..=3);
    assert!(total >= 114, "{total} of 120 answered");
    assert!(coverage >= 0.91 && median >= 3.5, "coverage {coverage}, median NEES {median}");
}

/// The measurement behind the three-scene check, in ten scenes (about 6 min, so not in the
/// suite: `cargo test --release -p geoloc-core --test calibration -- --ignored`): 389 of the
/// 400 answers inside the χ²₆ 95 % region (97.25 %; binomial 95 % interval 95.1–98.5 %),
/// median NEES 4.6 against χ²₆'s 5.35 (393, 98.25 % and 3.9 from the kernels' weights alone;
/// over 40 scenes those put 98.3 % of 1600 inside). Asserted: at least 92 % inside, median
/// NEES at least 2.5, as in the three-scene
/// check.
#[test]
#[ignore = "a ten-scene measurement (about 6 min); the suite runs the three-scene check"]
fn sensor_offset_coverage_over_ten_scenes() {
    let (total, coverage, median) = sensor_offset_coverage(1..=10);
    assert!(total >= 380, "{total} of 400 answered");
    assert!(coverage >= 0.92 && median >= 2.5, "coverage {coverage}, median NEES {median}");
}

/// A run displaced beyond what the adjustment's tracks tolerate — [`sensor_offset_scene`] with
/// the 12 labels moved by 0.39 m / 10° — is an island to them: matched among its own keyframes
/// only, it stayed 0.45 m / 10° off, no run in the label report, and answers beside it were
/// 0.40 m off with 17 of 39 inside their 95 % region. The images show the jump where the run
/// ends (keyframes 41–42: the labels' epipolar geometry keeps a fraction of the essential
/// matrix's inliers; where it begins, the jump lies along the epipolar geometry and two views
/// cannot see it), the run's keyframes located against the keyframes after it agree on one
/// correction back to keyframe 30 and disagree from 29, and the run alone is re-placed before
/// the adjustment: it is then recovered within 1 cm / 0.2° (asserted in the scene) and the
/// answers cover the truth.
#[test]
fn a_run_displaced_beyond_the_adjustments_reach_is_re_placed_from_the_images() {
    use geoloc_core::lie::se3;
    let (nees, record) = sensor_offset_scene(1, 2.0);
    assert!(record.breaks.iter().any(|b| b.at == 42), "{:?}", record.breaks);
    assert!(record.breaks.iter().all(|b| b.at == 30 || b.at == 42), "{:?}", record.breaks);
    let [segment] = record.replaced.as_slice() else { panic!("{:?}", record.replaced) };
    assert_eq!((segment.start, segment.end), (30, 42));
    let c = nalgebra::Vector6::from(segment.correction.expect("re-placed"));
    assert!(se3::phi(&c).norm().to_degrees() > 9.0, "{c}");
    let total = nees.len();
    let (coverage, median) = coverage_and_median(nees);
    eprintln!("NEES coverage {coverage:.3} of {total}, median NEES {median:.2}");
    assert!(total >= 38 && coverage >= 0.85, "{coverage} of {total}");
}

/// Labels that drift: the two passes of [`sensor_offset_scene`] (the labels on the same
/// sensor, 3 mm / 0.11° of noise), every label moved by exp(s ξ) in the world frame, s from 0
/// at the first keyframe to 1 at the last, ξ 0.49 m / 8° — 3 mm / 0.05° per keyframe, which
/// the labels' motion and the images agree on, but the second pass's labels lie 0.23 m / 4°
/// from the first's where the passes see the same place. The adjustment's tracks, proposed and
/// checked by the labels, never joined the passes: after it they stayed 0.23 m / 4.0° apart
/// (and the label-to-camera offset 0.72 m off). The map's retrieval pairs keyframes of the
/// two passes, the images tie them while the labels' epipolar geometry keeps none of their
/// matches, and the pose graph closes those loops before the adjustment
/// ([`geoloc_core::map::label_loops`]): the passes' relative poses come back within 3 cm /
/// 0.1° of the truth (measured 1.4 cm / 0.02°; 2.3 cm / 0.5° from the pose graph alone).
#[test]
fn labels_that_drift_between_two_passes_are_closed_by_the_revisits() {
    use geoloc_core::lie::se3;
    use geoloc_core::map::BuildOptions;
    use nalgebra::Vector3;
    const PASS: usize = KEYFRAMES_PER_PASS;
    let offset = sensor_offset();
    let xi = se3::twist(&Vector3::new(0.4, 0.2, -0.2), &(Vector3::new(0.2, 1.0, 0.3).normalize() * 8f64.to_radians()));
    let mut rng = SplitMix64::new(1);
    let (world, keyframes, times, cameras) =
        two_passes(&mut rng, |j, label| SE3::exp(&(xi * (j as f64 / (2 * PASS - 1) as f64))) * *label);
    // the median over the passes' pairs (j, j + PASS) of how far their relative pose is off
    let between_passes = |poses: &[SE3]| {
        let mut errors: Vec<(f64, f64)> = (0..PASS)
            .map(|j| {
                let truth = cameras[j].inverse() * cameras[j + PASS];
                let d = ((poses[j].inverse() * poses[j + PASS]).inverse() * truth).log();
                (se3::rho(&d).norm(), se3::phi(&d).norm().to_degrees())
            })
            .collect();
        errors.sort_by(|a, b| a.0.total_cmp(&b.0));
        errors[PASS / 2]
    };
    let labels: Vec<SE3> = keyframes.iter().map(|k| k.world_from_cam * offset).collect();
    let before = between_passes(&labels);
    assert!(before.0 > 0.2 && before.1 > 3.5, "{before:?}");
    let options = BuildOptions { refine_intrinsics: false, ..BuildOptions::default() };
    let map = Map::build_with_options(world.camera, keyframes, None, Some(&times), &options).expect("builds");
    let record = map.labels.clone().expect("adjusted");
    assert!(record.applied && record.breaks.is_empty(), "{}", record.summary());
    let closed = record.loops.iter().filter(|l| l.closed).count();
    assert!(closed >= PASS, "{closed} of {} loops closed", record.loops.len());
    assert!(record.loops.iter().all(|l| l.a < PASS && l.b >= PASS), "loops join the passes only");
    assert!(record.summary().contains("revisit(s) whose labels disagree with the images"), "{}", record.summary());
    let after = between_passes(&map.poses());
    assert!(after.0 < 0.03 && after.1 < 0.1, "{before:?} -> {after:?}");
    // the loops travel with the map
    let (back, _) = Map::from_bytes(&map.to_bytes("{}").expect("serializes")).expect("reads");
    assert_eq!(back.labels.expect("adjusted").loops, record.loops);
}
