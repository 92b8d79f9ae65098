//! How to solve: robust losses per residual family, stopping criteria, threads
//! and the linear solver.
use super::problem::PlaneFamily;
use super::SolverError;

/// A robust loss `rho(s)` on the squared residual norm `s`. `scale` is in the
/// residual's own units (pixels for reprojection, pixel equivalents, i.e.
/// `weight * metres`, for planes and priors): the residual size where the loss
/// starts to down-weight (Ceres' `a`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LossFunction {
    /// Plain least squares, `rho(s) = s`.
    Trivial,
    /// Quadratic below `scale`, linear above.
    Huber { scale: f64 },
    /// `rho(s) = 2 a^2 (sqrt(1 + s / a^2) - 1)`.
    SoftL1 { scale: f64 },
    /// `rho(s) = a^2 log(1 + s / a^2)`.
    Cauchy { scale: f64 },
}

impl LossFunction {
    /// The bridge's (kind, scale) code: 0 trivial, 1 Huber, 2 Soft-L1, 3 Cauchy.
    pub(crate) fn code(self) -> (i32, f64) {
        match self {
            LossFunction::Trivial => (0, 1.0),
            LossFunction::Huber { scale } => (1, scale),
            LossFunction::SoftL1 { scale } => (2, scale),
            LossFunction::Cauchy { scale } => (3, scale),
        }
    }

    /// `rho(s)`, the loss applied to a squared residual norm (Ceres' definition).
    pub fn rho(self, s: f64) -> f64 {
        match self {
            LossFunction::Trivial => s,
            LossFunction::Huber { scale } => {
                let b = scale * scale;
                if s > b {
                    2.0 * scale * s.sqrt() - b
                } else {
                    s
                }
            }
            LossFunction::SoftL1 { scale } => {
                let b = scale * scale;
                2.0 * b * ((1.0 + s / b).sqrt() - 1.0)
            }
            LossFunction::Cauchy { scale } => {
                let b = scale * scale;
                b * (1.0 + s / b).ln()
            }
        }
    }

    fn validate(self, what: &str) -> Result<(), SolverError> {
        let (_, scale) = self.code();
        if scale.is_finite() && scale > 0.0 {
            Ok(())
        } else {
            Err(SolverError::InvalidOptions(format!(
                "{what} loss scale must be finite and > 0, got {scale}"
            )))
        }
    }
}

/// The linear solver inside each Levenberg-Marquardt step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LinearSolver {
    /// By problem size: dense Schur up to [`SolverOptions::dense_schur_max_poses`]
    /// variable poses, sparse Schur up to [`SolverOptions::sparse_schur_max_poses`]
    /// (when Ceres has a sparse library), iterative Schur beyond.
    Auto,
    DenseSchur,
    SparseSchur,
    IterativeSchur,
    DenseQr,
    DenseNormalCholesky,
    SparseNormalCholesky,
}

impl LinearSolver {
    pub(crate) fn code(self) -> Option<i32> {
        match self {
            LinearSolver::Auto => None,
            LinearSolver::DenseSchur => Some(0),
            LinearSolver::SparseSchur => Some(1),
            LinearSolver::IterativeSchur => Some(2),
            LinearSolver::DenseQr => Some(3),
            LinearSolver::DenseNormalCholesky => Some(4),
            LinearSolver::SparseNormalCholesky => Some(5),
        }
    }

    pub(crate) fn from_code(code: i32) -> Option<Self> {
        [
            LinearSolver::DenseSchur,
            LinearSolver::SparseSchur,
            LinearSolver::IterativeSchur,
            LinearSolver::DenseQr,
            LinearSolver::DenseNormalCholesky,
            LinearSolver::SparseNormalCholesky,
        ]
        .into_iter()
        .find(|s| s.code() == Some(code))
    }

    /// Whether the solver needs a sparse linear-algebra library.
    pub fn needs_sparse_library(self) -> bool {
        matches!(
            self,
            LinearSolver::SparseSchur | LinearSolver::SparseNormalCholesky
        )
    }
}

