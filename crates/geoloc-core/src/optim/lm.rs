//! One generic Levenberg–Marquardt / Gauss–Newton driver for small problems on manifolds
//! (D ≤ 12 local parameters), used by triangulation, PnP (including the joint
//! point-correction solve), the motion model and fusion.
//!
//! The problem supplies the Gauss–Newton normal equations H = Σ Jᵀ W J, g = Σ Jᵀ W r and the
//! robust cost at a state (IRLS: W includes the robust weights of the current residuals),
//! and the retraction x ⊞ δ. Each LM iteration solves (H + λ·diag(H)) δ = −g; a step that
//! lowers the cost is taken and λ shrinks, otherwise λ grows. Two hooks let a problem that
//! is not a plain D-parameter system (PnP with point corrections: a Schur complement over
//! the eliminated blocks) run through the same loop: [`LeastSquares::damped_step`] solves the
//! damped system its own way and [`LeastSquares::evaluate`] may return only the cost of a
//! candidate. With [`LmOptions::gauss_newton`] the loop is plain Gauss–Newton: λ = 0 and every
//! step is taken. Not converging is not an error: the driver returns its best state and a
//! report.

use nalgebra::{SMatrix, SVector};

/// The normal equations of a problem at a state: H = Σ JᵀWJ and g = Σ JᵀWr (g is half the
/// gradient of the cost Σ rᵀWr).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Linearization<const D: usize> {
    /// H = Σ JᵀWJ (undamped).
    pub h: SMatrix<f64, D, D>,
    /// g = Σ JᵀWr.
    pub g: SVector<f64, D>,
}

/// A problem evaluated at a state: its cost, and its normal equations unless the problem
/// solves its damped system itself and only needs the cost ([`LeastSquares::evaluate`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Evaluation<const D: usize> {
    /// The (robust) cost.
    pub cost: f64,
    /// The normal equations, if computed.
    pub linearization: Option<Linearization<D>>,
}

/// The outcome of one damped solve.
#[derive(Clone, Debug, PartialEq)]
pub enum DampedStep<S> {
    /// The damped system is not positive definite: the driver raises λ.
    NotPositiveDefinite,
    /// The system could not be formed (a singular block, non-finite numbers).
    NonFinite,
    /// A step δ, the decrease of the cost the local quadratic model predicts for it (halved:
    /// −(gᵀδ + ½δᵀHδ)) and the candidate state x ⊞ δ.
    Step {
        /// ‖δ‖.
        norm: f64,
        /// The model's predicted decrease (half the cost units, as above).
        predicted_decrease: f64,
        /// x ⊞ δ.
        candidate: S,
    },
}

/// A least-squares problem in D local parameters.
pub trait LeastSquares<const D: usize> {
    /// The state the parameters perturb (a point, a pose, a pose and point corrections).
    type State: Clone;

    /// (H, g, cost) at `state`, with H = Σ Jᵀ W J, g = Σ Jᵀ W r.
    fn normal_equations(&self, state: &Self::State) -> (SMatrix<f64, D, D>, SVector<f64, D>, f64);

    /// state ⊞ δ.
    fn retract(&self, state: &Self::State, delta: &SVector<f64, D>) -> Self::State;

    /// The problem at `state` (default: the normal equations and the cost).
    fn evaluate(&self, state: &Self::State) -> Evaluation<D> {
        let (h, g, cost) = self.normal_equations(state);
        Evaluation { cost, linearization: Some(Linearization { h, g }) }
    }

    /// Hook: solves the damped system at `state` with damping `lambda`. The default solves
    /// (H + λ·diag(max(H_ii, 1e-12))) δ = −g by Cholesky with the normal equations of the
    /// last [`LeastSquares::evaluate`] and retracts.
    fn damped_step(
        &self,
        state: &Self::State,
        linearization: Option<&Linearization<D>>,
        lambda: f64,
    ) -> DampedStep<Self::State> {
        let Some(Linearization { h, g }) = linearization else { return DampedStep::NonFinite };
        let mut damped = *h;
        for i in 0..D {
            damped[(i, i)] += lambda * h[(i, i)].max(MIN_DIAGONAL);
        }
        let Some(chol) = damped.cholesky() else { return DampedStep::NotPositiveDefinite };
        let delta = chol.solve(&(-g));
        // Half the quadratic model's predicted decrease, −(gᵀδ + ½δᵀHδ) (g is the
        // half-gradient of the cost).
        let predicted_decrease = -(g.dot(&delta) + 0.5 * delta.dot(&(h * delta)));
        DampedStep::Step { norm: delta.norm(), predicted_decrease, candidate: self.retract(state, &delta) }
    }
}

