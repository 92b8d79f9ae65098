//! Absolute pose (PnP) of a camera from 2D-3D correspondences: P3P (Lambda Twist)
//! inside LO-RANSAC, then robust Levenberg-Marquardt refinement of the 6-DoF pose.
//!
//! Everything is measured in pixels through the real camera model: the bearing of
//! a keypoint is `Camera::unproject(pixel)` (COLMAP pixel convention, the centre of
//! the top-left pixel is (0.5, 0.5), as stored in the database), and the residual of
//! a correspondence under `cam_from_world` is
//! `r = Camera::project(R X_world + t) - pixel` (infinite when the point is behind
//! the camera, so that cheirality is part of the score and P3P's up to four
//! solutions are disambiguated by their support).
//!
//! Refinement minimises `½ Σ ρ(|r_i|²)` over the pose with a left-multiplied rotation
//! update `R ← exp([δω]×) R`, `t ← t + δt`; the Jacobian is
//! `∂r/∂(δω, δt) = J_dist · J_persp · [-[R X]× | I]`, with `J_persp` the analytic
//! derivative of `(x/z, y/z)` and `J_dist` the derivative of the distortion-and-
//! intrinsics map (`Camera::project_normalized`) by central differences
//! (exact `diag(fx, fy)` for pinhole models). Robust losses are handled by
//! iteratively reweighted normal equations (weight `ρ'(s)`), with every step
//! accepted only when the true robust cost decreases.
use nalgebra::{Matrix2, Matrix2x3, Matrix6, SMatrix, UnitQuaternion, Vector2, Vector3, Vector6};
use rand_chacha::ChaCha8Rng;

use super::p3p::p3p;
use super::ransac::{self, Estimator, RansacError, RansacOptions};
use super::InvalidOptions;
use crate::scene::{Camera, CameraModel, Rigid3};

/// A keypoint (pixels, COLMAP convention) and the world point it observes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence2D3D {
    pub pixel: Vector2<f64>,
    pub point_in_world: Vector3<f64>,
}

/// Robust loss ρ(s) of a squared residual s (px²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RobustLoss {
    /// ρ(s) = s.
    Trivial,
    /// ρ(s) = s for s <= c², 2 c sqrt(s) - c² beyond; c = `scale_px`.
    Huber { scale_px: f64 },
    /// ρ(s) = c² ln(1 + s / c²); c = `scale_px`.
    Cauchy { scale_px: f64 },
}

impl RobustLoss {
    fn rho(&self, s: f64) -> f64 {
        match *self {
            RobustLoss::Trivial => s,
            RobustLoss::Huber { scale_px: c } => {
                if s <= c * c {
                    s
                } else {
                    2.0 * c * s.sqrt() - c * c
                }
            }
            RobustLoss::Cauchy { scale_px: c } => c * c * (s / (c * c)).ln_1p(),
        }
    }

    /// ρ'(s): the weight of a residual in the reweighted normal equations.
    fn weight(&self, s: f64) -> f64 {
        match *self {
            RobustLoss::Trivial => 1.0,
            RobustLoss::Huber { scale_px: c } => {
                if s <= c * c {
                    1.0
                } else {
                    c / s.sqrt()
                }
            }
            RobustLoss::Cauchy { scale_px: c } => 1.0 / (1.0 + s / (c * c)),
        }
    }

    fn validate(&self) -> Result<(), InvalidOptions> {
        match *self {
            RobustLoss::Trivial => Ok(()),
            RobustLoss::Huber { scale_px } | RobustLoss::Cauchy { scale_px } => {
                if scale_px.is_finite() && scale_px > 0.0 {
                    Ok(())
                } else {
                    Err(InvalidOptions::new(
                        "loss.scale_px",
                        format!("must be finite and > 0, got {scale_px}"),
                    ))
                }
            }
        }
    }
}

