//! The pinhole camera and its Jacobians.
//!
//! A point X in the world is seen by a camera with pose T = world_from_cam = (R, t) at
//!
//!   p = T⁻¹ X = Rᵀ (X − t)                 (p_cam = cam_from_world · p_world)
//!   π(T, X) = (f_x p_x / p_z + c_x,  f_y p_y / p_z + c_y)
//!
//! (the paper's Π(T, X) = K T⁻¹ X). Pixels are *undistorted*: Python removes lens
//! distortion with OpenCV before anything reaches the core. Pose Jacobians are for the
//! right perturbation T ⊞ δ = T exp(δ^), δ = (ρ, φ): there p = exp(−δ^) T⁻¹ X ≈ p − ρ + p^ φ,
//! so ∂p/∂δ = [−I | p^].

use nalgebra::{Matrix2x3, Matrix2x6, Vector2, Vector3};

mod distortion;
pub use distortion::Distortion;

use crate::error::{GeolocError, Result};
use crate::lie::{SE3, so3};

/// Pinhole intrinsics K = (f_x, f_y, c_x, c_y), in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Focal length along x (pixels).
    pub fx: f64,
    /// Focal length along y (pixels).
    pub fy: f64,
    /// Principal point x (pixels).
    pub cx: f64,
    /// Principal point y (pixels).
    pub cy: f64,
}

impl Camera {
    /// Checked constructor: finite values and positive focal lengths.
    ///
    /// # Errors
    /// [`GeolocError::InvalidInput`] naming the offending intrinsic.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self> {
        for (name, v) in [("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)] {
            if !v.is_finite() {
                return Err(GeolocError::invalid(name, format!("must be finite, got {v}")));
            }
        }
        for (name, v) in [("fx", fx), ("fy", fy)] {
            if v <= 0.0 {
                return Err(GeolocError::invalid(name, format!("focal length must be > 0, got {v}")));
            }
        }
        Ok(Self { fx, fy, cx, cy })
    }

    /// π of a point already in camera coordinates (no check of p_z > 0).
    #[inline]
    pub fn project_cam(&self, p_cam: &Vector3<f64>) -> Vector2<f64> {
        let inv_z = 1.0 / p_cam.z;
        Vector2::new(self.fx * p_cam.x * inv_z + self.cx, self.fy * p_cam.y * inv_z + self.cy)
    }

    /// ∂π/∂p_cam = [[f_x/z, 0, −f_x x/z²], [0, f_y/z, −f_y y/z²]].
    #[inline]
    pub fn j_uv_pcam(&self, p_cam: &Vector3<f64>) -> Matrix2x3<f64> {
        let inv_z = 1.0 / p_cam.z;
        let inv_z2 = inv_z * inv_z;
        Matrix2x3::new(
            self.fx * inv_z,
            0.0,
            -self.fx * p_cam.x * inv_z2,
            0.0,
            self.fy * inv_z,
            -self.fy * p_cam.y * inv_z2,
        )
    }

    /// K⁻¹ = [[1/f_x, 0, −c_x/f_x], [0, 1/f_y, −c_y/f_y], [0, 0, 1]].
    pub fn inverse_matrix(&self) -> nalgebra::Matrix3<f64> {
        nalgebra::Matrix3::new(
            1.0 / self.fx,
            0.0,
            -self.cx / self.fx,
            0.0,
            1.0 / self.fy,
            -self.cy / self.fy,
            0.0,
            0.0,
            1.0,
        )
    }

    /// The bearing K⁻¹ (u, v, 1) of an (undistorted) pixel, with z = 1.
    #[inline]
    pub fn unproject(&self, uv: &Vector2<f64>) -> Vector3<f64> {
        Vector3::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy, 1.0)
    }
}

/// A point projected by a world_from_cam pose, with what the Jacobians need.
#[derive(Clone, Copy, Debug)]
pub struct Projection {
    /// p_cam = T⁻¹ X.
    pub p_cam: Vector3<f64>,
    /// π(T, X) in pixels.
    pub uv: Vector2<f64>,
}

/// Projects world point `x` into the camera `world_from_cam` (see the module doc).
#[inline]
pub fn project(camera: &Camera, world_from_cam: &SE3, x: &Vector3<f64>) -> Projection {
    let r = world_from_cam.rotation.matrix();
    let p_cam = r.tr_mul(&(x - world_from_cam.translation));
    Projection { p_cam, uv: camera.project_cam(&p_cam) }
}