/// Options of [`levenberg_marquardt`], with documented defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LmOptions {
    /// Iteration cap (default 50).
    pub max_iterations: usize,
    /// Initial damping λ relative to diag(H) (default 1e-4).
    pub initial_lambda: f64,
    /// Stop when a step lowers the cost — or the quadratic model predicts it would — by less
    /// than this fraction (default 1e-12). Unused by Gauss–Newton.
    pub cost_tolerance: f64,
    /// Stop when ‖δ‖ falls below this (default 1e-12; metres/radians for our problems).
    pub step_tolerance: f64,
    /// Plain Gauss–Newton instead of LM (default false): λ = 0, every step is taken, and the
    /// loop stops after a step shorter than `step_tolerance`, when H is singular, or at the cap.
    pub gauss_newton: bool,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            initial_lambda: 1e-4,
            cost_tolerance: 1e-12,
            step_tolerance: 1e-12,
            gauss_newton: false,
        }
    }
}

impl LmOptions {
    /// Gauss–Newton with an iteration cap and a step tolerance (see [`LmOptions::gauss_newton`]).
    pub fn gauss_newton(max_iterations: usize, step_tolerance: f64) -> Self {
        Self { max_iterations, step_tolerance, gauss_newton: true, initial_lambda: 0.0, ..Self::default() }
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
    /// Gauss–Newton only: H is singular, no step could be taken.
    Singular,
}

impl Termination {
    /// A short lower-case name ("cost_converged", …).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::CostConverged => "cost_converged",
            Self::StepConverged => "step_converged",
            Self::NoDescent => "no_descent",
            Self::MaxIterations => "max_iterations",
            Self::NonFinite => "non_finite",
            Self::Singular => "singular",
        }
    }
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
    /// Whether the stop means convergence (not an iteration cap, a singular system or
    /// non-finite numbers).
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
    let (x, report, _) = solve(problem, state, options);
    (x, report)
}

/// [`levenberg_marquardt`], also returning the undamped H = Σ JᵀWJ at the returned state
/// (the information matrix a covariance is built from, without another pass over the data;
/// zeros for a problem whose [`LeastSquares::evaluate`] returns no normal equations).
pub fn levenberg_marquardt_with_information<P, const D: usize>(
    problem: &P,
    state: P::State,
    options: &LmOptions,
) -> (P::State, LmReport, SMatrix<f64, D, D>)
where
    P: LeastSquares<D>,
{
    let (x, report, evaluation) = solve(problem, state, options);
    (x, report, evaluation.linearization.map_or_else(SMatrix::zeros, |l| l.h))
}

/// The one driver: LM or Gauss–Newton per `options`; returns the state, the report and the
/// evaluation at the returned state.
pub fn solve<P, const D: usize>(
    problem: &P,
    state: P::State,
    options: &LmOptions,
) -> (P::State, LmReport, Evaluation<D>)
where
    P: LeastSquares<D>,
{
    let evaluation = problem.evaluate(&state);
    let finite = evaluation.cost.is_finite()
        && evaluation.linearization.is_none_or(|l| l.h.iter().chain(l.g.iter()).all(|v| v.is_finite()));
    if !finite {
        let report = LmReport {
            iterations: 0,
            initial_cost: evaluation.cost,
            final_cost: evaluation.cost,
            termination: Termination::NonFinite,
        };
        return (state, report, evaluation);
    }
    let (mut x, mut current) = (state, evaluation);
    let initial_cost = current.cost;
    let mut lambda = if options.gauss_newton { 0.0 } else { options.initial_lambda };
    let report = |iterations, final_cost, termination| LmReport { iterations, initial_cost, final_cost, termination };
    for iteration in 1..=options.max_iterations {
        let step = problem.damped_step(&x, current.linearization.as_ref(), lambda);
        let stop = if options.gauss_newton {
            gauss_newton_step(problem, step, &mut x, &mut current, options)
        } else {
            lm_step(problem, step, &mut x, &mut current, &mut lambda, options)
        };
        if let Some(termination) = stop {
            return (x, report(iteration, current.cost, termination), current);
        }
    }
    (x, report(options.max_iterations, current.cost, Termination::MaxIterations), current)
}

