// Ceres bundle adjustment behind a flat-array cxx bridge (src/solver/ffi.rs).
// One call per solve; every C++ exception is returned to Rust as an Err.
#pragma once
#include "rust/cxx.h"

namespace colmap_lidar {

struct BaProblemFfi;
struct BaOptionsFfi;
struct BaSummaryFfi;
struct BaEvaluationFfi;
struct BaJacobianFfi;

// Builds the problem, solves it and writes the solution back into `problem`.
BaSummaryFfi solve_bundle_adjustment(BaProblemFfi& problem,
                                     const BaOptionsFfi& options);

// Builds the problem and evaluates every residual without solving.
BaEvaluationFfi evaluate_bundle_adjustment(BaProblemFfi& problem,
                                           const BaOptionsFfi& options);

// Builds the problem and returns its Jacobian at the current parameters.
BaJacobianFfi jacobian_bundle_adjustment(BaProblemFfi& problem,
                                         const BaOptionsFfi& options);

// True when Ceres was built with a sparse linear-algebra library.
bool sparse_linear_algebra_available();

}  // namespace colmap_lidar
