//! Seeded sampling helpers shared by tests, property tests and benchmarks (not for
//! production code paths, which draw from [`crate::rng`]).
//!
//! Deterministic and dependency-free so a failing case can be replayed from its seed on any
//! machine.

use nalgebra::{Matrix6, Vector3, Vector6};

use crate::lie::{SE3, SO3, Twist};

pub use crate::rng::SplitMix64;

/// Samplers of geometric objects, for tests and benchmarks (the generator itself, and the
/// scalar draws production code uses, live in [`crate::rng`]).
impl SplitMix64 {
    /// A direction uniform on the unit sphere.
    pub fn unit_vector(&mut self) -> Vector3<f64> {
        loop {
            let v = Vector3::new(self.normal(), self.normal(), self.normal());
            let n = v.norm();
            if n > 1e-6 {
                return v / n;
            }
        }
    }

    /// A rotation uniform on SO(3) (Shoemake's uniform unit quaternion).
    pub fn rotation(&mut self) -> SO3 {
        let (u1, u2, u3) = (self.uniform(), self.uniform(), self.uniform());
        let (s1, s2) = ((1.0 - u1).sqrt(), u1.sqrt());
        let (a, b) = (std::f64::consts::TAU * u2, std::f64::consts::TAU * u3);
        SO3::from_quaternion_wxyz([s2 * b.cos(), s1 * a.sin(), s1 * a.cos(), s2 * b.sin()])
            .expect("invariant: a Shoemake quaternion has unit norm")
    }

    /// A rotation vector with the given angle and a uniform axis.
    pub fn rotation_vector(&mut self, angle_rad: f64) -> Vector3<f64> {
        angle_rad * self.unit_vector()
    }

    /// A twist whose rotation has angle `angle_rad` and whose ρ is uniform in a ball of
    /// radius `max_translation`.
    pub fn twist(&mut self, angle_rad: f64, max_translation: f64) -> Twist {
        let rho = self.unit_vector() * max_translation * self.uniform().cbrt();
        let phi = self.rotation_vector(angle_rad);
        crate::lie::se3::twist(&rho, &phi)
    }

    /// Pose noise for the right perturbation T·exp(δ^): each translation axis N(0, σ_t²),
    /// each rotation axis N(0, σ_r²) (translation first), i.e. δ ~ N(0, [`isotropic_pose_covariance`]).
    pub fn pose_noise(&mut self, sigma_t: f64, sigma_r: f64) -> Twist {
        Twist::new(
            sigma_t * self.normal(),
            sigma_t * self.normal(),
            sigma_t * self.normal(),
            sigma_r * self.normal(),
            sigma_r * self.normal(),
            sigma_r * self.normal(),
        )
    }

    /// A pose with a uniform rotation and a translation uniform in a ball of radius
    /// `max_translation`.
    pub fn pose(&mut self, max_translation: f64) -> SE3 {
        let t = self.unit_vector() * max_translation * self.uniform().cbrt();
        SE3::new(self.rotation(), t)
    }
}

/// diag(σ_t², σ_t², σ_t², σ_r², σ_r², σ_r²): the covariance of [`SplitMix64::pose_noise`].
pub fn isotropic_pose_covariance(sigma_t: f64, sigma_r: f64) -> Matrix6<f64> {
    let (vt, vr) = (sigma_t * sigma_t, sigma_r * sigma_r);
    Matrix6::from_diagonal(&Vector6::new(vt, vt, vt, vr, vr, vr))
}

/// A world_from_cam pose at `centre` whose optical axis (z) points at `target`, y down.
pub fn look_at(centre: &Vector3<f64>, target: &Vector3<f64>) -> SE3 {
    let z = (target - centre).normalize();
    let up = if z.y.abs() > 0.9 { Vector3::x() } else { Vector3::y() };
    let x = up.cross(&z).normalize();
    let y = z.cross(&x);
    SE3::new(SO3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, y, z])), *centre)
}

/// The angle regimes every Lie identity is checked in: identity, tiny,
/// just around the Taylor threshold, ordinary, and just short of π.
pub const ANGLE_REGIMES_RAD: [f64; 7] = [0.0, 1e-9, 1e-8, 0.19, 0.21, 1.3, std::f64::consts::PI - 1e-6];

#[cfg(test)]
mod tests {
    use super::*;

    /// For uniform rotations the angle has density (1 − cos θ)/π, so E[cos θ]... use
    /// E[tr R] = 0 (the trace of a Haar-random rotation has mean 0).
    #[test]
    fn uniform_rotations_have_zero_mean_trace() {
        let mut rng = SplitMix64::new(11);
        let n = 50_000;
        let mean_trace = (0..n).map(|_| rng.rotation().matrix().trace()).sum::<f64>() / n as f64;
        assert!(mean_trace.abs() < 0.02, "{mean_trace}");
    }
}

/// Bytes of the binary descriptors of a [`LandmarkScene`].
pub const LANDMARK_DESCRIPTOR_BYTES: usize = 32;

/// A frame of what [`LandmarkScene::observe`] returned, taken at `timestamp`: binary
/// descriptors of [`LANDMARK_DESCRIPTOR_BYTES`], no global descriptor, the default pixel σ.
pub fn landmark_frame<'a>(
    timestamp: f64,
    keypoints: &'a [nalgebra::Vector2<f64>],
    data: &'a [u8],
) -> crate::localizer::Frame<'a> {
    crate::localizer::Frame {
        timestamp,
        keypoints,
        descriptors: crate::matching::Descriptors::Binary { data, width: LANDMARK_DESCRIPTOR_BYTES },
        global: None,
        pixel_sigmas: None,
    }
}

