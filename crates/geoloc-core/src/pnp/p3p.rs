//! The minimal absolute-pose solver: Grunert's P3P as given by Haralick et al.,
//! "Review and analysis of solutions of the three point perspective pose estimation
//! problem", IJCV 1994 (§2.1).
//!
//! With unit bearings j₁, j₂, j₃ and world points P₁, P₂, P₃, let a = |P₂−P₃|, b = |P₁−P₃|,
//! c = |P₁−P₂| and cos α = j₂·j₃, cos β = j₁·j₃, cos γ = j₁·j₂. The depths sᵢ along the
//! bearings satisfy the three laws of cosines; with s₂ = u s₁, s₃ = v s₁ they reduce to a
//! quartic in v (coefficients A₄…A₀ below), u follows linearly, s₁² = b²/(1 + v² − 2v cos β).
//! Each positive-depth solution gives camera-frame points sᵢjᵢ, aligned with Pᵢ by the
//! Kabsch/Umeyama absolute orientation.

use nalgebra::{Matrix3, Vector3};

use crate::lie::{SE3, SO3};

/// |A₄| below this fraction of max|Aᵢ| makes the quartic degenerate for this sample.
const DEGENERATE_LEADING: f64 = 1e-12;

/// All world_from_cam poses consistent with three bearing/point pairs (0 to 4 of them).
///
/// `bearings` must be unit vectors in the camera frame (K⁻¹(u, v, 1) normalized).
pub fn p3p(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> Vec<SE3> {
    let [j1, j2, j3] = bearings;
    let [p1, p2, p3] = points;
    let a2 = (p2 - p3).norm_squared();
    let b2 = (p1 - p3).norm_squared();
    let c2 = (p1 - p2).norm_squared();
    if b2 <= 0.0 || a2 <= 0.0 || c2 <= 0.0 {
        return Vec::new();
    }
    let (ca, cb, cg) = (j2.dot(j3), j1.dot(j3), j1.dot(j2));
    let amc = (a2 - c2) / b2;
    let apc = (a2 + c2) / b2;
    let coeffs = [
        (1.0 + amc).powi(2) - 4.0 * a2 / b2 * cg * cg, // A0
        4.0 * (-amc * (1.0 + amc) * cb + 2.0 * a2 / b2 * cg * cg * cb - (1.0 - apc) * ca * cg), // A1
        2.0 * (amc * amc - 1.0 + 2.0 * amc * amc * cb * cb + 2.0 * (b2 - c2) / b2 * ca * ca - 4.0 * apc * ca * cb * cg
            + 2.0 * (b2 - a2) / b2 * cg * cg), // A2
        4.0 * (amc * (1.0 - amc) * cb - (1.0 - apc) * ca * cg + 2.0 * c2 / b2 * ca * ca * cb), // A3
        (amc - 1.0).powi(2) - 4.0 * c2 / b2 * ca * ca, // A4
    ];
    let Some(world_frame) = triangle_frame(points) else { return Vec::new() };
    let mut poses = Vec::with_capacity(4);
    for v in real_quartic_roots(&coeffs) {
        let denom = 2.0 * (cg - v * ca);
        if denom.abs() < 1e-14 {
            continue;
        }
        let u = ((-1.0 + amc) * v * v - 2.0 * amc * cb * v + 1.0 + amc) / denom;
        let s1_sq = b2 / (1.0 + v * v - 2.0 * v * cb);
        if s1_sq.is_nan() || s1_sq <= 0.0 || u <= 0.0 || v <= 0.0 {
            continue;
        }
        let s1 = s1_sq.sqrt();
        let cam_points = [j1 * s1, j2 * (u * s1), j3 * (v * s1)];
        if let Some(cam_frame) = triangle_frame(&cam_points) {
            // R_wc maps the camera triangle's frame onto the world triangle's
            let r = world_frame * cam_frame.transpose();
            let rotation = SO3::from_matrix_unchecked(r);
            poses.push(SE3::new(rotation, points[0] - rotation * cam_points[0]));
        }
    }
    poses
}

/// Real roots of A₀ + A₁v + A₂v² + A₃v³ + A₄v⁴ by Ferrari's method, each polished by Newton
/// steps on the original quartic (the closed form alone loses digits near double roots).
fn real_quartic_roots(coeffs: &[f64; 5]) -> Vec<f64> {
    let scale = coeffs.iter().fold(0.0_f64, |m, c| m.max(c.abs()));
    if scale == 0.0 || coeffs[4].abs() < DEGENERATE_LEADING * scale {
        return Vec::new();
    }
    // monic x⁴ + a x³ + b x² + c x + d, depressed by x = y − a/4: y⁴ + p y² + q y + r
    let [d, c, b, a] = [coeffs[0], coeffs[1], coeffs[2], coeffs[3]].map(|v| v / coeffs[4]);
    let a2 = a * a;
    let p = b - 3.0 * a2 / 8.0;
    let q = c - a * b / 2.0 + a2 * a / 8.0;
    let r = d - a * c / 4.0 + a2 * b / 16.0 - 3.0 * a2 * a2 / 256.0;
    let mut ys = Vec::with_capacity(4);
    if q.abs() <= BIQUADRATIC_TOLERANCE * (1.0 + p.abs() + r.abs()) {
        // y⁴ + p y² + r = 0: a quadratic in y²
        for z in real_quadratic_roots(1.0, p, r) {
            if z >= 0.0 {
                ys.push(z.sqrt());
                ys.push(-z.sqrt());
            }
        }
    } else {
        // resolvent cubic 8m³ + 8p m² + (2p² − 8r) m − q² = 0 has a root m > 0; then
        // (y² + p/2 + m)² = (√(2m) y − q/(2√(2m)))² splits into two quadratics
        let m = largest_real_cubic_root(p, p * p / 4.0 - r, -q * q / 8.0);
        if m > 0.0 {
            let s = (2.0 * m).sqrt();
            ys.extend(real_quadratic_roots(1.0, -s, p / 2.0 + m + q / (2.0 * s)));
            ys.extend(real_quadratic_roots(1.0, s, p / 2.0 + m - q / (2.0 * s)));
        }
    }
    let poly = |x: f64| (((x + a) * x + b) * x + c) * x + d;
    let dpoly = |x: f64| ((4.0 * x + 3.0 * a) * x + 2.0 * b) * x + c;
    ys.into_iter()
        .map(|y| {
            let mut x = y - a / 4.0;
            for _ in 0..NEWTON_STEPS {
                let slope = dpoly(x);
                if slope == 0.0 {
                    break;
                }
                x -= poly(x) / slope;
            }
            x
        })
        .filter(|x| x.is_finite())
        .collect()
}

/// Newton steps that polish each quartic root.
const NEWTON_STEPS: usize = 2;
/// |q| below this (relative) makes the depressed quartic biquadratic.
const BIQUADRATIC_TOLERANCE: f64 = 1e-14;

/// Real roots of α x² + β x + γ (stable form, no cancellation).
fn real_quadratic_roots(alpha: f64, beta: f64, gamma: f64) -> Vec<f64> {
    let disc = beta * beta - 4.0 * alpha * gamma;
    if disc < 0.0 {
        return Vec::new();
    }
    let t = -0.5 * (beta + beta.signum() * disc.sqrt());
    if t == 0.0 {
        return vec![0.0, 0.0];
    }
    vec![t / alpha, gamma / t]
}

/// The largest real root of m³ + e₂ m² + e₁ m + e₀ with (e₂, e₁, e₀) = (p, p²/4 − r, −q²/8),
/// i.e. the resolvent 8m³ + 8pm² + (2p² − 8r)m − q² divided by 8 (Cardano / Viète).
fn largest_real_cubic_root(e2: f64, e1: f64, e0: f64) -> f64 {
    // depress: m = t − e2/3 → t³ + P t + Q
    let shift = e2 / 3.0;
    let pp = e1 - e2 * e2 / 3.0;
    let qq = 2.0 * e2 * e2 * e2 / 27.0 - e2 * e1 / 3.0 + e0;
    let disc = qq * qq / 4.0 + pp * pp * pp / 27.0;
    let t = if disc > 0.0 {
        let sq = disc.sqrt();
        (-qq / 2.0 + sq).cbrt() + (-qq / 2.0 - sq).cbrt()
    } else if pp < 0.0 {
        // three real roots: the largest is 2√(−P/3) cos(⅓ acos(…))
        let rho = (-pp / 3.0).sqrt();
        let arg = (-qq / (2.0 * rho * rho * rho)).clamp(-1.0, 1.0);
        2.0 * rho * (arg.acos() / 3.0).cos()
    } else {
        (-qq).cbrt()
    };
    let mut m = t - shift;
    // one Newton step on the undepressed cubic
    let f = ((m + e2) * m + e1) * m + e0;
    let df = (3.0 * m + 2.0 * e2) * m + e1;
    if df != 0.0 {
        m -= f / df;
    }
    m
}

/// The orthonormal frame [e₁ e₂ e₃] of a triangle: e₁ along P₂ − P₁, e₃ normal to the
/// triangle, e₂ = e₃ × e₁. Two congruent triangles' frames differ by exactly the rotation
/// between them, so R_wc = F_world F_camᵀ (Kneip et al. 2011 use the same construction).
/// None for a degenerate (collinear) triangle.
fn triangle_frame(p: &[Vector3<f64>; 3]) -> Option<Matrix3<f64>> {
    let e1 = (p[1] - p[0]).try_normalize(f64::EPSILON)?;
    let e3 = e1.cross(&(p[2] - p[0])).try_normalize(f64::EPSILON)?;
    Some(Matrix3::from_columns(&[e1, e3.cross(&e1), e3]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    /// Against the eigenvalues of the companion matrix (an independent method) on random
    /// quartics with four real roots.
    #[test]
    fn quartic_roots_match_companion_eigenvalues() {
        let mut rng = SplitMix64::new(9);
        for _ in 0..500 {
            let roots: Vec<f64> = (0..4).map(|_| rng.uniform_in(-3.0, 3.0)).collect();
            let mut c = vec![1.0];
            for r in &roots {
                let mut next = vec![0.0; c.len() + 1];
                for (i, a) in c.iter().enumerate() {
                    next[i + 1] += a;
                    next[i] -= r * a;
                }
                c = next;
            }
            let lead = rng.uniform_in(0.5, 2.0);
            let coeffs = [c[0] * lead, c[1] * lead, c[2] * lead, c[3] * lead, c[4] * lead];
            let mut got = real_quartic_roots(&coeffs);
            let companion = nalgebra::Matrix4::new(
                0.0, 0.0, 0.0, -c[0], 1.0, 0.0, 0.0, -c[1], 0.0, 1.0, 0.0, -c[2], 0.0, 0.0, 1.0, -c[3],
            );
            let mut want: Vec<f64> = nalgebra::linalg::Schur::try_new(companion, f64::EPSILON, 500)
                .expect("converges")
                .complex_eigenvalues()
                .iter()
                .map(|z| z.re)
                .collect();
            got.sort_by(f64::total_cmp);
            want.sort_by(f64::total_cmp);
            assert_eq!(got.len(), 4, "{roots:?} → {got:?}");
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-6, "{got:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn quartic_roots_of_a_known_polynomial() {
        // (v − 1)(v − 2)(v + 3)(v² + 1)/(v² + 1) → use (v−1)(v−2)(v+3)(v−0.5)
        let roots = [1.0, 2.0, -3.0, 0.5];
        // expand Π (v − rᵢ)
        let mut c = vec![1.0];
        for r in roots {
            let mut next = vec![0.0; c.len() + 1];
            for (i, a) in c.iter().enumerate() {
                next[i + 1] += a;
                next[i] -= r * a;
            }
            c = next;
        }
        let mut got = real_quartic_roots(&[c[0], c[1], c[2], c[3], c[4]]);
        got.sort_by(f64::total_cmp);
        let mut want = roots;
        want.sort_by(f64::total_cmp);
        assert_eq!(got.len(), 4);
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-12, "{got:?}");
        }
        // v⁴ + 1 has no real root
        assert!(real_quartic_roots(&[1.0, 0.0, 0.0, 0.0, 1.0]).is_empty());
    }

    #[test]
    fn p3p_recovers_random_poses() {
        let mut rng = SplitMix64::new(42);
        let mut errors = Vec::new();
        for _ in 0..2000 {
            let world_from_cam = rng.pose(5.0);
            let cam_points: Vec<Vector3<f64>> = (0..3)
                .map(|_| Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-2.0, 2.0), rng.uniform_in(1.0, 8.0)))
                .collect();
            let world: [Vector3<f64>; 3] = std::array::from_fn(|i| world_from_cam * cam_points[i]);
            let bearings: [Vector3<f64>; 3] = std::array::from_fn(|i| cam_points[i].normalize());
            let solutions = p3p(&bearings, &world);
            let best =
                solutions.iter().map(|s| (s.inverse() * world_from_cam).log().norm()).fold(f64::INFINITY, f64::min);
            errors.push(best);
        }
        errors.sort_by(f64::total_cmp);
        // near-double roots (a nearly degenerate triangle) lose digits; RANSAC's local
        // optimization polishes those, so the tail only has to be close
        assert!(errors[1000] < 1e-10, "median {}", errors[1000]);
        assert!(errors[1980] < 1e-6, "99th percentile {}", errors[1980]);
        assert!(errors[1999] < 1e-2, "worst {}", errors[1999]);
    }

    #[test]
    fn triangle_frames_give_the_rotation_between_congruent_triangles() {
        let mut rng = SplitMix64::new(3);
        for _ in 0..100 {
            let t = rng.pose(10.0);
            let tri: [Vector3<f64>; 3] = std::array::from_fn(|_| rng.unit_vector() * 3.0);
            let moved = tri.map(|p| t * p);
            let r = triangle_frame(&moved).expect("non-degenerate")
                * triangle_frame(&tri).expect("non-degenerate").transpose();
            assert!((r - t.rotation.matrix()).abs().max() < 1e-12);
        }
        let line = [Vector3::zeros(), Vector3::x(), Vector3::x() * 2.0];
        assert!(triangle_frame(&line).is_none());
    }
}
