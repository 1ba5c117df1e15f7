//! The map estimates its own camera (intrinsics refined at map-build time from the
//! known poses): a simulated recording whose real camera differs from the nominal one the
//! caller gives (focal lengths and principal point 1–2 % off, a Kinect-sized lens
//! distortion) — the map's correction recovers the real camera where the keypoints are,
//! localization against the refined map is several times more accurate than against the
//! nominal one, and the correction survives save/load with bit-identical results.

use std::sync::Arc;

use geoloc_core::camera::{Camera, Distortion};
use geoloc_core::lie::SE3;
use geoloc_core::localizer::{Localizer, LocalizerOptions};
use geoloc_core::map::{DescriptorSet, Keyframe, Map, RetrievalKind};
use geoloc_core::selfcal::{IntrinsicsCorrection, SelfCalibrationOptions};
use geoloc_core::testing::{self, LandmarkScene, SplitMix64};
use nalgebra::{Vector2, Vector3};

const WIDTH: usize = testing::LANDMARK_DESCRIPTOR_BYTES;
/// Pixel noise of the simulated keypoints (px, per axis).
const NOISE_PX: f64 = 0.5;

/// The camera that really took the images.
fn real_camera() -> (Camera, Distortion) {
    (
        Camera::new(516.0, 529.0, 314.0, 243.0).expect("valid"),
        Distortion { k1: -0.06, k2: 0.02, p1: 0.004, p2: -0.003, k3: 0.0 },
    )
}

/// The camera the caller believes in (the 7-Scenes folklore).
fn nominal() -> Camera {
    Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid")
}

/// Walking along x while turning the head ±20° left and right (rotation makes the focal
/// length observable: under pure translation it trades off with depth).
fn pose(t: f64, offset: f64) -> SE3 {
    let c = Vector3::new(-2.0 + 0.6 * t, offset, 0.0);
    let yaw: f64 = 0.35 * (1.3 * t).sin();
    let pitch: f64 = 0.12 * (0.7 * t).cos();
    testing::look_at(&c, &(c + Vector3::new(5.0 * yaw.tan(), 5.0 * pitch.tan(), 5.0)))
}

/// What the real camera records at `pose`: keypoints with noise, descriptors with 3 bits flipped.
fn observe(world: &LandmarkScene, rng: &mut SplitMix64, pose: &SE3) -> (Vec<Vector2<f64>>, Vec<u8>) {
    let (camera, distortion) = real_camera();
    let (mut keypoints, mut data) = (Vec::new(), Vec::new());
    for (x, d) in world.landmarks.iter().zip(&world.descriptors) {
        let p = pose.rotation.matrix().tr_mul(&(x - pose.translation));
        if p.z < 0.5 {
            continue;
        }
        let xd = distortion.distort(&Vector2::new(p.x / p.z, p.y / p.z));
        let u = Vector2::new(camera.fx * xd.x + camera.cx, camera.fy * xd.y + camera.cy);
        if (0.0..640.0).contains(&u.x) && (0.0..480.0).contains(&u.y) {
            keypoints.push(u + Vector2::new(rng.normal(), rng.normal()) * NOISE_PX);
            let mut d = *d;
            for _ in 0..3 {
                let bit = (rng.next_u64() % (8 * WIDTH as u64)) as usize;
                d[bit / 8] ^= 1 << (bit % 8);
            }
            data.extend_from_slice(&d);
        }
    }
    (keypoints, data)
}

