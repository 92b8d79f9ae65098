//! Conversion between the Rust problem types and the flat cxx structs, and the
//! two calls across the bridge.
use super::ffi::ffi;
use super::options::{LinearSolver, SolverOptions};
use super::problem::{BundleAdjustmentProblem, ConstantParams, PlaneFamily};
use super::summary::{
    Evaluation, FamilyCost, ResidualFamily, SolveSummary, SolveTimes, TerminationType,
};
use super::SolverError;

/// Quaternion or normal scaled to exact unit length (validated as near-unit).
fn normalized<const N: usize>(v: &[f64]) -> [f64; N] {
    let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(v) {
        *o = x / norm;
    }
    out
}

/// Number of residual families the bridge must know about: reprojection, pose
/// prior, and plane families up to the largest one used.
fn num_families(problem: &BundleAdjustmentProblem, options: &SolverOptions) -> u32 {
    let max_plane = problem
        .planes
        .iter()
        .map(|p| p.family)
        .chain(options.plane_family_losses.iter().map(|(f, _)| *f))
        .map(PlaneFamily::index)
        .max()
        .unwrap_or(2);
    2 + max_plane.max(2) + 1
}

pub(crate) fn to_ffi_options(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
    linear_solver: LinearSolver,
) -> ffi::BaOptionsFfi {
    let mut loss_kind = Vec::new();
    let mut loss_scale = Vec::new();
    for index in 0..num_families(problem, options) {
        // from_index cannot fail: indices up to the largest validated family.
        let loss = match ResidualFamily::from_index(index) {
            Some(ResidualFamily::Reprojection) => options.reprojection_loss,
            Some(ResidualFamily::PosePrior) => options.pose_prior_loss,
            Some(ResidualFamily::Plane(f)) => options.loss_for_plane_family(f),
            None => options.plane_loss,
        };
        let (kind, scale) = loss.code();
        loss_kind.push(kind);
        loss_scale.push(scale);
    }
    ffi::BaOptionsFfi {
        loss_kind,
        loss_scale,
        // validate() checked it fits.
        max_iterations: i32::try_from(options.max_iterations).unwrap_or(i32::MAX),
        function_tolerance: options.function_tolerance,
        gradient_tolerance: options.gradient_tolerance,
        parameter_tolerance: options.parameter_tolerance,
        max_time_s: options.max_time_s,
        num_threads: i32::try_from(options.num_threads).unwrap_or(1),
        linear_solver: linear_solver.code().unwrap_or(0),
        logging: options.logging,
    }
}

pub(crate) fn to_ffi_problem(problem: &BundleAdjustmentProblem) -> ffi::BaProblemFfi {
    let mut p = ffi::BaProblemFfi {
        poses: Vec::with_capacity(7 * problem.poses.len()),
        pose_constant: Vec::with_capacity(problem.poses.len()),
        camera_model_ids: Vec::new(),
        camera_param_offsets: vec![0],
        camera_params: Vec::new(),
        camera_param_constant: Vec::new(),
        points: Vec::with_capacity(3 * problem.points.len()),
        point_constant: Vec::with_capacity(problem.points.len()),
        obs_pose: Vec::with_capacity(problem.observations.len()),
        obs_camera: Vec::with_capacity(problem.observations.len()),
        obs_point: Vec::with_capacity(problem.observations.len()),
        obs_pixel: Vec::with_capacity(2 * problem.observations.len()),
        obs_weight: Vec::with_capacity(problem.observations.len()),
        plane_point: Vec::with_capacity(problem.planes.len()),
        plane_normal: Vec::with_capacity(3 * problem.planes.len()),
        plane_offset: Vec::with_capacity(problem.planes.len()),
        plane_weight: Vec::with_capacity(problem.planes.len()),
        plane_family: Vec::with_capacity(problem.planes.len()),
        prior_pose: Vec::new(),
        prior_position: Vec::new(),
        prior_rotation: Vec::new(),
        prior_position_weight: Vec::new(),
        prior_rotation_weight: Vec::new(),
    };
    for pose in &problem.poses {
        let q: [f64; 4] = normalized(&pose.cam_from_world[..4]);
        p.poses.extend_from_slice(&q);
        p.poses.extend_from_slice(&pose.cam_from_world[4..]);
        p.pose_constant.push(u8::from(pose.constant));
    }
    for camera in &problem.cameras {
        p.camera_model_ids.push(camera.model_id);
        p.camera_params.extend_from_slice(&camera.params);
        for k in 0..camera.params.len() {
            let constant = match &camera.constant {
                ConstantParams::None => false,
                ConstantParams::All => true,
                ConstantParams::Mask(mask) => mask[k],
            };
            p.camera_param_constant.push(u8::from(constant));
        }
        // Parameter counts are tiny (validated against the model).
        p.camera_param_offsets.push(p.camera_params.len() as u32);
    }
    for point in &problem.points {
        p.points.extend_from_slice(&point.position_in_world);
        p.point_constant.push(u8::from(point.constant));
    }
    for obs in &problem.observations {
        p.obs_pose.push(obs.pose_idx);
        p.obs_camera.push(obs.camera_idx);
        p.obs_point.push(obs.point_idx);
        p.obs_pixel.extend_from_slice(&obs.pixel_px);
        p.obs_weight.push(obs.weight);
    }
    for plane in &problem.planes {
        p.plane_point.push(plane.point_idx);
        let n: [f64; 3] = normalized(&plane.normal);
        p.plane_normal.extend_from_slice(&n);
        p.plane_offset.push(plane.offset_m);
        p.plane_weight.push(plane.weight);
        p.plane_family
            .push(ResidualFamily::Plane(plane.family).index());
    }
    for prior in &problem.pose_priors {
        p.prior_pose.push(prior.pose_idx);
        match &prior.position_in_world {
            Some(c) => {
                p.prior_position.extend_from_slice(c);
                p.prior_position_weight.push(prior.position_weight);
            }
            None => {
                p.prior_position.extend_from_slice(&[0.0; 3]);
                p.prior_position_weight.push(0.0);
            }
        }
        match &prior.cam_from_world_rotation {
            Some(q) => {
                let q: [f64; 4] = normalized(q);
                p.prior_rotation.extend_from_slice(&q);
                p.prior_rotation_weight.push(prior.rotation_weight);
            }
            None => {
                p.prior_rotation.extend_from_slice(&[1.0, 0.0, 0.0, 0.0]);
                p.prior_rotation_weight.push(0.0);
            }
        }
    }
    p
}