/// Options of [`refine_absolute_pose`].
#[derive(Clone, Debug, PartialEq)]
pub struct PoseRefinementOptions {
    /// Robust loss on the reprojection error. Default: Cauchy with a 1 px scale
    /// (COLMAP's absolute pose refinement uses the same).
    pub loss: RobustLoss,
    /// Levenberg-Marquardt iterations at most. Default: 100.
    pub max_iterations: usize,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    /// Default: 1e-10.
    pub function_tolerance: f64,
    /// Stop when the step (rotation in rad plus translation relative to the
    /// scene's extent) is below this. Default: 1e-12.
    pub step_tolerance: f64,
}

impl Default for PoseRefinementOptions {
    fn default() -> Self {
        Self {
            loss: RobustLoss::Cauchy { scale_px: 1.0 },
            max_iterations: 100,
            function_tolerance: 1e-10,
            step_tolerance: 1e-12,
        }
    }
}

impl PoseRefinementOptions {
    pub fn validate(&self) -> Result<(), InvalidOptions> {
        self.loss.validate()?;
        if !(self.function_tolerance >= 0.0 && self.step_tolerance >= 0.0) {
            return Err(InvalidOptions::new(
                "function_tolerance/step_tolerance",
                "must be >= 0",
            ));
        }
        Ok(())
    }
}

/// The result of [`refine_absolute_pose`].
#[derive(Clone, Debug, PartialEq)]
pub struct PoseRefinementSummary {
    pub cam_from_world: Rigid3,
    /// `½ Σ ρ(|r_i|²)` (px²) at the start and at the end.
    pub initial_cost: f64,
    pub final_cost: f64,
    pub num_iterations: usize,
    /// A tolerance was reached (rather than the iteration limit).
    pub converged: bool,
}

/// Why [`refine_absolute_pose`] could not run.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PoseRefinementError {
    #[error(transparent)]
    InvalidOptions(#[from] InvalidOptions),
    #[error("pose refinement needs 3 correspondences in front of the camera, got {usable}")]
    TooFewObservations { usable: usize },
    #[error("pose refinement got a non-finite initial pose")]
    NonFinitePose,
}

/// Reprojection residual (px) of `c` under `cam_from_world`; `None` behind the
/// camera or outside the model's domain.
#[inline]
fn residual_px(
    camera: &Camera,
    cam_from_world: &Rigid3,
    c: &Correspondence2D3D,
) -> Option<Vector2<f64>> {
    let point_in_cam = cam_from_world.transform_point(&c.point_in_world);
    camera.project(&point_in_cam).map(|p| p - c.pixel)
}

/// Derivative of pixel coordinates w.r.t. normalised image coordinates.
fn distortion_jacobian(camera: &Camera, normalized: &Vector2<f64>) -> Option<Matrix2<f64>> {
    match (camera.model, camera.params.as_slice()) {
        (CameraModel::SimplePinhole, &[f, _, _]) => return Some(Matrix2::new(f, 0.0, 0.0, f)),
        (CameraModel::Pinhole, &[fx, fy, _, _]) => return Some(Matrix2::new(fx, 0.0, 0.0, fy)),
        _ => {}
    }
    const H: f64 = 1e-6;
    let dx = Vector2::new(H, 0.0);
    let dy = Vector2::new(0.0, H);
    let col_x = (camera.project_normalized(&(normalized + dx))?
        - camera.project_normalized(&(normalized - dx))?)
        / (2.0 * H);
    let col_y = (camera.project_normalized(&(normalized + dy))?
        - camera.project_normalized(&(normalized - dy))?)
        / (2.0 * H);
    Some(Matrix2::from_columns(&[col_x, col_y]))
}

/// Residual (px) and its Jacobian w.r.t. the pose update `(δω, δt)` (see the
/// module doc) of `c` under `[rotation | translation]`; `None` behind the camera
/// or outside the model's domain.
#[inline]
fn residual_and_jacobian(
    camera: &Camera,
    rotation: &nalgebra::Matrix3<f64>,
    translation: &Vector3<f64>,
    c: &Correspondence2D3D,
) -> Option<(Vector2<f64>, SMatrix<f64, 2, 6>)> {
    let rotated = rotation * c.point_in_world;
    let p_cam = rotated + translation;
    if !(p_cam.z > 0.0) {
        return None;
    }
    let normalized = Vector2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z);
    let pixel = camera.project_normalized(&normalized)?;
    let j_dist = distortion_jacobian(camera, &normalized)?;
    let inv_z = 1.0 / p_cam.z;
    let j_persp = Matrix2x3::new(
        inv_z,
        0.0,
        -normalized.x * inv_z,
        0.0,
        inv_z,
        -normalized.y * inv_z,
    );
    let j_point = j_dist * j_persp; // d pixel / d p_cam
    let mut j = SMatrix::<f64, 2, 6>::zeros();
    // d p_cam / d δω = -[R X]×, d p_cam / d δt = I.
    j.fixed_view_mut::<2, 3>(0, 0)
        .copy_from(&(j_point * -rotated.cross_matrix()));
    j.fixed_view_mut::<2, 3>(0, 3).copy_from(&j_point);
    Some((pixel - c.pixel, j))
}

