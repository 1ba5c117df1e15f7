//! The pose lines `geoloc-rs localize` writes.
//!
//! ```text
//! # timestamp tx ty tz qx qy qz qw source cov_upper_21(row-major, right perturbation, translation first); pose: …
//! t tx ty tz qx qy qz qw source c11 c12 c13 c14 c15 c16 c22 c23 … c66
//! ```
//! The first eight columns are the TUM trajectory format (world_from_cam: the camera centre
//! and the unit quaternion x, y, z, w with w ≥ 0), so evo and other TUM tools read the file
//! as it is. Then the source (`geometric`, `fused`, `motion` or `lost`) and the 21 entries
//! of the upper triangle of the 6×6 covariance, row by row (right perturbation
//! T·exp(δ^), δ = (ρ, φ): translation first). A `lost` frame has `nan` in every pose and
//! covariance column (TUM readers such as numpy's `loadtxt` read it; drop those rows before
//! evaluating). Every number is written in the shortest form that reads back to the same
//! f64 bits (pose columns plain decimal, covariance entries in scientific notation).

use std::fmt::Write as _;

use geoloc_core::localizer::{Localization, Source};

/// The header comment line (without the newline): the columns, then which pose they hold —
/// the camera's own (`camera_pose`) or the pose in the convention of the map's labels — so
/// that a logged file says which frame it is in.
pub fn header(camera_pose: bool) -> String {
    let pose = if camera_pose {
        "world_from_cam: the camera's own pose"
    } else {
        "world_from_cam in the convention of the map's pose labels"
    };
    format!(
        "# timestamp tx ty tz qx qy qz qw source cov_upper_21(row-major, right perturbation, translation first); pose: {pose}"
    )
}

/// Number of upper-triangle entries of a 6×6 matrix.
pub const COV_ENTRIES: usize = 21;

/// One frame's line (without the newline).
pub fn line(timestamp: f64, result: &Localization) -> String {
    let mut s = format!("{timestamp}");
    match &result.estimate {
        Some(e) => {
            let t = e.world_from_cam.translation;
            let [mut w, mut x, mut y, mut z] = e.world_from_cam.rotation.to_quaternion_wxyz();
            if w < 0.0 {
                (w, x, y, z) = (-w, -x, -y, -z);
            }
            for v in [t.x, t.y, t.z, x, y, z, w] {
                let _ = write!(s, " {v}");
            }
            let _ = write!(s, " {}", result.source);
            for i in 0..6 {
                for j in i..6 {
                    let _ = write!(s, " {:e}", e.covariance[(i, j)]);
                }
            }
        }
        None => {
            s.push_str(&" nan".repeat(7));
            let _ = write!(s, " {}", Source::Lost);
            s.push_str(&" nan".repeat(COV_ENTRIES));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use geoloc_core::lie::SE3;
    use geoloc_core::localizer::{Estimate, Timings};
    use nalgebra::{Matrix6, Vector6};

    fn result(estimate: Option<Estimate>, source: Source) -> Localization {
        let reason = String::new();
        Localization {
            estimate,
            source,
            reason,
            keyframe: 0,
            inliers: 0,
            map_noise_scale: 1.0,
            novelty: None,
            timings: Timings::default(),
        }
    }

    #[test]
    fn numbers_read_back_bit_exactly_and_the_quaternion_has_w_nonnegative() {
        let pose = SE3::exp(&Vector6::new(0.1, -2.0 / 3.0, 1e-17, 3.0, 0.2, -0.1));
        let mut cov = Matrix6::from_fn(|i, j| 1e-7 / (1.0 + (i + j) as f64));
        cov[(0, 5)] = 1.0 / 3.0;
        let text = line(
            1305031102.175304,
            &result(Some(Estimate { world_from_cam: pose, covariance: cov, pixel_covariance: cov }), Source::Fused),
        );
        let cols: Vec<&str> = text.split(' ').collect();
        assert_eq!(cols.len(), 8 + 1 + COV_ENTRIES);
        assert_eq!(cols[8], "fused");
        let num = |i: usize| cols[i].parse::<f64>().expect("a number");
        assert_eq!(num(0).to_bits(), 1305031102.175304f64.to_bits());
        assert_eq!(num(3).to_bits(), pose.translation.z.to_bits());
        assert!(num(7) >= 0.0);
        let q = pose.rotation.to_quaternion_wxyz();
        let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
        assert_eq!(num(4).to_bits(), (sign * q[1]).to_bits());
        assert_eq!(num(9 + 5).to_bits(), cov[(0, 5)].to_bits());
        assert_eq!(num(9 + 6).to_bits(), cov[(1, 1)].to_bits()); // row 2 starts at c22
        assert_eq!(num(9 + 20).to_bits(), cov[(5, 5)].to_bits());
    }

    #[test]
    fn a_lost_frame_is_nan_columns_with_the_source_lost() {
        let text = line(2.5, &result(None, Source::Lost));
        let cols: Vec<&str> = text.split(' ').collect();
        assert_eq!(cols.len(), 30);
        assert_eq!(cols[0], "2.5");
        assert_eq!(cols[8], "lost");
        assert!(cols[1..8].iter().chain(&cols[9..]).all(|c| *c == "nan"));
    }
}
