//! What a solve or an evaluation reports.
use super::options::LinearSolver;
use super::problem::PlaneFamily;

/// Why the solver stopped (Ceres' termination types).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TerminationType {
    /// A tolerance was reached.
    Convergence,
    /// The iteration or time limit was reached first.
    NoConvergence,
    /// The solver failed (e.g. the cost could not be evaluated at the start).
    Failure,
    UserSuccess,
    UserFailure,
}

impl TerminationType {
    pub(crate) fn from_code(code: i32) -> Self {
        match code {
            0 => TerminationType::Convergence,
            1 => TerminationType::NoConvergence,
            3 => TerminationType::UserSuccess,
            4 => TerminationType::UserFailure,
            _ => TerminationType::Failure,
        }
    }
}

/// A family of residuals sharing a robust loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum ResidualFamily {
    Reprojection,
    PosePrior,
    Plane(PlaneFamily),
}

impl ResidualFamily {
    /// Index on the bridge: 0 reprojection, 1 pose prior, 2 + plane family index.
    pub(crate) fn index(self) -> u32 {
        match self {
            ResidualFamily::Reprojection => 0,
            ResidualFamily::PosePrior => 1,
            ResidualFamily::Plane(f) => 2 + f.index(),
        }
    }

    pub(crate) fn from_index(index: u32) -> Option<Self> {
        match index {
            0 => Some(ResidualFamily::Reprojection),
            1 => Some(ResidualFamily::PosePrior),
            n => PlaneFamily::from_index(n - 2).map(ResidualFamily::Plane),
        }
    }
}

/// Cost of one residual family: `0.5 * sum rho(|r|^2)` as Ceres defines it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FamilyCost {
    pub family: ResidualFamily,
    pub num_residual_blocks: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
}

/// The outcome of [`super::solve`].
#[derive(Clone, Debug, PartialEq)]
pub struct SolveSummary {
    /// Ceres' cost `0.5 * sum rho(|r|^2)` before the solve.
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Levenberg-Marquardt iterations (successful and unsuccessful steps).
    pub num_iterations: usize,
    pub termination: TerminationType,
    /// Whether the parameters written back can be used (Ceres'
    /// `IsSolutionUsable` and a finite final cost). When false, the problem's
    /// parameters hold Ceres' last accepted state and should be discarded.
    pub usable: bool,
    /// Wall-clock time inside Ceres, seconds.
    pub time_s: f64,
    /// Ceres' message.
    pub message: String,
    /// The linear solver Ceres used (`None` when nothing was solved).
    pub linear_solver: Option<LinearSolver>,
    /// Per family present in the problem, in family order.
    pub families: Vec<FamilyCost>,
    /// Where the time went.
    pub times: SolveTimes,
    /// The Schur eliminator's block sizes, "row,e,f" ("d": dynamic, the
    /// slow general code); empty for other linear solvers.
    pub schur_structure: String,
}

/// Where a solve's time went, seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SolveTimes {
    /// Building the Ceres problem from the bridge's arrays (outside `time_s`).
    pub build_s: f64,
    /// Evaluating each residual family's cost before and after the solve
    /// (outside `time_s`).
    pub family_cost_s: f64,
    /// Ceres' preprocessing: ordering, structure detection (inside `time_s`).
    pub preprocessor_s: f64,
    /// Residuals alone, for the cost of trial steps (inside `time_s`).
    pub residual_s: f64,
    /// Residuals with Jacobians (inside `time_s`).
    pub jacobian_s: f64,
    /// Schur elimination and the linear solve (inside `time_s`).
    pub linear_solver_s: f64,
}

impl std::ops::AddAssign for SolveTimes {
    fn add_assign(&mut self, o: Self) {
        self.build_s += o.build_s;
        self.family_cost_s += o.family_cost_s;
        self.preprocessor_s += o.preprocessor_s;
        self.residual_s += o.residual_s;
        self.jacobian_s += o.jacobian_s;
        self.linear_solver_s += o.linear_solver_s;
    }
}

impl std::fmt::Display for SolveSummary {
    /// One line for logs: costs, iterations, time, solver, outcome, and the
    /// final cost of each family.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "cost {:.4e} -> {:.4e} in {} iterations ({:.3} s, {:?}, {:?}{})",
            self.initial_cost,
            self.final_cost,
            self.num_iterations,
            self.time_s,
            self.linear_solver,
            self.termination,
            if self.usable { "" } else { ", NOT usable" }
        )?;
        for family in &self.families {
            write!(
                f,
                "; {:?} x{}: {:.4e} -> {:.4e}",
                family.family, family.num_residual_blocks, family.initial_cost, family.final_cost
            )?;
        }
        Ok(())
    }
}

impl SolveSummary {
    /// The cost entry of one family, if present.
    pub fn family(&self, family: ResidualFamily) -> Option<&FamilyCost> {
        self.families.iter().find(|f| f.family == family)
    }
}

/// Residuals of a problem at its current parameters ([`super::evaluate_residuals`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    /// Observations (2 each), then plane constraints (1 each), then pose priors
    /// (6 each: position xyz, rotation xyz), in input order; weights applied,
    /// loss not applied. NaN where a residual could not be evaluated (point
    /// behind the camera).
    pub residuals: Vec<f64>,
    /// Per family present: blocks and `0.5 * sum rho(|r|^2)` over the blocks that
    /// evaluated (`initial_cost == final_cost`).
    pub families: Vec<FamilyCost>,
    /// Residual blocks that could not be evaluated.
    pub num_failed_blocks: usize,
}

impl Evaluation {
    /// The reprojection residual of observation `i`.
    pub fn observation(&self, i: usize) -> [f64; 2] {
        [self.residuals[2 * i], self.residuals[2 * i + 1]]
    }
}