/// Robust cost `½ Σ ρ(|r|²)` and the number of usable correspondences; points
/// that do not project cost as much as a residual of `BEHIND_PENALTY_PX`.
fn robust_cost(
    camera: &Camera,
    cam_from_world: &Rigid3,
    data: &[Correspondence2D3D],
    loss: &RobustLoss,
) -> (f64, usize) {
    const BEHIND_PENALTY_PX: f64 = 1e3;
    let mut cost = 0.0;
    let mut usable = 0;
    for c in data {
        match residual_px(camera, cam_from_world, c) {
            Some(r) => {
                cost += 0.5 * loss.rho(r.norm_squared());
                usable += 1;
            }
            None => cost += 0.5 * loss.rho(BEHIND_PENALTY_PX * BEHIND_PENALTY_PX),
        }
    }
    (cost, usable)
}

/// Non-linear refinement of `cam_from_world` minimising the robust reprojection
/// error (pixels, through the real camera model) of `correspondences` (usually the
/// RANSAC inliers). See the module doc for the formulation.
pub fn refine_absolute_pose(
    camera: &Camera,
    initial_cam_from_world: &Rigid3,
    correspondences: &[Correspondence2D3D],
    options: &PoseRefinementOptions,
) -> Result<PoseRefinementSummary, PoseRefinementError> {
    options.validate()?;
    let initial = *initial_cam_from_world;
    if !(initial.translation.iter().all(|x| x.is_finite())
        && initial.rotation.coords.iter().all(|x| x.is_finite()))
    {
        return Err(PoseRefinementError::NonFinitePose);
    }
    let loss = options.loss;
    let (mut cost, usable) = robust_cost(camera, &initial, correspondences, &loss);
    if usable < 3 {
        return Err(PoseRefinementError::TooFewObservations { usable });
    }
    // Translation steps are compared with the scene's extent for the tolerance.
    let extent_m = correspondences
        .iter()
        .map(|c| initial.transform_point(&c.point_in_world).norm())
        .filter(|d| d.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-9);
    let initial_cost = cost;
    let mut pose = initial;
    let mut damping = 1e-4;
    let mut converged = false;
    let mut iterations = 0;
    while iterations < options.max_iterations {
        iterations += 1;
        let mut hessian = Matrix6::<f64>::zeros();
        let mut gradient = Vector6::<f64>::zeros();
        let rotation = pose.rotation_matrix();
        for c in correspondences {
            let Some((r, j)) = residual_and_jacobian(camera, &rotation, &pose.translation, c)
            else {
                continue;
            };
            let w = loss.weight(r.norm_squared());
            hessian += w * j.transpose() * j;
            gradient += w * j.transpose() * r;
        }
        if !(hessian.iter().all(|x| x.is_finite()) && gradient.iter().all(|x| x.is_finite())) {
            break;
        }
        // Damped steps until one lowers the cost.
        let mut accepted = None;
        while damping <= 1e12 {
            let mut damped = hessian;
            for i in 0..6 {
                damped[(i, i)] += damping * hessian[(i, i)].max(1e-12);
            }
            let Some(step) = damped.cholesky().map(|ch| ch.solve(&(-gradient))) else {
                damping *= 10.0;
                continue;
            };
            let delta_rotation = Vector3::new(step[0], step[1], step[2]);
            let candidate = Rigid3::new(
                UnitQuaternion::from_scaled_axis(delta_rotation) * pose.rotation,
                pose.translation + Vector3::new(step[3], step[4], step[5]),
            );
            let (candidate_cost, _) = robust_cost(camera, &candidate, correspondences, &loss);
            if candidate_cost < cost {
                let step_size = delta_rotation.norm() + step.fixed_rows::<3>(3).norm() / extent_m;
                accepted = Some((candidate, candidate_cost, step_size));
                damping = (damping * 0.1).max(1e-12);
                break;
            }
            damping *= 10.0;
        }
        let Some((candidate, candidate_cost, step_size)) = accepted else {
            // No damping lowers the cost: at a minimum to machine precision.
            converged = true;
            break;
        };
        let decrease = (cost - candidate_cost) / cost.max(f64::MIN_POSITIVE);
        pose = candidate;
        cost = candidate_cost;
        if decrease < options.function_tolerance || step_size < options.step_tolerance {
            converged = true;
            break;
        }
    }
    Ok(PoseRefinementSummary {
        cam_from_world: pose,
        initial_cost,
        final_cost: cost,
        num_iterations: iterations,
        converged,
    })
}

