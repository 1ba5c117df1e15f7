//! One generic Levenberg–Marquardt for small problems on manifolds (D ≤ 6 parameters).
//!
//! The problem supplies the Gauss–Newton normal equations H = Σ Jᵀ W J, g = Σ Jᵀ W r and the
//! robust cost at a state (IRLS: W includes the robust weights of the current residuals),
//! and the retraction x ⊞ δ. Each iteration solves (H + λ·diag(H)) δ = −g; a step that
//! lowers the cost is taken and λ shrinks, otherwise λ grows. Not converging is not an
//! error: the solver returns its best state and a report.

use nalgebra::{SMatrix, SVector};

/// A least-squares problem in D local parameters.
pub trait LeastSquares<const D: usize> {
    /// The state the parameters perturb (a point, a pose).
    type State: Clone;
    /// (H, g, cost) at `state`, with H = Σ Jᵀ W J, g = Σ Jᵀ W r.
    fn normal_equations(&self, state: &Self::State) -> (SMatrix<f64, D, D>, SVector<f64, D>, f64);
    /// state ⊞ δ.
    fn retract(&self, state: &Self::State, delta: &SVector<f64, D>) -> Self::State;
}

/// Options of [`levenberg_marquardt`], with documented defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LmOptions {
    /// Iteration cap (default 50).
    pub max_iterations: usize,
    /// Initial damping λ relative to diag(H) (default 1e-4).
    pub initial_lambda: f64,
    /// Stop when a step lowers the cost — or the quadratic model predicts it would — by less
    /// than this fraction (default 1e-12).
    pub cost_tolerance: f64,
    /// Stop when ‖δ‖ falls below this (default 1e-12; metres/radians for our problems).
    pub step_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self { max_iterations: 50, initial_lambda: 1e-4, cost_tolerance: 1e-12, step_tolerance: 1e-12 }
    }
}

/// Why the solver stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// The relative cost decrease fell below the tolerance.
    CostConverged,
    /// The step fell below the tolerance.
    StepConverged,
    /// No step lowers the cost any more (λ reached its cap): a minimum to working precision.
    NoDescent,
    /// The iteration cap was hit.
    MaxIterations,
    /// The cost or the normal equations were not finite.
    NonFinite,
}

/// What the solver did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LmReport {
    /// Iterations run.
    pub iterations: usize,
    /// Cost at the start.
    pub initial_cost: f64,
    /// Cost at the returned state.
    pub final_cost: f64,
    /// Why it stopped.
    pub termination: Termination,
}

impl LmReport {
    /// Whether the stop means convergence (not an iteration cap or non-finite numbers).
    pub fn converged(&self) -> bool {
        matches!(self.termination, Termination::CostConverged | Termination::StepConverged | Termination::NoDescent)
    }
}

const MAX_LAMBDA: f64 = 1e12;
const MIN_LAMBDA: f64 = 1e-12;
/// Floor of the damping diagonal, so a zero curvature direction is still damped.
const MIN_DIAGONAL: f64 = 1e-12;

/// Minimizes `problem` from `state`; see the module doc.
pub fn levenberg_marquardt<P, const D: usize>(problem: &P, state: P::State, options: &LmOptions) -> (P::State, LmReport)
where
    P: LeastSquares<D>,
{
    let (x, report, _) = levenberg_marquardt_with_information(problem, state, options);
    (x, report)
}