/// One LM iteration: take the step if it lowers the cost (λ shrinks), else grow λ. Returns
/// why to stop, if the loop should.
fn lm_step<P, const D: usize>(
    problem: &P,
    step: DampedStep<P::State>,
    x: &mut P::State,
    current: &mut Evaluation<D>,
    lambda: &mut f64,
    options: &LmOptions,
) -> Option<Termination>
where
    P: LeastSquares<D>,
{
    let raise = |lambda: &mut f64| {
        *lambda *= 10.0;
        (*lambda > MAX_LAMBDA).then_some(Termination::NoDescent)
    };
    let (norm, predicted_decrease, candidate) = match step {
        DampedStep::Step { norm, predicted_decrease, candidate } => (norm, predicted_decrease, candidate),
        DampedStep::NonFinite => return Some(Termination::NonFinite),
        DampedStep::NotPositiveDefinite => return raise(lambda),
    };
    if norm < options.step_tolerance {
        return Some(Termination::StepConverged);
    }
    // When even the model's predicted decrease is below the tolerance we are at the minimum
    // to working precision — stop here instead of raising λ through a dozen rejected steps.
    if predicted_decrease <= options.cost_tolerance * current.cost {
        return Some(Termination::CostConverged);
    }
    // Evaluate the candidate right away (for plain problems: linearize it): steps are mostly
    // accepted, and this saves the separate cost pass of each accepted step.
    let next = problem.evaluate(&candidate);
    if !(next.cost.is_finite() && next.cost < current.cost) {
        return raise(lambda);
    }
    let decrease = (current.cost - next.cost) / current.cost.max(f64::MIN_POSITIVE);
    (*x, *current) = (candidate, next);
    *lambda = (*lambda * 0.1).max(MIN_LAMBDA);
    (decrease < options.cost_tolerance).then_some(Termination::CostConverged)
}

/// One Gauss–Newton iteration: the undamped step is always taken; stop after one below the
/// tolerance, or when H is singular.
fn gauss_newton_step<P, const D: usize>(
    problem: &P,
    step: DampedStep<P::State>,
    x: &mut P::State,
    current: &mut Evaluation<D>,
    options: &LmOptions,
) -> Option<Termination>
where
    P: LeastSquares<D>,
{
    let (norm, candidate) = match step {
        DampedStep::Step { norm, candidate, .. } => (norm, candidate),
        DampedStep::NonFinite => return Some(Termination::NonFinite),
        DampedStep::NotPositiveDefinite => return Some(Termination::Singular),
    };
    *x = candidate;
    *current = problem.evaluate(x);
    (norm < options.step_tolerance).then_some(Termination::StepConverged)
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

    /// Gauss–Newton on a linear problem: one step to the exact minimum, a second (zero) step
    /// ends the loop.
    #[test]
    fn gauss_newton_solves_a_linear_problem_in_one_step() {
        struct Linear;
        impl LeastSquares<2> for Linear {
            type State = Vector2<f64>;
            fn normal_equations(&self, p: &Vector2<f64>) -> (Matrix2<f64>, Vector2<f64>, f64) {
                let j = Matrix2::new(2.0, 1.0, 0.0, 3.0);
                let r = j * p - Vector2::new(1.0, 2.0);
                (j.transpose() * j, j.transpose() * r, r.norm_squared())
            }
            fn retract(&self, p: &Vector2<f64>, d: &Vector2<f64>) -> Vector2<f64> {
                p + d
            }
        }
        let (x, report) = levenberg_marquardt(&Linear, Vector2::new(5.0, -5.0), &LmOptions::gauss_newton(20, 1e-12));
        // closed form: J x = b
        assert!((x - Vector2::new(1.0 / 6.0, 2.0 / 3.0)).norm() < 1e-14, "{x:?}");
        assert_eq!(report.termination, Termination::StepConverged);
        assert_eq!(report.iterations, 2);
        assert!(report.final_cost < 1e-28);
    }

    #[test]
    fn gauss_newton_reports_a_singular_system() {
        struct Flat;
        impl LeastSquares<2> for Flat {
            type State = Vector2<f64>;
            fn normal_equations(&self, _: &Vector2<f64>) -> (Matrix2<f64>, Vector2<f64>, f64) {
                (Matrix2::new(1.0, 0.0, 0.0, 0.0), Vector2::new(1.0, 0.0), 1.0)
            }
            fn retract(&self, p: &Vector2<f64>, d: &Vector2<f64>) -> Vector2<f64> {
                p + d
            }
        }
        let (_, report) = levenberg_marquardt(&Flat, Vector2::zeros(), &LmOptions::gauss_newton(20, 1e-12));
        assert_eq!(report.termination, Termination::Singular);
        assert!(!report.converged());
    }

    #[test]
    fn non_finite_start_is_reported_not_panicked() {
        let (_, report) = levenberg_marquardt(&Rosenbrock, Vector2::new(f64::NAN, 1.0), &LmOptions::default());
        assert_eq!(report.termination, Termination::NonFinite);
    }
}