/// Writes the solved values back: variable poses, variable intrinsics and
/// variable points only, so constant blocks stay bit-identical (the bridge
/// re-normalises quaternions, which may change their last bit).
pub(crate) fn from_ffi_problem(p: &ffi::BaProblemFfi, problem: &mut BundleAdjustmentProblem) {
    for (pose, values) in problem.poses.iter_mut().zip(p.poses.chunks_exact(7)) {
        if !pose.constant {
            pose.cam_from_world.copy_from_slice(values);
        }
    }
    for (c, camera) in problem.cameras.iter_mut().enumerate() {
        let begin = p.camera_param_offsets[c] as usize;
        for k in 0..camera.params.len() {
            if !camera.is_param_constant(k) {
                camera.params[k] = p.camera_params[begin + k];
            }
        }
    }
    for (point, values) in problem.points.iter_mut().zip(p.points.chunks_exact(3)) {
        if !point.constant {
            point.position_in_world.copy_from_slice(values);
        }
    }
}

fn family_costs(num_blocks: &[u32], initial: &[f64], fin: &[f64]) -> Vec<FamilyCost> {
    num_blocks
        .iter()
        .enumerate()
        .filter(|(_, &n)| n > 0)
        .filter_map(|(i, &n)| {
            Some(FamilyCost {
                family: ResidualFamily::from_index(i as u32)?,
                num_residual_blocks: n as usize,
                initial_cost: initial[i],
                final_cost: fin[i],
            })
        })
        .collect()
}

fn num_variable_poses(problem: &BundleAdjustmentProblem) -> usize {
    problem.poses.iter().filter(|p| !p.constant).count()
}