/// A usable correspondence with its unit bearing (camera frame).
#[derive(Clone, Copy, Debug)]
struct PnpDatum {
    correspondence: Correspondence2D3D,
    bearing: Vector3<f64>,
}

/// P3P + pixel reprojection error; local optimisation = a few unrobust
/// Gauss-Newton (LM) steps on the inliers.
struct PnpEstimator<'a> {
    camera: &'a Camera,
    local_refinement: PoseRefinementOptions,
}

impl Estimator for PnpEstimator<'_> {
    type Datum = PnpDatum;
    type Model = Rigid3;
    const MIN_SAMPLES: usize = 3;

    fn estimate(&self, sample: &[PnpDatum]) -> Vec<Rigid3> {
        let bearings = [sample[0].bearing, sample[1].bearing, sample[2].bearing];
        let points = [
            sample[0].correspondence.point_in_world,
            sample[1].correspondence.point_in_world,
            sample[2].correspondence.point_in_world,
        ];
        p3p(&bearings, &points)
    }

    #[inline]
    fn residual_sq(&self, model: &Rigid3, datum: &PnpDatum) -> f64 {
        residual_px(self.camera, model, &datum.correspondence)
            .map_or(f64::INFINITY, |r| r.norm_squared())
    }

    fn refine(&self, model: &Rigid3, inliers: &[PnpDatum]) -> Option<Rigid3> {
        let data: Vec<Correspondence2D3D> = inliers.iter().map(|d| d.correspondence).collect();
        refine_absolute_pose(self.camera, model, &data, &self.local_refinement)
            .ok()
            .map(|s| s.cam_from_world)
    }
}

/// Options of [`estimate_absolute_pose`].
#[derive(Clone, Debug, PartialEq)]
pub struct AbsolutePoseOptions {
    /// RANSAC settings; `max_error` is the reprojection error threshold in
    /// pixels. Defaults: max_error 12 px (COLMAP's `abs_pose_max_error`; the
    /// default suits the initial, not yet refined, poses of incremental SfM),
    /// confidence 0.9999, min_iterations 30, max_iterations 10000, local
    /// optimisation on.
    pub ransac: RansacOptions,
    /// Fewest inliers to accept a pose. Default: 30 (COLMAP's `abs_pose_min_num_inliers`).
    pub min_num_inliers: usize,
    /// Smallest ratio of inliers to all given correspondences (unusable ones
    /// included) to accept a pose. Default: 0.25 (COLMAP's `abs_pose_min_inlier_ratio`).
    pub min_inlier_ratio: f64,
    /// Refine the RANSAC pose on its inliers. Default: true.
    pub refine: bool,
    /// Final refinement. Default: [`PoseRefinementOptions::default`] (Cauchy 1 px).
    pub refinement: PoseRefinementOptions,
    /// Levenberg-Marquardt iterations of each local optimisation step inside
    /// RANSAC (least squares on the current inliers). Default: 4.
    pub local_refinement_iterations: usize,
}

