//! The cxx bridge to the C++ side (`cpp/`): camera projection (for cross-checks)
//! and the Ceres bundle-adjustment solve. Flat arrays in, flat arrays out.

// The bridge module keeps cxx's conventional name inside `solver::ffi`.
#[allow(clippy::module_inception)]
#[cxx::bridge(namespace = "colmap_lidar")]
pub(crate) mod ffi {
    /// A bundle-adjustment problem as flat, index-addressed arrays. Built and
    /// validated by `super::bridge`; the C++ side re-checks every size and index
    /// (a failed glog CHECK inside Ceres would kill the process) and writes the
    /// solved values back into `poses`, `camera_params` and `points`.
    struct BaProblemFfi {
        /// 7 per pose: qw qx qy qz tx ty tz (`cam_from_world`, unit quaternion).
        poses: Vec<f64>,
        /// 1 per pose: 1 = constant.
        pose_constant: Vec<u8>,
        /// 1 per camera: COLMAP model id.
        camera_model_ids: Vec<i32>,
        /// num_cameras + 1 offsets into `camera_params`.
        camera_param_offsets: Vec<u32>,
        /// All cameras' parameters, concatenated.
        camera_params: Vec<f64>,
        /// 1 per entry of `camera_params`: 1 = constant.
        camera_param_constant: Vec<u8>,
        /// 3 per point (world frame).
        points: Vec<f64>,
        /// 1 per point: 1 = constant.
        point_constant: Vec<u8>,
        /// 1 per observation each.
        obs_pose: Vec<u32>,
        obs_camera: Vec<u32>,
        obs_point: Vec<u32>,
        /// 2 per observation.
        obs_pixel: Vec<f64>,
        /// 1 per observation.
        obs_weight: Vec<f64>,
        /// 1 per plane constraint each, except `plane_normal` (3 per constraint).
        plane_point: Vec<u32>,
        plane_normal: Vec<f64>,
        plane_offset: Vec<f64>,
        plane_weight: Vec<f64>,
        /// Residual family index of each plane constraint (>= 2).
        plane_family: Vec<u32>,
        /// 1 per prior each, except `prior_position` (3) and `prior_rotation` (4:
        /// qw qx qy qz of the prior `cam_from_world` rotation).
        prior_pose: Vec<u32>,
        prior_position: Vec<f64>,
        prior_rotation: Vec<f64>,
        prior_position_weight: Vec<f64>,
        prior_rotation_weight: Vec<f64>,
    }

    /// Solver options in the C++ side's terms (all validated in Rust).
    struct BaOptionsFfi {
        /// Per residual family (0 reprojection, 1 pose prior, 2.. plane families):
        /// 0 trivial, 1 Huber, 2 Soft-L1, 3 Cauchy.
        loss_kind: Vec<i32>,
        /// Per residual family: the loss scale (ignored for trivial).
        loss_scale: Vec<f64>,
        max_iterations: i32,
        function_tolerance: f64,
        gradient_tolerance: f64,
        parameter_tolerance: f64,
        max_time_s: f64,
        num_threads: i32,
        /// 0 dense Schur, 1 sparse Schur, 2 iterative Schur, 3 dense QR,
        /// 4 dense normal Cholesky, 5 sparse normal Cholesky.
        linear_solver: i32,
        logging: bool,
    }

    /// What a solve reports.
    struct BaSummaryFfi {
        initial_cost: f64,
        final_cost: f64,
        num_iterations: i32,
        /// 0 convergence, 1 no convergence, 2 failure, 3 user success, 4 user failure.
        termination: i32,
        usable: bool,
        time_s: f64,
        message: String,
        linear_solver_used: i32,
        /// Per residual family (same indexing as the options' losses).
        family_num_blocks: Vec<u32>,
        family_initial_cost: Vec<f64>,
        family_final_cost: Vec<f64>,
        /// Where the time went, seconds: building the Ceres problem, the two
        /// evaluations of every family's cost (before and after), and Ceres'
        /// own split of `time_s`.
        build_time_s: f64,
        family_cost_time_s: f64,
        preprocessor_time_s: f64,
        residual_time_s: f64,
        jacobian_time_s: f64,
        linear_solver_time_s: f64,
        /// Ceres' Schur structure used, "row,e,f" block sizes ("d" dynamic);
        /// empty for other linear solvers.
        schur_structure: String,
    }

    /// Residuals at the current parameters, without solving.
    struct BaEvaluationFfi {
        /// Observations (2 each), then planes (1 each), then priors (6 each), in
        /// input order, as the cost functions return them (weights applied, loss
        /// not applied). NaN where a cost function failed (point behind camera).
        residuals: Vec<f64>,
        family_num_blocks: Vec<u32>,
        /// Per family: sum of 0.5 * rho(|r|^2) over residual blocks that evaluated.
        family_cost: Vec<f64>,
        /// Residual blocks whose cost function returned false.
        num_failed_blocks: u32,
    }

    /// The Jacobian at the current parameters, in compressed rows: one column
    /// per tangent dimension of each variable parameter block, blocks in the
    /// order points, then each pose's rotation and translation, then
    /// intrinsics. Robust losses are applied as the solver applies them.
    struct BaJacobianFfi {
        num_rows: u64,
        num_cols: u64,
        /// num_rows + 1 offsets into `cols` and `values`.
        row_starts: Vec<u64>,
        cols: Vec<u32>,
        values: Vec<f64>,
        /// The residuals, loss-corrected like the rows.
        residuals: Vec<f64>,
        /// Per variable block, in column order: 0 point, 1 pose rotation
        /// (Ceres' quaternion tangent: `q <- [cos|d|, sin|d| d/|d|] * q`),
        /// 2 pose translation, 3 camera intrinsics.
        block_kind: Vec<u32>,
        /// Index of the point, pose or camera in the problem's arrays.
        block_index: Vec<u32>,
        /// Tangent size (the block's number of columns).
        block_size: Vec<u32>,
    }

    unsafe extern "C++" {
        include!("colmap-lidar/cpp/camera_bridge.h");

        /// Projects camera-frame points (xyz triples) with COLMAP model `model_id`
        /// and `params`, writing pixel pairs into `pixels` (NaN where the point
        /// cannot be projected). Errors on an unknown model or wrong sizes.
        fn project_points(
            model_id: i32,
            params: &[f64],
            points_in_cam: &[f64],
            pixels: &mut [f64],
        ) -> Result<()>;
    }

    unsafe extern "C++" {
        include!("colmap-lidar/cpp/bundle_adjustment.h");

        /// Builds the Ceres problem, solves it, writes the solution back into
        /// `problem` and returns the summary. Any C++ exception becomes `Err`.
        fn solve_bundle_adjustment(
            problem: &mut BaProblemFfi,
            options: &BaOptionsFfi,
        ) -> Result<BaSummaryFfi>;

        /// Builds the Ceres problem and evaluates every residual at the current
        /// parameters without solving.
        fn evaluate_bundle_adjustment(
            problem: &mut BaProblemFfi,
            options: &BaOptionsFfi,
        ) -> Result<BaEvaluationFfi>;

        /// Builds the Ceres problem and returns its Jacobian and residuals at the
        /// current parameters (the problem is not changed).
        fn jacobian_bundle_adjustment(
            problem: &mut BaProblemFfi,
            options: &BaOptionsFfi,
        ) -> Result<BaJacobianFfi>;

        /// True when this Ceres build has a sparse linear-algebra library
        /// (SuiteSparse, Eigen sparse or CXSparse) for SPARSE_SCHUR.
        fn sparse_linear_algebra_available() -> bool;
    }
}