/// A field of landmarks at depth 3–6 m in front of the x axis, each with a random binary
/// descriptor: the simulated scene of the localizer tests (core, calibration, geoloc-rs).
#[derive(Clone, Debug)]
pub struct LandmarkScene {
    /// World points.
    pub landmarks: Vec<Vector3<f64>>,
    /// One descriptor per landmark.
    pub descriptors: Vec<[u8; LANDMARK_DESCRIPTOR_BYTES]>,
    /// fx = fy = 525, (cx, cy) = (320, 240), 640×480 images.
    pub camera: crate::camera::Camera,
}

impl LandmarkScene {
    /// `count` landmarks uniform in x ∈ [−half_width_m, half_width_m], y ∈ [−1.5, 1.5], z ∈ [3, 6].
    pub fn new(rng: &mut SplitMix64, count: usize, half_width_m: f64) -> Self {
        let landmarks = (0..count)
            .map(|_| {
                Vector3::new(
                    rng.uniform_in(-half_width_m, half_width_m),
                    rng.uniform_in(-1.5, 1.5),
                    rng.uniform_in(3.0, 6.0),
                )
            })
            .collect();
        let descriptors = (0..count).map(|_| std::array::from_fn(|_| (rng.next_u64() & 0xff) as u8)).collect();
        let camera = crate::camera::Camera::new(525.0, 525.0, 320.0, 240.0).expect("invariant: valid intrinsics");
        Self { landmarks, descriptors, camera }
    }

    /// What a camera at `pose` sees: keypoints with 0.5 px Gaussian noise and descriptors with
    /// `flipped_bits` random bits flipped (row-major bytes).
    pub fn observe(
        &self,
        rng: &mut SplitMix64,
        pose: &SE3,
        flipped_bits: usize,
    ) -> (Vec<nalgebra::Vector2<f64>>, Vec<u8>) {
        let (mut kps, mut desc) = (Vec::new(), Vec::new());
        for (x, d) in self.landmarks.iter().zip(&self.descriptors) {
            let p = crate::camera::project(&self.camera, pose, x);
            if p.p_cam.z > 0.5 && (0.0..640.0).contains(&p.uv.x) && (0.0..480.0).contains(&p.uv.y) {
                kps.push(p.uv + nalgebra::Vector2::new(rng.normal(), rng.normal()) * 0.5);
                let mut d = *d;
                for _ in 0..flipped_bits {
                    let bit = (rng.next_u64() % (8 * LANDMARK_DESCRIPTOR_BYTES as u64)) as usize;
                    d[bit / 8] ^= 1 << (bit % 8);
                }
                desc.extend_from_slice(&d);
            }
        }
        (kps, desc)
    }
}

/// A camera walking along x at 0.6 m/s from `start_x` (m), `offset` (m) beside the path,
/// looking forward (+z) with a gentle sway: world_from_cam at time `t` (s).
pub fn walk(t: f64, offset: f64, start_x: f64) -> SE3 {
    let c = Vector3::new(start_x + 0.6 * t, offset + 0.05 * (2.0 * t).sin(), 0.0);
    look_at(&c, &(c + Vector3::new(0.1 * (1.3 * t).sin(), 0.0, 5.0)))
}

/// The 44-byte frame stream of one self-consistent record that claims ~4.12 GB: the stream
/// header, the length field and the fixed fields (float descriptors of the widest width),
/// nothing else. Returns the bytes and the claimed payload length. Readers must refuse it
/// before allocating.
pub fn huge_frame_record_claim() -> (Vec<u8>, usize) {
    use crate::frames::{
        CHECKSUM_BYTES, FIXED_BYTES, MAX_DESCRIPTOR_WIDTH, MAX_KEYPOINTS, payload_len, write_stream_header,
    };
    let width = MAX_DESCRIPTOR_WIDTH;
    let n = (4_120_000_000 - FIXED_BYTES - CHECKSUM_BYTES) / (16 + 8 + 4 * width);
    let len = payload_len(n, 1, width, 0).expect("invariant: no overflow");
    assert!(n <= MAX_KEYPOINTS && u32::try_from(len).is_ok(), "the claim passes every size check");
    let mut bytes = Vec::new();
    write_stream_header(&mut bytes).expect("invariant: in memory");
    bytes.extend((len as u32).to_le_bytes());
    bytes.extend(1.0f64.to_le_bytes());
    bytes.extend((n as u32).to_le_bytes());
    bytes.extend([1, 0, 0, 0]);
    bytes.extend((width as u32).to_le_bytes());
    bytes.extend(0u32.to_le_bytes());
    assert_eq!(bytes.len(), 44);
    (bytes, len)
}

/// The `vocabulary.node_offsets` and `vocabulary.children` arrays of a chain of `nodes`
/// levels: node i has node i + 1 (first, so a descent with equal centres runs the whole
/// chain) and word i; the last node's children are words. `nodes + 1` words.
pub fn chain_vocabulary(nodes: usize) -> (Vec<i64>, Vec<i64>) {
    let mut offsets = vec![0i64];
    let mut children = Vec::with_capacity(2 * nodes);
    for i in 0..nodes {
        children.push(if i + 1 < nodes { i as i64 + 1 } else { -(i as i64) - 2 });
        children.push(-(i as i64) - 1);
        offsets.push(children.len() as i64);
    }
    (offsets, children)
}