impl Default for AbsolutePoseOptions {
    fn default() -> Self {
        Self {
            ransac: RansacOptions {
                max_error: 12.0,
                min_iterations: 30,
                ..RansacOptions::default()
            },
            min_num_inliers: 30,
            min_inlier_ratio: 0.25,
            refine: true,
            refinement: PoseRefinementOptions::default(),
            local_refinement_iterations: 4,
        }
    }
}

impl AbsolutePoseOptions {
    pub fn validate(&self) -> Result<(), InvalidOptions> {
        self.ransac.validate()?;
        self.refinement.validate()?;
        if !(0.0..=1.0).contains(&self.min_inlier_ratio) {
            return Err(InvalidOptions::new(
                "min_inlier_ratio",
                format!("must be in [0, 1], got {}", self.min_inlier_ratio),
            ));
        }
        Ok(())
    }
}

/// A registered image.
#[derive(Clone, Debug, PartialEq)]
pub struct RegisteredPose {
    pub cam_from_world: Rigid3,
    /// Per input correspondence: reprojection error <= `max_error` px under the
    /// final pose (false for unusable ones: non-finite, or not unprojectable).
    pub inlier_mask: Vec<bool>,
    pub num_inliers: usize,
    /// Inliers of the RANSAC pose (before refinement).
    pub num_ransac_inliers: usize,
    pub num_ransac_iterations: usize,
    /// Mean reprojection error (px) of the final inliers.
    pub mean_inlier_error_px: f64,
    /// `None` when refinement was off or could not run (then the pose is RANSAC's).
    pub refinement: Option<PoseRefinementSummary>,
}

/// What [`estimate_absolute_pose`] concluded.
#[derive(Clone, Debug, PartialEq)]
pub enum AbsolutePoseOutcome {
    Registered(RegisteredPose),
    /// Fewer usable correspondences (finite, unprojectable pixels excluded) than
    /// `max(3, min_num_inliers)`.
    NotEnoughCorrespondences {
        usable: usize,
        needed: usize,
    },
    /// No sample gave a model with at least 3 inliers.
    RansacFailed {
        iterations: usize,
    },
    /// The best pose has too few inliers (count or ratio).
    TooFewInliers {
        num_inliers: usize,
        needed: usize,
    },
}

