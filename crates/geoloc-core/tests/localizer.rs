//! The localizer on a simulated sequence: synthetic keyframes and features, clean and with
//! 20 % of frames given a gross geometric failure.

use std::sync::Arc;

use geoloc_core::camera::{Camera, project};
use geoloc_core::lie::SE3;
use geoloc_core::localizer::{Frame, Localizer, LocalizerOptions, Source};
use geoloc_core::map::{DescriptorSet, Keyframe, Map, RetrievalKind};
use geoloc_core::matching::Descriptors;
use geoloc_core::testing::{SplitMix64, look_at};
use nalgebra::{Vector2, Vector3};

const WIDTH: usize = 32;

struct World {
    landmarks: Vec<Vector3<f64>>,
    descriptors: Vec<[u8; WIDTH]>,
    camera: Camera,
}

impl World {
    fn new(rng: &mut SplitMix64) -> Self {
        let landmarks = (0..1000)
            .map(|_| Vector3::new(rng.uniform_in(-4.0, 4.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(3.0, 7.0)))
            .collect();
        let descriptors = (0..1000).map(|_| std::array::from_fn(|_| (rng.next_u64() & 0xff) as u8)).collect();
        Self { landmarks, descriptors, camera: Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid") }
    }

    /// What a camera at `pose` sees: keypoints with 0.5 px noise and descriptors with 3
    /// flipped bits.
    fn observe(&self, rng: &mut SplitMix64, pose: &SE3) -> (Vec<Vector2<f64>>, Vec<u8>) {
        let (mut kps, mut desc) = (Vec::new(), Vec::new());
        for (x, d) in self.landmarks.iter().zip(&self.descriptors) {
            let p = project(&self.camera, pose, x);
            if p.p_cam.z > 0.5 && (0.0..640.0).contains(&p.uv.x) && (0.0..480.0).contains(&p.uv.y) {
                kps.push(p.uv + Vector2::new(rng.normal(), rng.normal()) * 0.5);
                let mut d = *d;
                for _ in 0..3 {
                    let bit = (rng.next_u64() % (8 * WIDTH as u64)) as usize;
                    d[bit / 8] ^= 1 << (bit % 8);
                }
                desc.extend_from_slice(&d);
            }
        }
        (kps, desc)
    }
}

/// A camera walking along x at 0.6 m/s, looking forward (+z), with a gentle sway.
fn walk(t: f64, offset: f64) -> SE3 {
    let c = Vector3::new(-1.5 + 0.6 * t, offset + 0.05 * (2.0 * t).sin(), 0.0);
    look_at(&c, &(c + Vector3::new(0.1 * (1.3 * t).sin(), 0.0, 5.0)))
}

fn run(corrupt_fraction: f64) -> (Vec<f64>, Vec<Source>) {
    let mut rng = SplitMix64::new(11);
    let world = World::new(&mut rng);
    let keyframes: Vec<Keyframe> = (0..60)
        .map(|i| {
            let pose = walk(i as f64 * 0.1, 0.0);
            let (keypoints, data) = world.observe(&mut rng, &pose);
            Keyframe {
                world_from_cam: pose,
                keypoints,
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect();
    let map =
        Map::build(world.camera, keyframes, None, RetrievalKind::Bow { branching: 8, depth: 3 }, 0).expect("valid map");
    let mut localizer = Localizer::new(Arc::new(map), LocalizerOptions::default());
    let (mut errors, mut sources) = (Vec::new(), Vec::new());
    let mut corrupt_rng = SplitMix64::new(5);
    for f in 0..90 {
        let t = 0.3 + f as f64 / 30.0;
        let truth = walk(t, 0.15);
        let (keypoints, mut data) = world.observe(&mut rng, &truth);
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
        let frame = Frame {
            timestamp: t,
            keypoints: &keypoints,
            descriptors: Descriptors::Binary { data: &data, width: WIDTH },
            global: None,
        };
        let r = localizer.localize(&frame).expect("valid frame");
        sources.push(r.source);
        if let Some(p) = r.world_from_cam {
            errors.push((p.translation - truth.translation).norm());
        } else {
            errors.push(f64::INFINITY);
        }
    }
    (errors, sources)
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[s.len() / 2]
}

#[test]
fn clean_sequence_is_localized_and_fused() {
    let (errors, sources) = run(0.0);
    assert!(median(&errors) < 0.02, "median error {} m", median(&errors));
    assert!(sources[..2].iter().all(|s| *s == Source::Geometric));
    let fused = sources.iter().filter(|s| **s == Source::Fused).count();
    assert!(fused > 70, "{fused} fused of {}", sources.len());
    assert!(!sources.contains(&Source::Lost));
}

/// Issue #4: 20 % of frames with a gross failure of the geometric locator; the median error
/// stays within 1.2× of the clean run's (the motion model and the gate absorb them).
#[test]
fn gross_failures_are_absorbed_by_the_motion_model() {
    let (clean, _) = run(0.0);
    let (corrupt, sources) = run(0.2);
    let motion = sources.iter().filter(|s| **s == Source::Motion).count();
    eprintln!(
        "clean median {:.2} mm, 20 % corrupted median {:.2} mm, {motion} motion-only frames of {}",
        1e3 * median(&clean),
        1e3 * median(&corrupt),
        sources.len()
    );
    assert!(motion >= 8, "{motion} frames fell back to the motion model");
    assert!(median(&corrupt) <= 1.2 * median(&clean), "{} vs clean {}", median(&corrupt), median(&clean));
    assert!(corrupt.iter().all(|e| e.is_finite()));
}
