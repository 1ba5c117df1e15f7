//! Bindings of `geoloc_core::lie`: batched over rows, (N, in) float64 → (N, out) float64,
//! matrices flattened row-major. Shapes, dtypes and leading batch axes are handled by
//! `python/geoloc/lie.py`; these functions check widths, layout, finiteness and rotations.

use geoloc_core::lie::{SE3, SO3, Twist, check_rotation_vector, check_twist, se3, so3, try_rotation_angle};
use nalgebra::Vector3;
use numpy::{PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::convert::{batch_len, fill_rows, matrix_from_row, row, rows, vector_from_row, write_matrix};

/// The row a value comes from, and whether the caller passed a single item (`single=True`
/// from `geoloc.lie`, no batch axis): errors then name the argument without an index.
#[derive(Clone, Copy)]
struct Row {
    index: usize,
    single: bool,
}

impl Row {
    /// `e` reported for argument `name` at this row (`name[i]`, or `name` for a single item).
    fn label(self, e: geoloc_core::GeolocError, name: &str) -> geoloc_core::GeolocError {
        if self.single { e.named(name) } else { e.at(name, self.index) }
    }
}

/// One 9-value row as a rotation, strictly checked.
fn rotation_of(name: &str, x: &[f64; 9], i: Row) -> geoloc_core::Result<SO3> {
    SO3::from_matrix(&matrix_from_row::<3, 3>(x)).map_err(|e| i.label(e, name))
}

/// One 16-value row as a rigid transform, strictly checked.
fn pose_of(name: &str, x: &[f64; 16], i: Row) -> geoloc_core::Result<SE3> {
    SE3::from_matrix(&matrix_from_row::<4, 4>(x)).map_err(|e| i.label(e, name))
}

/// One 3-value row as a rotation vector within the exponential map's range.
fn phi_of(x: &[f64; 3], i: Row) -> geoloc_core::Result<Vector3<f64>> {
    let phi = vector_from_row(x);
    check_rotation_vector(&phi).map_err(|e| i.label(e, "phi"))?;
    Ok(phi)
}

/// One 6-value row as a twist within the exponential map's range.
fn xi_of(x: &[f64; 6], i: Row) -> geoloc_core::Result<Twist> {
    let xi = vector_from_row(x);
    check_twist(&xi).map_err(|e| i.label(e, "xi"))?;
    Ok(xi)
}

/// [`phi_of`], refused where J_l(φ) is singular ([`so3::check_jacobian_invertible`]).
fn invertible_phi_of(x: &[f64; 3], i: Row) -> geoloc_core::Result<Vector3<f64>> {
    let phi = phi_of(x, i)?;
    so3::check_jacobian_invertible(&phi).map_err(|e| i.label(e, "phi"))?;
    Ok(phi)
}

/// [`xi_of`], refused where 𝒥_l(ξ) is singular (its rotation part's J_l,
/// [`so3::check_jacobian_invertible`]).
fn invertible_xi_of(x: &[f64; 6], i: Row) -> geoloc_core::Result<Twist> {
    let xi = xi_of(x, i)?;
    so3::check_jacobian_invertible(&se3::phi(&xi)).map_err(|e| i.label(e, "xi"))?;
    Ok(xi)
}

/// Row `i` of a flat (N, 16) slice as a rigid transform.
fn pose_at(name: &str, values: &[f64], i: Row) -> geoloc_core::Result<SE3> {
    pose_of(name, row::<16>(values, i.index), i)
}

/// Defines a `#[pyfunction]` mapping each row of one (N, IN) array to a row of (N, OUT).
macro_rules! unary {
    ($(#[$doc:meta])* fn $name:ident($arg:ident: $width_in:literal) -> $width_out:literal
        = |$i:ident, $x:ident, $out:ident| $body:block) => {
        $(#[$doc])*
        #[pyfunction]
        #[pyo3(signature = ($arg, *, single=false))]
        pub fn $name<'py>(
            py: Python<'py>,
            $arg: PyReadonlyArray2<'py, f64>,
            single: bool,
        ) -> PyResult<Bound<'py, PyArray2<f64>>> {
            let values = rows::<$width_in>(stringify!($arg), &$arg)?;
            fill_rows::<$width_out, _>(py, values.len() / $width_in, |index, $out| {
                let $x = row::<$width_in>(values, index);
                #[allow(unused_variables)]
                let $i = Row { index, single };
                $body
            })
        }
    };
}

unary! {
    /// φ^ of each row φ.
    fn so3_hat(phi: 3) -> 9 = |_i, x, out| { write_matrix(&so3::hat(&vector_from_row(x)), out); Ok(()) }
}
unary! {
    /// The vee of the skew part of each 3×3 row.
    fn so3_vee(m: 9) -> 3 = |_i, x, out| {
        write_matrix(&so3::vee(&matrix_from_row::<3, 3>(x)), out);
        Ok(())
    }
}
unary! {
    /// exp(φ^) of each row φ.
    fn so3_exp(phi: 3) -> 9 = |i, x, out| { write_matrix(SO3::exp(&phi_of(x, i)?).matrix(), out); Ok(()) }
}
unary! {
    /// log(R)^∨ of each rotation row.
    fn so3_log(rotation: 9) -> 3 = |i, x, out| {
        write_matrix(&rotation_of("R", x, i)?.log(), out);
        Ok(())
    }
}
unary! {
    /// The rotation nearest to each 3×3 row (SVD / polar factor).
    fn so3_project(m: 9) -> 9 = |i, x, out| {
        let r = SO3::from_matrix_projected(&matrix_from_row::<3, 3>(x)).map_err(|e| i.label(e, "R"))?;
        write_matrix(r.matrix(), out);
        Ok(())
    }
}
unary! {
    /// Θ(R) ∈ [0, π] of each 3×3 row (atan2 form; near-rotations within 1e-2 accepted,
    /// other matrices refused).
    fn rotation_angle(rotation: 9) -> 1 = |i, x, out| {
        out[0] = try_rotation_angle(&matrix_from_row::<3, 3>(x)).map_err(|e| i.label(e, "R"))?;
        Ok(())
    }
}
unary! {
    /// Unit quaternion (w, x, y, z) of each rotation row.
    fn so3_to_quaternion_wxyz(rotation: 9) -> 4 = |i, x, out| {
        out.copy_from_slice(&rotation_of("R", x, i)?.to_quaternion_wxyz());
        Ok(())
    }
}
unary! {
    /// Rotation of each quaternion row (w, x, y, z), normalized first.
    fn so3_from_quaternion_wxyz(q: 4) -> 9 = |i, x, out| {
        let r = SO3::from_quaternion_wxyz(*x).map_err(|e| i.label(e, "q"))?;
        write_matrix(r.matrix(), out);
        Ok(())
    }
}
unary! {
    /// J_l(φ) of each row.
    fn so3_left_jacobian(phi: 3) -> 9 = |i, x, out| { write_matrix(&so3::left_jacobian(&phi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// J_r(φ) of each row.
    fn so3_right_jacobian(phi: 3) -> 9 = |i, x, out| { write_matrix(&so3::right_jacobian(&phi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// J_l⁻¹(φ) of each row.
    fn so3_left_jacobian_inv(phi: 3) -> 9 = |i, x, out| { write_matrix(&so3::left_jacobian_inverse(&invertible_phi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// J_r⁻¹(φ) of each row.
    fn so3_right_jacobian_inv(phi: 3) -> 9 = |i, x, out| { write_matrix(&so3::right_jacobian_inverse(&invertible_phi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// ξ^ (4×4) of each twist row (ρ, φ).
    fn se3_hat(xi: 6) -> 16 = |_i, x, out| { write_matrix(&se3::hat(&vector_from_row(x)), out); Ok(()) }
}
unary! {
    /// The twist of each 4×4 row of se(3).
    fn se3_vee(m: 16) -> 6 = |_i, x, out| { write_matrix(&se3::vee(&matrix_from_row::<4, 4>(x)), out); Ok(()) }
}
unary! {
    /// ad(ξ) (6×6) of each twist row.
    fn se3_curly_hat(xi: 6) -> 36 = |_i, x, out| { write_matrix(&se3::curly_hat(&vector_from_row(x)), out); Ok(()) }
}
unary! {
    /// exp(ξ^) of each twist row (ρ, φ).
    fn se3_exp(xi: 6) -> 16 = |i, x, out| { write_matrix(&SE3::exp(&xi_of(x, i)?).matrix(), out); Ok(()) }
}
unary! {
    /// log(T)^∨ = (ρ, φ) of each rigid-transform row.
    fn se3_log(pose: 16) -> 6 = |i, x, out| {
        write_matrix(&pose_of("T", x, i)?.log(), out);
        Ok(())
    }
}
unary! {
    /// T⁻¹ of each rigid-transform row.
    fn se3_inverse(pose: 16) -> 16 = |i, x, out| {
        write_matrix(&pose_of("T", x, i)?.inverse().matrix(), out);
        Ok(())
    }
}
unary! {
    /// Ad(T) (6×6) of each rigid-transform row.
    fn se3_adjoint(pose: 16) -> 36 = |i, x, out| {
        write_matrix(&pose_of("T", x, i)?.adjoint(), out);
        Ok(())
    }
}
unary! {
    /// Each 4×4 row with its rotation block projected onto SO(3).
    fn se3_project(pose: 16) -> 16 = |i, x, out| {
        let t = SE3::from_matrix_projected(&matrix_from_row::<4, 4>(x)).map_err(|e| i.label(e, "T"))?;
        write_matrix(&t.matrix(), out);
        Ok(())
    }
}
unary! {
    /// 𝒥_l(ξ) of each twist row.
    fn se3_left_jacobian(xi: 6) -> 36 = |i, x, out| { write_matrix(&se3::left_jacobian(&xi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// 𝒥_r(ξ) of each twist row.
    fn se3_right_jacobian(xi: 6) -> 36 = |i, x, out| { write_matrix(&se3::right_jacobian(&xi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// 𝒥_l⁻¹(ξ) of each twist row.
    fn se3_left_jacobian_inv(xi: 6) -> 36 = |i, x, out| { write_matrix(&se3::left_jacobian_inverse(&invertible_xi_of(x, i)?), out); Ok(()) }
}
unary! {
    /// 𝒥_r⁻¹(ξ) of each twist row.
    fn se3_right_jacobian_inv(xi: 6) -> 36 = |i, x, out| { write_matrix(&se3::right_jacobian_inverse(&invertible_xi_of(x, i)?), out); Ok(()) }
}

/// T₁T₂ for each pair of rows.
#[pyfunction]
#[pyo3(signature = (pose1, pose2, *, single=false))]
pub fn se3_compose<'py>(
    py: Python<'py>,
    pose1: PyReadonlyArray2<'py, f64>,
    pose2: PyReadonlyArray2<'py, f64>,
    single: bool,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let n = batch_len(&[("T1", pose1.shape()[0]), ("T2", pose2.shape()[0])])?;
    let (a, b) = (rows::<16>("T1", &pose1)?, rows::<16>("T2", &pose2)?);
    fill_rows::<16, _>(py, n, |index, out| {
        let i = Row { index, single };
        write_matrix(&(pose_at("T1", a, i)? * pose_at("T2", b, i)?).matrix(), out);
        Ok(())
    })
}

/// d(T₁, T₂) = ‖log(T₁⁻¹T₂)^∨‖ for each pair of rows, as (N, 1).
#[pyfunction]
#[pyo3(signature = (pose1, pose2, *, single=false))]
pub fn se3_distance<'py>(
    py: Python<'py>,
    pose1: PyReadonlyArray2<'py, f64>,
    pose2: PyReadonlyArray2<'py, f64>,
    single: bool,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let n = batch_len(&[("T1", pose1.shape()[0]), ("T2", pose2.shape()[0])])?;
    let (a, b) = (rows::<16>("T1", &pose1)?, rows::<16>("T2", &pose2)?);
    fill_rows::<1, _>(py, n, |index, out| {
        let i = Row { index, single };
        out[0] = pose_at("T1", a, i)?.distance(&pose_at("T2", b, i)?);
        Ok(())
    })
}

/// T₁ exp(α log(T₁⁻¹T₂)) for each pair of rows and each α (N, 1).
#[pyfunction]
#[pyo3(signature = (pose1, pose2, alpha, *, single=false))]
pub fn se3_interpolate<'py>(
    py: Python<'py>,
    pose1: PyReadonlyArray2<'py, f64>,
    pose2: PyReadonlyArray2<'py, f64>,
    alpha: PyReadonlyArray2<'py, f64>,
    single: bool,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let n = batch_len(&[("T1", pose1.shape()[0]), ("T2", pose2.shape()[0]), ("alpha", alpha.shape()[0])])?;
    let (a, b) = (rows::<16>("T1", &pose1)?, rows::<16>("T2", &pose2)?);
    let alpha = rows::<1>("alpha", &alpha)?;
    fill_rows::<16, _>(py, n, |index, out| {
        let i = Row { index, single };
        let t = pose_at("T1", a, i)?.checked_interpolate(&pose_at("T2", b, i)?, alpha[index])?;
        write_matrix(&t.matrix(), out);
        Ok(())
    })
}

/// T p = R p + t for each pose row and point row.
#[pyfunction]
#[pyo3(signature = (pose, points, *, single=false))]
pub fn se3_transform_points<'py>(
    py: Python<'py>,
    pose: PyReadonlyArray2<'py, f64>,
    points: PyReadonlyArray2<'py, f64>,
    single: bool,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let n = batch_len(&[("T", pose.shape()[0]), ("points", points.shape()[0])])?;
    let (t, p) = (rows::<16>("T", &pose)?, rows::<3>("points", &points)?);
    fill_rows::<3, _>(py, n, |index, out| {
        let i = Row { index, single };
        write_matrix(&(pose_at("T", t, i)? * vector_from_row(row::<3>(p, index))), out);
        Ok(())
    })
}

/// Registers the functions of this file on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(so3_hat, m)?)?;
    m.add_function(wrap_pyfunction!(so3_vee, m)?)?;
    m.add_function(wrap_pyfunction!(so3_exp, m)?)?;
    m.add_function(wrap_pyfunction!(so3_log, m)?)?;
    m.add_function(wrap_pyfunction!(so3_project, m)?)?;
    m.add_function(wrap_pyfunction!(rotation_angle, m)?)?;
    m.add_function(wrap_pyfunction!(so3_to_quaternion_wxyz, m)?)?;
    m.add_function(wrap_pyfunction!(so3_from_quaternion_wxyz, m)?)?;
    m.add_function(wrap_pyfunction!(so3_left_jacobian, m)?)?;
    m.add_function(wrap_pyfunction!(so3_right_jacobian, m)?)?;
    m.add_function(wrap_pyfunction!(so3_left_jacobian_inv, m)?)?;
    m.add_function(wrap_pyfunction!(so3_right_jacobian_inv, m)?)?;
    m.add_function(wrap_pyfunction!(se3_hat, m)?)?;
    m.add_function(wrap_pyfunction!(se3_vee, m)?)?;
    m.add_function(wrap_pyfunction!(se3_curly_hat, m)?)?;
    m.add_function(wrap_pyfunction!(se3_exp, m)?)?;
    m.add_function(wrap_pyfunction!(se3_log, m)?)?;
    m.add_function(wrap_pyfunction!(se3_inverse, m)?)?;
    m.add_function(wrap_pyfunction!(se3_adjoint, m)?)?;
    m.add_function(wrap_pyfunction!(se3_project, m)?)?;
    m.add_function(wrap_pyfunction!(se3_left_jacobian, m)?)?;
    m.add_function(wrap_pyfunction!(se3_right_jacobian, m)?)?;
    m.add_function(wrap_pyfunction!(se3_left_jacobian_inv, m)?)?;
    m.add_function(wrap_pyfunction!(se3_right_jacobian_inv, m)?)?;
    m.add_function(wrap_pyfunction!(se3_compose, m)?)?;
    m.add_function(wrap_pyfunction!(se3_distance, m)?)?;
    m.add_function(wrap_pyfunction!(se3_interpolate, m)?)?;
    m.add_function(wrap_pyfunction!(se3_transform_points, m)?)?;
    Ok(())
}