/// Validates, converts, solves through Ceres and writes the solution back.
pub(crate) fn solve(
    problem: &mut BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<SolveSummary, SolverError> {
    problem.validate()?;
    options.validate()?;
    let sparse_available = ffi::sparse_linear_algebra_available();
    let linear_solver =
        options.resolve_linear_solver(num_variable_poses(problem), sparse_available);
    if linear_solver.needs_sparse_library() && !sparse_available {
        return Err(SolverError::InvalidOptions(format!(
            "{linear_solver:?} needs a sparse linear algebra library, which this Ceres build lacks"
        )));
    }
    let mut p = to_ffi_problem(problem);
    let o = to_ffi_options(problem, options, linear_solver);
    let s = ffi::solve_bundle_adjustment(&mut p, &o)
        .map_err(|e| SolverError::Ceres(e.what().to_owned()))?;
    from_ffi_problem(&p, problem);
    Ok(SolveSummary {
        initial_cost: s.initial_cost,
        final_cost: s.final_cost,
        num_iterations: usize::try_from(s.num_iterations).unwrap_or(0),
        termination: TerminationType::from_code(s.termination),
        usable: s.usable,
        time_s: s.time_s,
        message: s.message,
        linear_solver: LinearSolver::from_code(s.linear_solver_used),
        families: family_costs(
            &s.family_num_blocks,
            &s.family_initial_cost,
            &s.family_final_cost,
        ),
        times: SolveTimes {
            build_s: s.build_time_s,
            family_cost_s: s.family_cost_time_s,
            preprocessor_s: s.preprocessor_time_s,
            residual_s: s.residual_time_s,
            jacobian_s: s.jacobian_time_s,
            linear_solver_s: s.linear_solver_time_s,
        },
        schur_structure: s.schur_structure,
    })
}

/// Validates, converts and evaluates every residual without solving.
pub(crate) fn evaluate(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<Evaluation, SolverError> {
    problem.validate()?;
    options.validate()?;
    let mut p = to_ffi_problem(problem);
    let o = to_ffi_options(problem, options, LinearSolver::DenseSchur);
    let e = ffi::evaluate_bundle_adjustment(&mut p, &o)
        .map_err(|e| SolverError::Ceres(e.what().to_owned()))?;
    Ok(Evaluation {
        residuals: e.residuals,
        families: family_costs(&e.family_num_blocks, &e.family_cost, &e.family_cost),
        num_failed_blocks: e.num_failed_blocks as usize,
    })
}

/// Validates, converts and returns the Jacobian at the current parameters.
pub(crate) fn jacobian(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<ffi::BaJacobianFfi, SolverError> {
    problem.validate()?;
    options.validate()?;
    let mut p = to_ffi_problem(problem);
    let o = to_ffi_options(problem, options, LinearSolver::DenseSchur);
    ffi::jacobian_bundle_adjustment(&mut p, &o).map_err(|e| SolverError::Ceres(e.what().to_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Rigid3;
    use crate::solver::problem::{BaCamera, BaObservation, BaPoint, BaPose};

    fn tiny_problem() -> BundleAdjustmentProblem {
        BundleAdjustmentProblem {
            poses: vec![BaPose::new(&Rigid3::identity(), false)],
            cameras: vec![BaCamera {
                model_id: 1,
                params: vec![100.0, 100.0, 50.0, 50.0],
                constant: ConstantParams::All,
            }],
            points: vec![BaPoint {
                position_in_world: [0.1, -0.2, 2.0],
                constant: false,
            }],
            observations: vec![BaObservation {
                pose_idx: 0,
                camera_idx: 0,
                point_idx: 0,
                pixel_px: [55.0, 40.0],
                weight: 1.0,
            }],
            ..Default::default()
        }
    }

    /// The C++ side's own checks turn bad input that slipped past Rust into an
    /// exception, i.e. an `Err`, never a glog CHECK abort.
    #[test]
    fn cpp_checks_reject_what_rust_validation_would() {
        let problem = tiny_problem();
        let options = SolverOptions::default();
        let o = to_ffi_options(&problem, &options, LinearSolver::DenseSchur);

        let mut ok = to_ffi_problem(&problem);
        let e = ffi::evaluate_bundle_adjustment(&mut ok, &o).expect("valid problem");
        // Hand-computed: (100 * 0.1 / 2 + 50 - 55, 100 * -0.2 / 2 + 50 - 40).
        assert_eq!(e.residuals.len(), 2);
        assert!((e.residuals[0] - 0.0).abs() < 1e-12 && (e.residuals[1] - 0.0).abs() < 1e-12);

        type Mutation = fn(&mut ffi::BaProblemFfi);
        let mutations: [(&str, Mutation); 6] = [
            ("point index", |p| p.obs_point[0] = 7),
            ("pose index", |p| p.obs_pose[0] = 1),
            ("NaN point", |p| p.points[2] = f64::NAN),
            ("short pixel array", |p| {
                p.obs_pixel.pop();
            }),
            ("non-unit quaternion", |p| p.poses[0] = 3.0),
            ("parameter count", |p| p.camera_model_ids[0] = 0),
        ];
        for (name, mutate) in mutations {
            let mut p = to_ffi_problem(&problem);
            mutate(&mut p);
            let Err(err) = ffi::solve_bundle_adjustment(&mut p, &o) else {
                panic!("{name}: accepted");
            };
            assert!(
                err.what().starts_with("bundle adjustment:"),
                "{name}: {}",
                err.what()
            );
        }
        let mut bad_options = to_ffi_options(&problem, &options, LinearSolver::DenseSchur);
        bad_options.loss_kind[0] = 9;
        let mut p = to_ffi_problem(&problem);
        assert!(ffi::solve_bundle_adjustment(&mut p, &bad_options).is_err());
    }

    #[test]
    fn family_indices_round_trip() {
        for family in [
            ResidualFamily::Reprojection,
            ResidualFamily::PosePrior,
            ResidualFamily::Plane(PlaneFamily::Projection),
            ResidualFamily::Plane(PlaneFamily::Nearest),
            ResidualFamily::Plane(PlaneFamily::Ground),
            ResidualFamily::Plane(PlaneFamily::Other(0)),
            ResidualFamily::Plane(PlaneFamily::Other(63)),
        ] {
            assert_eq!(ResidualFamily::from_index(family.index()), Some(family));
        }
        assert_eq!(ResidualFamily::from_index(2 + 3 + 64), None);
    }
}