/// Options of one solve. Defaults are Ceres' own stopping criteria, plain least
/// squares everywhere, one thread and the size-based linear solver.
#[derive(Clone, Debug, PartialEq)]
pub struct SolverOptions {
    /// Loss on reprojection residuals. Default: trivial.
    pub reprojection_loss: LossFunction,
    /// Loss on pose-prior residuals. Default: trivial.
    pub pose_prior_loss: LossFunction,
    /// Loss on point-to-plane residuals of any family not listed in
    /// `plane_family_losses`. Default: trivial.
    pub plane_loss: LossFunction,
    /// Per-family overrides of `plane_loss`. Default: none.
    pub plane_family_losses: Vec<(PlaneFamily, LossFunction)>,
    /// Maximum Levenberg-Marquardt iterations. Default: 100.
    pub max_iterations: usize,
    /// Stop when the relative cost decrease falls below this. Default: 1e-6.
    pub function_tolerance: f64,
    /// Stop when the max-norm of the projected gradient falls below this.
    /// Default: 1e-10.
    pub gradient_tolerance: f64,
    /// Stop when the relative step size falls below this. Default: 1e-8.
    pub parameter_tolerance: f64,
    /// Wall-clock limit in seconds; 0 means none. Default: 0.
    pub max_time_s: f64,
    /// Threads for Jacobian evaluation and linear algebra. More than one can
    /// change the last bits of the result between runs. Default: 1.
    pub num_threads: usize,
    /// Default: [`LinearSolver::Auto`].
    pub linear_solver: LinearSolver,
    /// Auto: dense Schur below this many variable poses. Default: 150.
    pub dense_schur_max_poses: usize,
    /// Auto: sparse Schur below this many variable poses, iterative above.
    /// Default: 1000.
    pub sparse_schur_max_poses: usize,
    /// Ceres' per-iteration progress to stdout and its warnings to stderr.
    /// Default: false.
    pub logging: bool,
}

impl Default for SolverOptions {
    fn default() -> Self {
        Self {
            reprojection_loss: LossFunction::Trivial,
            pose_prior_loss: LossFunction::Trivial,
            plane_loss: LossFunction::Trivial,
            plane_family_losses: Vec::new(),
            max_iterations: 100,
            function_tolerance: 1e-6,
            gradient_tolerance: 1e-10,
            parameter_tolerance: 1e-8,
            max_time_s: 0.0,
            num_threads: 1,
            linear_solver: LinearSolver::Auto,
            dense_schur_max_poses: 150,
            sparse_schur_max_poses: 1000,
            logging: false,
        }
    }
}

impl SolverOptions {
    /// Checks ranges: finite non-negative tolerances, positive loss scales, at
    /// least one thread, iterations within `i32`.
    pub fn validate(&self) -> Result<(), SolverError> {
        self.reprojection_loss.validate("reprojection")?;
        self.pose_prior_loss.validate("pose prior")?;
        self.plane_loss.validate("plane")?;
        for (family, loss) in &self.plane_family_losses {
            loss.validate(&format!("plane family {family:?}"))?;
        }
        for (name, value) in [
            ("function_tolerance", self.function_tolerance),
            ("gradient_tolerance", self.gradient_tolerance),
            ("parameter_tolerance", self.parameter_tolerance),
            ("max_time_s", self.max_time_s),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(SolverError::InvalidOptions(format!(
                    "{name} must be finite and >= 0, got {value}"
                )));
            }
        }
        if self.num_threads == 0 || self.num_threads > 1024 {
            return Err(SolverError::InvalidOptions(format!(
                "num_threads must be in 1..=1024, got {}",
                self.num_threads
            )));
        }
        if i32::try_from(self.max_iterations).is_err() {
            return Err(SolverError::InvalidOptions(format!(
                "max_iterations too large: {}",
                self.max_iterations
            )));
        }
        Ok(())
    }

    /// The loss of a plane family (override or `plane_loss`).
    pub fn loss_for_plane_family(&self, family: PlaneFamily) -> LossFunction {
        self.plane_family_losses
            .iter()
            .rev()
            .find(|(f, _)| *f == family)
            .map_or(self.plane_loss, |(_, loss)| *loss)
    }

    /// The linear solver `Auto` resolves to for `num_variable_poses`.
    pub fn resolve_linear_solver(
        &self,
        num_variable_poses: usize,
        sparse_available: bool,
    ) -> LinearSolver {
        match self.linear_solver {
            LinearSolver::Auto => {
                if num_variable_poses < self.dense_schur_max_poses {
                    LinearSolver::DenseSchur
                } else if num_variable_poses < self.sparse_schur_max_poses && sparse_available {
                    LinearSolver::SparseSchur
                } else {
                    LinearSolver::IterativeSchur
                }
            }
            explicit => explicit,
        }
    }
}
