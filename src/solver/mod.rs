//! Bundle adjustment through Ceres (C++ in `cpp/`, bridged by cxx).
//!
//! One call per solve: a [`BundleAdjustmentProblem`] (poses, intrinsics, points,
//! reprojection observations, point-to-plane constraints, pose priors and which
//! blocks are constant) is validated in Rust, flattened into arrays, solved by
//! Ceres, and the solution is written back in place. [`solve`] returns a
//! [`SolveSummary`]; [`evaluate_residuals`] evaluates without solving (for
//! reports and for the tests that compare the C++ residuals with the Rust
//! references in [`reference`]); [`pose_covariances`] gives each variable
//! pose's covariance at a solution (Ceres' Jacobian, points eliminated in
//! Rust, see [`covariance`]).
//!
//! Residuals (formulas also above each C++ functor):
//! * reprojection: `w * (project(K, R X + t) - x_obs)`, pixels;
//! * point-to-plane: `w * (n . X - d)`, signed, linear in `X` (no NaN on the plane);
//! * pose prior: `w_p * (C - C_prior)` and `w_r * angle_axis(R R_prior^T)`.
//!
//! Gauge: reprojection alone leaves a 7-DoF similarity free. Fix it with
//! constant poses (two poses fix scale too), with pose priors, or with planes.
//! Planes fix it only if no similarity maps each plane onto itself: three
//! planes through one point (a room corner) leave the scale about that point
//! free; a fourth plane not through it (an opposite wall) fixes it.
//!
//! Linear solver ([`LinearSolver::Auto`]): dense Schur for small problems,
//! sparse Schur (SuiteSparse in Debian's Ceres 2.1) for medium, iterative
//! Schur with the Schur-Jacobi preconditioner for huge ones. Points form the
//! first elimination group, poses and intrinsics the second.
pub(crate) mod bridge;
pub mod covariance;
pub(crate) mod ffi;
pub mod options;
pub mod problem;
pub mod reference;
pub mod summary;

pub use covariance::{
    clustered_pose_covariances, pose_covariances, sigma_of_variance, CovarianceError,
    PoseCovariances,
};
pub use options::{LinearSolver, LossFunction, SolverOptions};
pub use problem::{
    BaCamera, BaObservation, BaPoint, BaPose, BundleAdjustmentProblem, ConstantParams,
    PlaneConstraint, PlaneFamily, PosePrior,
};
pub use summary::{
    Evaluation, FamilyCost, ResidualFamily, SolveSummary, SolveTimes, TerminationType,
};

/// Errors of the solver bridge.
#[derive(Debug, thiserror::Error)]
pub enum SolverError {
    /// The problem failed validation (names the item, its index and the issue).
    #[error("invalid bundle-adjustment problem: {0}")]
    InvalidProblem(String),
    /// The options failed validation.
    #[error("invalid solver options: {0}")]
    InvalidOptions(String),
    /// An exception thrown on the C++ side.
    #[error("Ceres bridge error: {0}")]
    Ceres(String),
}

/// Solves `problem` in place: validates it and `options`, runs Ceres and
/// writes the solved poses, intrinsics and points back. A solve that runs but
/// fails (e.g. a point behind a camera at the start) is `Ok` with
/// `summary.usable == false`; bad input is `Err` and leaves `problem` unchanged.
pub fn solve(
    problem: &mut BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<SolveSummary, SolverError> {
    bridge::solve(problem, options)
}

/// Evaluates every residual at the current parameters through the C++ cost
/// functions, without solving. Per-family costs use `options`' losses.
pub fn evaluate_residuals(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<Evaluation, SolverError> {
    bridge::evaluate(problem, options)
}

/// Whether this Ceres build can run the sparse linear solvers.
pub fn sparse_linear_algebra_available() -> bool {
    ffi::ffi::sparse_linear_algebra_available()
}

/// Projects camera-frame points with the C++ camera model code used by the
/// solver. Exposed so tests and tools can check it against [`crate::scene::Camera::project`].
pub fn project_points_cpp(
    model_id: i32,
    params: &[f64],
    points_in_cam: &[[f64; 3]],
) -> Result<Vec<[f64; 2]>, String> {
    let flat: Vec<f64> = points_in_cam.iter().flatten().copied().collect();
    let mut pixels = vec![0.0; points_in_cam.len() * 2];
    ffi::ffi::project_points(model_id, params, &flat, &mut pixels)
        .map_err(|e| e.what().to_owned())?;
    Ok(pixels.chunks_exact(2).map(|p| [p[0], p[1]]).collect())
}
