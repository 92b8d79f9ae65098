//! Rust reference implementations of every residual the C++ side computes,
//! written independently from it (nalgebra and [`Camera::project`]) so tests
//! can compare the two, and usable for reports without crossing the bridge.
use nalgebra::{UnitQuaternion, Vector2, Vector3};

use super::options::SolverOptions;
use super::problem::{BaObservation, BundleAdjustmentProblem, PlaneConstraint, PosePrior};
use super::summary::ResidualFamily;
use crate::scene::{Camera, CameraId, CameraModel, Rigid3};

fn quaternion(q: &[f64]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// `weight * (project(camera, R X + t) - pixel)`; `None` when the camera model
/// cannot project the point (or the model id is unknown).
pub fn reprojection_residual(
    problem: &BundleAdjustmentProblem,
    obs: &BaObservation,
) -> Option<[f64; 2]> {
    let pose = &problem.poses[obs.pose_idx as usize];
    let cam = &problem.cameras[obs.camera_idx as usize];
    let point = &problem.points[obs.point_idx as usize].position_in_world;
    let camera = Camera {
        id: CameraId(0),
        model: CameraModel::from_id(i64::from(cam.model_id))?,
        width: 0,
        height: 0,
        params: cam.params.clone(),
    };
    let p = &pose.cam_from_world;
    let cam_from_world = Rigid3::new(quaternion(&p[..4]), Vector3::new(p[4], p[5], p[6]));
    let point_in_cam = cam_from_world.transform_point(&Vector3::from(*point));
    let pixel = camera.project(&point_in_cam)?;
    let r = (pixel - Vector2::from(obs.pixel_px)) * obs.weight;
    Some([r.x, r.y])
}

/// `weight * (n . X - d)`.
pub fn plane_residual(problem: &BundleAdjustmentProblem, plane: &PlaneConstraint) -> f64 {
    let x = Vector3::from(problem.points[plane.point_idx as usize].position_in_world);
    let n = Vector3::from(plane.normal).normalize();
    plane.weight * (n.dot(&x) - plane.offset_m)
}

/// `[w_p * (C - C_prior), w_r * angle_axis(R R_prior^T)]`, zeros for a missing part.
pub fn pose_prior_residual(problem: &BundleAdjustmentProblem, prior: &PosePrior) -> [f64; 6] {
    let p = &problem.poses[prior.pose_idx as usize].cam_from_world;
    let rotation = quaternion(&p[..4]);
    let center = -(rotation.inverse() * Vector3::new(p[4], p[5], p[6]));
    let mut r = [0.0; 6];
    if let Some(c) = &prior.position_in_world {
        let d = (center - Vector3::from(*c)) * prior.position_weight;
        r[..3].copy_from_slice(d.as_slice());
    }
    if let Some(q) = &prior.cam_from_world_rotation {
        let err = (rotation * quaternion(q).inverse()).scaled_axis() * prior.rotation_weight;
        r[3..].copy_from_slice(err.as_slice());
    }
    r
}

/// All residuals in the layout of [`super::Evaluation::residuals`] (NaN where a
/// point cannot be projected).
pub fn residuals(problem: &BundleAdjustmentProblem) -> Vec<f64> {
    let mut out = Vec::with_capacity(
        2 * problem.observations.len() + problem.planes.len() + 6 * problem.pose_priors.len(),
    );
    for obs in &problem.observations {
        out.extend_from_slice(&reprojection_residual(problem, obs).unwrap_or([f64::NAN; 2]));
    }
    for plane in &problem.planes {
        out.push(plane_residual(problem, plane));
    }
    for prior in &problem.pose_priors {
        out.extend_from_slice(&pose_prior_residual(problem, prior));
    }
    out
}

/// Cost `0.5 * sum rho(|r|^2)` of each family present, in family order, with the
/// losses of `options` (blocks that cannot be evaluated are skipped).
pub fn family_costs(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Vec<(ResidualFamily, f64)> {
    let mut costs: std::collections::BTreeMap<ResidualFamily, f64> = Default::default();
    for obs in &problem.observations {
        let entry = costs.entry(ResidualFamily::Reprojection).or_default();
        if let Some(r) = reprojection_residual(problem, obs) {
            *entry += 0.5 * options.reprojection_loss.rho(r[0] * r[0] + r[1] * r[1]);
        }
    }
    for plane in &problem.planes {
        let r = plane_residual(problem, plane);
        let loss = options.loss_for_plane_family(plane.family);
        *costs
            .entry(ResidualFamily::Plane(plane.family))
            .or_default() += 0.5 * loss.rho(r * r);
    }
    for prior in &problem.pose_priors {
        let r = pose_prior_residual(problem, prior);
        let s: f64 = r.iter().map(|v| v * v).sum();
        *costs.entry(ResidualFamily::PosePrior).or_default() +=
            0.5 * options.pose_prior_loss.rho(s);
    }
    costs.into_iter().collect()
}