/// PnP: P3P in LO-RANSAC (reprojection error in pixels through `camera`), then
/// robust refinement on the inliers, then the inliers of the refined pose.
/// `prior_cam_from_world` (e.g. a pose prior or a previous estimate) is scored
/// first: when good, it seeds the adaptive iteration count and the local
/// optimisation. Deterministic for a given RNG state.
pub fn estimate_absolute_pose(
    camera: &Camera,
    correspondences: &[Correspondence2D3D],
    prior_cam_from_world: Option<&Rigid3>,
    options: &AbsolutePoseOptions,
    rng: &mut ChaCha8Rng,
) -> Result<AbsolutePoseOutcome, InvalidOptions> {
    options.validate()?;
    let mut data = Vec::with_capacity(correspondences.len());
    let mut data_index = Vec::with_capacity(correspondences.len());
    for (i, c) in correspondences.iter().enumerate() {
        if !(c
            .pixel
            .iter()
            .chain(c.point_in_world.iter())
            .all(|x| x.is_finite()))
        {
            continue;
        }
        let Some(ray) = camera.unproject(&c.pixel) else {
            continue;
        };
        let norm = ray.norm();
        if !(norm.is_finite() && norm > 0.0) {
            continue;
        }
        data.push(PnpDatum {
            correspondence: *c,
            bearing: ray / norm,
        });
        data_index.push(i);
    }
    let needed = options.min_num_inliers.max(PnpEstimator::MIN_SAMPLES);
    if data.len() < needed {
        return Ok(AbsolutePoseOutcome::NotEnoughCorrespondences {
            usable: data.len(),
            needed,
        });
    }
    let estimator = PnpEstimator {
        camera,
        local_refinement: PoseRefinementOptions {
            loss: RobustLoss::Trivial,
            max_iterations: options.local_refinement_iterations,
            ..PoseRefinementOptions::default()
        },
    };
    let initial: Vec<Rigid3> = prior_cam_from_world.into_iter().copied().collect();
    let report = match ransac::run(&estimator, &data, &initial, &options.ransac, rng) {
        Ok(report) => report,
        Err(RansacError::NoModel { iterations, .. }) => {
            return Ok(AbsolutePoseOutcome::RansacFailed { iterations })
        }
        Err(RansacError::InvalidOptions(e)) => return Err(e),
        Err(RansacError::NotEnoughData { got, needed }) => {
            return Ok(AbsolutePoseOutcome::NotEnoughCorrespondences {
                usable: got,
                needed,
            })
        }
    };
    let enough = |num_inliers: usize| {
        num_inliers >= options.min_num_inliers
            && num_inliers as f64 >= options.min_inlier_ratio * correspondences.len() as f64
    };
    let needed_inliers = options
        .min_num_inliers
        .max((options.min_inlier_ratio * correspondences.len() as f64).ceil() as usize);
    if !enough(report.num_inliers) {
        return Ok(AbsolutePoseOutcome::TooFewInliers {
            num_inliers: report.num_inliers,
            needed: needed_inliers,
        });
    }
    let mut cam_from_world = report.model;
    let mut refinement = None;
    if options.refine {
        let inliers: Vec<Correspondence2D3D> = data
            .iter()
            .zip(&report.inlier_mask)
            .filter(|(_, &inlier)| inlier)
            .map(|(d, _)| d.correspondence)
            .collect();
        if let Ok(summary) =
            refine_absolute_pose(camera, &cam_from_world, &inliers, &options.refinement)
        {
            cam_from_world = summary.cam_from_world;
            refinement = Some(summary);
        }
    }
    let max_sq = options.ransac.max_error * options.ransac.max_error;
    let mut inlier_mask = vec![false; correspondences.len()];
    let mut num_inliers = 0;
    let mut error_sum_px = 0.0;
    for (d, &i) in data.iter().zip(&data_index) {
        let r_sq = estimator.residual_sq(&cam_from_world, d);
        if r_sq <= max_sq {
            inlier_mask[i] = true;
            num_inliers += 1;
            error_sum_px += r_sq.sqrt();
        }
    }
    if !enough(num_inliers) {
        return Ok(AbsolutePoseOutcome::TooFewInliers {
            num_inliers,
            needed: needed_inliers,
        });
    }
    Ok(AbsolutePoseOutcome::Registered(RegisteredPose {
        cam_from_world,
        inlier_mask,
        num_inliers,
        num_ransac_inliers: report.num_inliers,
        num_ransac_iterations: report.num_iterations,
        mean_inlier_error_px: error_sum_px / num_inliers as f64,
        refinement,
    }))
}