/// ∂π/∂X = ∂π/∂p · Rᵀ.
#[inline]
pub fn j_uv_point(camera: &Camera, world_from_cam: &SE3, p: &Projection) -> Matrix2x3<f64> {
    camera.j_uv_pcam(&p.p_cam) * world_from_cam.rotation.matrix().transpose()
}

/// ∂π/∂δ for the right perturbation T exp(δ^) of world_from_cam: ∂π/∂p · [−I | p^].
#[inline]
pub fn j_uv_pose(camera: &Camera, p: &Projection) -> Matrix2x6<f64> {
    let j = camera.j_uv_pcam(&p.p_cam);
    let mut out = Matrix2x6::zeros();
    out.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-j));
    out.fixed_view_mut::<2, 3>(0, 3).copy_from(&(j * so3::hat(&p.p_cam)));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::Twist;
    use crate::testing::SplitMix64;
    use nalgebra::{SMatrix, SVector};

    const FD_STEP: f64 = 1e-6;
    const JAC_TOL: f64 = 1e-6;

    fn central<const N: usize>(f: impl Fn(&SVector<f64, N>) -> Vector2<f64>) -> SMatrix<f64, 2, N> {
        let mut j = SMatrix::<f64, 2, N>::zeros();
        for i in 0..N {
            let mut e = SVector::<f64, N>::zeros();
            e[i] = FD_STEP;
            j.set_column(i, &((f(&e) - f(&-e)) / (2.0 * FD_STEP)));
        }
        j
    }

    fn scene(rng: &mut SplitMix64) -> (Camera, SE3, Vector3<f64>) {
        let cam = Camera::new(525.0, 530.0, 320.0, 240.0).expect("valid");
        let pose = rng.pose(5.0);
        let p_cam = Vector3::new(rng.uniform_in(-1.0, 1.0), rng.uniform_in(-1.0, 1.0), rng.uniform_in(1.0, 6.0));
        (cam, pose, pose * p_cam)
    }

    #[test]
    fn projection_known_value() {
        let cam = Camera::new(500.0, 500.0, 320.0, 240.0).expect("valid");
        let p = project(&cam, &SE3::identity(), &Vector3::new(0.2, -0.1, 2.0));
        assert!((p.uv - Vector2::new(370.0, 215.0)).norm() < 1e-12);
        // a camera moved 1 m along world x sees the same point 1 m further left
        let moved = SE3::exp(&Twist::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0));
        let q = project(&cam, &moved, &Vector3::new(0.2, -0.1, 2.0));
        assert!((q.uv - Vector2::new(320.0 + 500.0 * (-0.8) / 2.0, 215.0)).norm() < 1e-12);
        assert!((cam.unproject(&p.uv) * 2.0 - p.p_cam).norm() < 1e-12);
    }

    #[test]
    fn point_jacobian_matches_central_differences() {
        let mut rng = SplitMix64::new(1);
        for _ in 0..200 {
            let (cam, pose, x) = scene(&mut rng);
            let p = project(&cam, &pose, &x);
            let numeric = central::<3>(|d| project(&cam, &pose, &(x + d)).uv);
            let analytic = j_uv_point(&cam, &pose, &p);
            assert!((analytic - numeric).abs().max() < JAC_TOL * analytic.abs().max().max(1.0));
        }
    }

    #[test]
    fn pose_jacobian_matches_central_differences_on_the_manifold() {
        let mut rng = SplitMix64::new(2);
        for _ in 0..200 {
            let (cam, pose, x) = scene(&mut rng);
            let p = project(&cam, &pose, &x);
            let numeric = central::<6>(|d| project(&cam, &(pose * SE3::exp(d)), &x).uv);
            let analytic = j_uv_pose(&cam, &p);
            assert!((analytic - numeric).abs().max() < JAC_TOL * analytic.abs().max().max(1.0));
        }
    }

    #[test]
    fn bad_intrinsics_are_named() {
        assert!(matches!(Camera::new(0.0, 1.0, 0.0, 0.0), Err(GeolocError::InvalidInput { name, .. }) if name == "fx"));
        assert!(
            matches!(Camera::new(1.0, 1.0, f64::NAN, 0.0), Err(GeolocError::InvalidInput { name, .. }) if name == "cx")
        );
    }
}