fn map(world: &LandmarkScene, rng: &mut SplitMix64, keyframes: usize) -> Map {
    let keyframes = (0..keyframes)
        .map(|i| {
            let truth = pose(i as f64 * 0.1, 0.0);
            let (keypoints, data) = observe(world, rng, &truth);
            Keyframe {
                world_from_cam: truth,
                keypoints,
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect();
    Map::build(nominal(), keyframes, None, RetrievalKind::Bow { branching: 8, depth: 4 }, 0).expect("valid map")
}

/// Median translation error (m) of single-image localization of 40 queries 0.15 m off the path.
fn median_error(map: Arc<Map>, world: &LandmarkScene, seed: u64) -> (f64, Vec<u64>) {
    let mut rng = SplitMix64::new(seed);
    let mut loc = Localizer::new(map, LocalizerOptions::default()).expect("valid options");
    let mut errors = Vec::new();
    let mut bits = Vec::new();
    for i in 0..40 {
        let truth = pose(0.35 + i as f64 * 0.2, 0.15);
        let (keypoints, data) = observe(world, &mut rng, &truth);
        let frame = testing::landmark_frame(i as f64, &keypoints, &data);
        loc.reset();
        let out = loc.localize(&frame).expect("valid frame");
        let e = out.estimate.map_or(f64::INFINITY, |e| (e.world_from_cam.translation - truth.translation).norm());
        if let Some(e) = out.estimate {
            bits.extend(e.world_from_cam.translation.iter().map(|v| v.to_bits()));
        }
        errors.push(e);
    }
    errors.sort_by(f64::total_cmp);
    (errors[errors.len() / 2], bits)
}

#[test]
fn the_map_estimates_the_real_camera_and_localizes_better_with_it() {
    let mut rng = SplitMix64::new(41);
    let world = LandmarkScene::new(&mut rng, 3000, 10.0);
    let plain = map(&world, &mut rng.clone(), 90);
    let refined = map(&world, &mut rng, 90).with_refined_intrinsics(&SelfCalibrationOptions::default()).expect("valid");
    let calibration = refined.self_calibration.clone().expect("tried");
    let correction = calibration.correction.expect("the tracks give a correction");
    assert_eq!(calibration.reason, "ok");
    assert!(
        calibration.rms_after_px < 1.0 && calibration.rms_before_px > 2.0 * calibration.rms_after_px,
        "rms {} -> {} px",
        calibration.rms_before_px,
        calibration.rms_after_px
    );
    // the correction against the real camera's, over the image area the keypoints cover
    let (camera, distortion) = real_camera();
    let exact = IntrinsicsCorrection { camera, distortion };
    let mut worst: f64 = 0.0;
    for i in 1..16 {
        for j in 1..12 {
            let u = Vector2::new(40.0 * i as f64, 40.0 * j as f64);
            let a = correction.correct(&nominal(), &u).expect("inverts");
            let b = exact.correct(&nominal(), &u).expect("inverts");
            worst = worst.max((a - b).norm());
        }
    }
    assert!(worst < 1.0, "the map's correction is {worst} px from the real camera's");
    // the keyframes' keypoints are stored corrected
    assert_ne!(refined.keyframes[0].keypoints, plain.keyframes[0].keypoints);
    let (plain_error, _) = median_error(Arc::new(plain), &world, 7);
    let refined = Arc::new(refined);
    let (refined_error, bits) = median_error(Arc::clone(&refined), &world, 7);
    assert!(refined_error < 0.5 * plain_error, "median {refined_error} m refined vs {plain_error} m nominal");
    // save / load: the same correction, the same bits out
    let dir = std::env::temp_dir().join(format!("geoloc-selfcal-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("refined.geoloc");
    refined.save(&path, "{}").expect("saves");
    let (loaded, header) = Map::load(&path).expect("loads");
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(loaded.intrinsics_correction(), Some(&correction));
    assert!(header.self_calibration.is_some_and(|h| h.reason == "ok"));
    let (_, loaded_bits) = median_error(Arc::new(loaded), &world, 7);
    assert_eq!(bits, loaded_bits);
}

#[test]
fn a_map_that_cannot_determine_its_camera_says_why_and_keeps_its_keypoints() {
    let mut rng = SplitMix64::new(42);
    let world = LandmarkScene::new(&mut rng, 300, 10.0);
    let plain = map(&world, &mut rng.clone(), 6);
    let out = map(&world, &mut rng, 6).with_refined_intrinsics(&SelfCalibrationOptions::default()).expect("valid");
    let calibration = out.self_calibration.clone().expect("tried");
    assert!(calibration.correction.is_none(), "{calibration:?}");
    assert!(calibration.reason.contains("do not determine the camera"), "{}", calibration.reason);
    assert!(calibration.correction_sigma_px > 0.5, "{calibration:?}");
    assert_eq!(out.keyframes[3].keypoints, plain.keyframes[3].keypoints);
    // refining twice is refused only once a correction is applied
    assert!(out.with_refined_intrinsics(&SelfCalibrationOptions::default()).is_ok());
}

/// Refining and building the 3D model in one step (the keyframe pairs matched once) gives
/// the map of the two steps, bit for bit — also with model options whose pairs differ (the
/// matches are then recomputed); pair matches computed with other options are refused.
#[test]
fn refining_with_the_model_equals_refining_then_building_it() {
    use geoloc_core::map::{ModelOptions, PairMatches, SceneModel, calibration_tracks};
    let mut rng = SplitMix64::new(43);
    let world = LandmarkScene::new(&mut rng, 1500, 10.0);
    let base = || map(&world, &mut rng.clone(), 40);
    let calibration = SelfCalibrationOptions::default();
    let other_pairs = ModelOptions { neighbours: 3, ..ModelOptions::default() };
    for options in [ModelOptions::default(), other_pairs] {
        let two_steps =
            base().with_refined_intrinsics(&calibration).and_then(|m| m.with_model(&options)).expect("valid");
        let one_step = base().with_refined_intrinsics_and_model(&calibration, &options).expect("valid");
        assert!(two_steps.model.as_ref().is_some_and(|m| m.len() > 100));
        assert!(two_steps.intrinsics_correction().is_some());
        assert_eq!(one_step.model, two_steps.model);
        assert_eq!(one_step.self_calibration, two_steps.self_calibration);
        let keypoints = |m: &Map| m.keyframes.iter().map(|k| k.keypoints.clone()).collect::<Vec<_>>();
        assert_eq!(keypoints(&one_step), keypoints(&two_steps));
    }
    let base = base();
    let matches = PairMatches::compute(&base.keyframes, &calibration_tracks()).expect("valid");
    assert!(matches.serves(&ModelOptions::default()) && !matches.serves(&other_pairs));
    let refused = SceneModel::from_pair_matches(&base.camera, &base.keyframes, None, &other_pairs, &matches);
    assert!(refused.is_err_and(|e| e.to_string().contains("pair_matches")));
    let fewer = &base.keyframes[..30];
    assert!(SceneModel::from_pair_matches(&base.camera, fewer, None, &ModelOptions::default(), &matches).is_err());
    // keyframes of the same count but other sizes: refused, not an index out of range
    let mut other = map(&world, &mut rng.clone(), 40).keyframes;
    other[7].keypoints.truncate(3);
    other[7].descriptors = other[7].descriptors.select(&[0, 1, 2]);
    assert!(SceneModel::from_pair_matches(&base.camera, &other, None, &ModelOptions::default(), &matches).is_err());
}

/// The one-pass build accepts what the two-step build accepted: keyframes without neighbour
/// pairs and matching options nobody checks then (a NaN ratio), keyframes with fewer
/// keypoints than descriptors (Map::build refuses those; SceneModel::build is public).
#[test]
fn the_model_build_accepts_what_it_accepted_before() {
    use geoloc_core::map::{ModelOptions, SceneModel};
    use geoloc_core::matching::MatchOptions;
    let mut rng = SplitMix64::new(45);
    let world = LandmarkScene::new(&mut rng, 300, 10.0);
    let base = map(&world, &mut rng, 4);
    let nan = ModelOptions {
        matching: MatchOptions { ratio: Some(f32::NAN), ..MatchOptions::default() },
        ..Default::default()
    };
    let one = SceneModel::build(&base.camera, &base.keyframes[..1], None, &nan).expect("no pair, nothing to match");
    assert!(one.is_empty());
    let mut short = base.keyframes[..1].to_vec();
    short[0].keypoints.truncate(2);
    assert!(SceneModel::build(&base.camera, &short, None, &ModelOptions::default()).is_ok_and(|m| m.is_empty()));
}