/// [`levenberg_marquardt`], also returning the undamped H = Σ JᵀWJ at the returned state
/// (the information matrix a covariance is built from, without another pass over the data).
pub fn levenberg_marquardt_with_information<P, const D: usize>(
    problem: &P,
    state: P::State,
    options: &LmOptions,
) -> (P::State, LmReport, SMatrix<f64, D, D>)
where
    P: LeastSquares<D>,
{
    let mut x = state;
    let (mut h, mut g, mut cost) = problem.normal_equations(&x);
    let initial_cost = cost;
    let mut lambda = options.initial_lambda;
    let report = |iterations, final_cost, termination| LmReport { iterations, initial_cost, final_cost, termination };
    if !cost.is_finite() || !h.iter().all(|v| v.is_finite()) {
        return (x, report(0, cost, Termination::NonFinite), h);
    }
    for iteration in 1..=options.max_iterations {
        let mut damped = h;
        for i in 0..D {
            damped[(i, i)] += lambda * h[(i, i)].max(MIN_DIAGONAL);
        }
        let Some(chol) = damped.cholesky() else {
            lambda *= 10.0;
            if lambda > MAX_LAMBDA {
                return (x, report(iteration, cost, Termination::NoDescent), h);
            }
            continue;
        };
        let delta = chol.solve(&(-g));
        if delta.norm() < options.step_tolerance {
            return (x, report(iteration, cost, Termination::StepConverged), h);
        }
        // Half the quadratic model's predicted decrease, −(gᵀδ + ½δᵀHδ) (g is the
        // half-gradient of the cost): when even that is below the tolerance we are at the
        // minimum to working precision — stop here instead of raising λ through a dozen
        // rejected steps.
        let predicted = -(g.dot(&delta) + 0.5 * delta.dot(&(h * delta)));
        if predicted <= options.cost_tolerance * cost {
            return (x, report(iteration, cost, Termination::CostConverged), h);
        }
        let candidate = problem.retract(&x, &delta);
        // Linearize at the candidate right away: steps are mostly accepted, and this saves
        // the separate cost pass of each accepted step.
        let (new_h, new_g, new_cost) = problem.normal_equations(&candidate);
        if new_cost.is_finite() && new_cost < cost {
            let decrease = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
            x = candidate;
            (h, g, cost) = (new_h, new_g, new_cost);
            lambda = (lambda * 0.1).max(MIN_LAMBDA);
            if decrease < options.cost_tolerance {
                return (x, report(iteration, cost, Termination::CostConverged), h);
            }
        } else {
            lambda *= 10.0;
            if lambda > MAX_LAMBDA {
                return (x, report(iteration, cost, Termination::NoDescent), h);
            }
        }
    }
    (x, report(options.max_iterations, cost, Termination::MaxIterations), h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// Rosenbrock as least squares: r = (10(y − x²), 1 − x); minimum at (1, 1).
    struct Rosenbrock;

    impl LeastSquares<2> for Rosenbrock {
        type State = Vector2<f64>;
        fn normal_equations(&self, p: &Vector2<f64>) -> (Matrix2<f64>, Vector2<f64>, f64) {
            let r = Vector2::new(10.0 * (p.y - p.x * p.x), 1.0 - p.x);
            let j = Matrix2::new(-20.0 * p.x, 10.0, -1.0, 0.0);
            (j.transpose() * j, j.transpose() * r, r.norm_squared())
        }
        fn retract(&self, p: &Vector2<f64>, d: &Vector2<f64>) -> Vector2<f64> {
            p + d
        }
    }

    #[test]
    fn finds_the_rosenbrock_minimum() {
        let (x, report) = levenberg_marquardt(&Rosenbrock, Vector2::new(-1.2, 1.0), &LmOptions::default());
        assert!((x - Vector2::new(1.0, 1.0)).norm() < 1e-8, "{x:?} {report:?}");
        assert!(report.converged());
        assert!(report.final_cost < 1e-16 && report.initial_cost > 1.0);
    }

    #[test]
    fn reports_the_iteration_cap() {
        let options = LmOptions { max_iterations: 2, ..LmOptions::default() };
        let (_, report) = levenberg_marquardt(&Rosenbrock, Vector2::new(-1.2, 1.0), &options);
        assert_eq!(report.termination, Termination::MaxIterations);
        assert!(!report.converged());
    }

    #[test]
    fn non_finite_start_is_reported_not_panicked() {
        let (_, report) = levenberg_marquardt(&Rosenbrock, Vector2::new(f64::NAN, 1.0), &LmOptions::default());
        assert_eq!(report.termination, Termination::NonFinite);
    }
}