/// Reprojection error in pixels of `c` under `cam_from_world`; `None` when the
/// point is behind the camera or outside the model's domain.
pub fn reprojection_error_px(
    camera: &Camera,
    cam_from_world: &Rigid3,
    c: &Correspondence2D3D,
) -> Option<f64> {
    residual_px(camera, cam_from_world, c).map(|r| r.norm())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::CameraId;
    use rand::{Rng, SeedableRng};

    fn pinhole() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::Pinhole,
            width: 1920,
            height: 1080,
            params: vec![1400.0, 1390.0, 960.0, 540.0],
        }
    }

    fn opencv() -> Camera {
        Camera {
            id: CameraId(2),
            model: CameraModel::OpenCv,
            width: 1920,
            height: 1080,
            params: vec![1400.0, 1390.0, 962.0, 538.0, -0.25, 0.08, 0.001, -0.0015],
        }
    }

    fn scene(
        camera: &Camera,
        truth: &Rigid3,
        n: usize,
        rng: &mut ChaCha8Rng,
    ) -> Vec<Correspondence2D3D> {
        let world_from_cam = truth.inverse();
        (0..n)
            .map(|_| {
                let pixel = Vector2::new(
                    rng.gen_range(0.0..f64::from(camera.width)),
                    rng.gen_range(0.0..f64::from(camera.height)),
                );
                let ray = camera.unproject(&pixel).unwrap();
                let point_in_cam = ray * rng.gen_range(3.0..20.0);
                Correspondence2D3D {
                    pixel,
                    point_in_world: world_from_cam.transform_point(&point_in_cam),
                }
            })
            .collect()
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        for camera in [pinhole(), opencv()] {
            let pose = Rigid3::new(
                UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0),
                Vector3::new(1.0, -2.0, 0.5),
            );
            for c in scene(&camera, &pose, 20, &mut rng) {
                let rotation = pose.rotation_matrix();
                let (_, j) =
                    residual_and_jacobian(&camera, &rotation, &pose.translation, &c).unwrap();
                for k in 0..6 {
                    let h = 1e-6;
                    let perturbed = |sign: f64| {
                        let mut delta = Vector6::<f64>::zeros();
                        delta[k] = sign * h;
                        let p = Rigid3::new(
                            UnitQuaternion::from_scaled_axis(delta.fixed_rows::<3>(0).into_owned())
                                * pose.rotation,
                            pose.translation + delta.fixed_rows::<3>(3),
                        );
                        residual_px(&camera, &p, &c).unwrap()
                    };
                    let numeric = (perturbed(1.0) - perturbed(-1.0)) / (2.0 * h);
                    let analytic = j.column(k);
                    assert!(
                        (numeric - analytic).norm() < 1e-5 * (1.0 + analytic.norm()),
                        "{} column {k}: {numeric:?} vs {analytic:?}",
                        camera.model.name()
                    );
                }
            }
        }
    }

    #[test]
    fn refinement_converges_on_noiseless_data() {
        // From a perturbed pose, least squares converges to the truth exactly.
        let camera = opencv();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let truth = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
            Vector3::new(0.5, -1.0, 2.0),
        );
        let data = scene(&camera, &truth, 50, &mut rng);
        let start = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.02, -0.01, 0.015) * truth.rotation,
            truth.translation + Vector3::new(0.1, -0.05, 0.2),
        );
        let summary = refine_absolute_pose(
            &camera,
            &start,
            &data,
            &PoseRefinementOptions {
                loss: RobustLoss::Trivial,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(summary.converged);
        assert!(summary.final_cost < 1e-12, "{}", summary.final_cost);
        assert!(summary.cam_from_world.rotation.angle_to(&truth.rotation) < 1e-9);
        assert!((summary.cam_from_world.translation - truth.translation).norm() < 1e-8);
    }

    #[test]
    fn too_few_and_invalid() {
        let camera = pinhole();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let data = scene(&camera, &Rigid3::identity(), 10, &mut rng);
        let outcome = estimate_absolute_pose(
            &camera,
            &data,
            None,
            &AbsolutePoseOptions::default(),
            &mut rng,
        )
        .unwrap();
        assert_eq!(
            outcome,
            AbsolutePoseOutcome::NotEnoughCorrespondences {
                usable: 10,
                needed: 30
            }
        );
        let bad = AbsolutePoseOptions {
            min_inlier_ratio: 2.0,
            ..Default::default()
        };
        assert!(estimate_absolute_pose(&camera, &data, None, &bad, &mut rng).is_err());
        assert_eq!(
            refine_absolute_pose(
                &camera,
                &Rigid3::identity(),
                &data[..2],
                &Default::default()
            ),
            Err(PoseRefinementError::TooFewObservations { usable: 2 })
        );
    }

    #[test]
    fn losses() {
        let huber = RobustLoss::Huber { scale_px: 2.0 };
        assert_eq!(huber.rho(1.0), 1.0);
        assert_eq!(huber.rho(16.0), 2.0 * 2.0 * 4.0 - 4.0);
        assert_eq!(huber.weight(16.0), 0.5);
        let cauchy = RobustLoss::Cauchy { scale_px: 1.0 };
        assert!((cauchy.rho(1.0) - 2f64.ln()).abs() < 1e-15);
        assert_eq!(cauchy.weight(1.0), 0.5);
        // ρ' is the derivative of ρ.
        for loss in [huber, cauchy] {
            for s in [0.5, 3.0, 40.0] {
                let numeric = (loss.rho(s + 1e-6) - loss.rho(s - 1e-6)) / 2e-6;
                assert!((numeric - loss.weight(s)).abs() < 1e-8);
            }
        }
    }
}
