//! Bundle adjustment of the map state through the Ceres bridge: builds a
//! [`BundleAdjustmentProblem`] for a local or global solve (what varies is the
//! [`BundleConfig`]), asks the associator for LiDAR planes of the variable
//! points, solves, and writes poses, points and (optionally) intrinsics back.
use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{DMatrix, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use super::associate::{AssociationQuery, PlaneAssociator, SolveKind};
use super::options::BundleOptions;
use super::report::PoseChangeRecord;
use super::state::{MapState, PointPlane, MAX_IMPLAUSIBLE_REFINEMENTS};
use crate::scene::{Camera, CameraId, ImageId, Point3DId, Rigid3};
use crate::solver::{
    clustered_pose_covariances, pose_covariances, sigma_of_variance, solve, BaCamera,
    BaObservation, BaPoint, BaPose, BundleAdjustmentProblem, ConstantParams, CovarianceError,
    LossFunction, PlaneFamily, PoseCovariances, PosePrior, SolveTimes, SolverError, SolverOptions,
};

/// What varies in one solve.
#[derive(Clone, Debug, Default)]
pub struct BundleConfig {
    /// Images whose poses vary (registered ones only).
    pub variable_images: BTreeSet<ImageId>,
    /// Images held fixed even if listed as variable (the gauge).
    pub fixed_images: BTreeSet<ImageId>,
    /// Cameras whose focal length and distortion vary (the principal point
    /// is held); the others are constant.
    pub refine_cameras: BTreeSet<CameraId>,
    /// Soft priors on poses (applied when the image's pose varies).
    pub pose_priors: Vec<SoftPosePrior>,
}

/// Why refined intrinsics cannot be right, if they cannot (COLMAP's bounds
/// on a camera after bundle adjustment): a focal length outside 0.1 to 10
/// times the larger image side, a distortion coefficient above 1 in size, a
/// value that is not finite, or, when it was refined
/// (`principal_point_refined`), a principal point outside the image.
pub fn implausible_intrinsics(camera: &Camera, principal_point_refined: bool) -> Option<String> {
    if camera.params.iter().any(|p| !p.is_finite()) {
        return Some("a parameter is not finite".into());
    }
    let side = f64::from(camera.width.max(camera.height));
    for &k in camera.model.focal_idxs() {
        let ratio = camera.params[k] / side;
        if !(0.1..=10.0).contains(&ratio) {
            return Some(format!(
                "focal length {:.1} px is {ratio:.3} times the larger image side",
                camera.params[k]
            ));
        }
    }
    let pp = camera.model.principal_point_idxs();
    let (cx, cy) = (camera.params[pp[0]], camera.params[pp[1]]);
    if principal_point_refined
        && !((0.0..=f64::from(camera.width)).contains(&cx)
            && (0.0..=f64::from(camera.height)).contains(&cy))
    {
        return Some(format!(
            "principal point ({cx:.1}, {cy:.1}) lies outside the {}x{} image",
            camera.width, camera.height
        ));
    }
    let fixed: Vec<usize> = camera
        .model
        .focal_idxs()
        .iter()
        .chain(pp.iter())
        .copied()
        .collect();
    for (k, &p) in camera.params.iter().enumerate() {
        if !fixed.contains(&k) && p.abs() > 1.0 {
            return Some(format!("distortion parameter {k} is {p:.3}"));
        }
    }
    None
}

/// The intrinsics blocks a solve of `config` refines: those of the cameras
/// in `config.refine_cameras` and of the cameras they share intrinsics with,
/// unless refinement took them out of bounds too often
/// ([`MapState::intrinsics_refinable`]).
fn refined_intrinsics(state: &MapState, config: &BundleConfig) -> BTreeSet<CameraId> {
    config
        .refine_cameras
        .iter()
        .map(|&id| state.intrinsics_of(id))
        .filter(|&owner| state.intrinsics_refinable(owner))
        .collect()
}

/// A soft prior on one image's pose: residuals `position_weight * (C - C0)`
/// (metres) and `rotation_weight * angle(R R0^T)` (radians), in pixel
/// equivalents.
#[derive(Clone, Debug)]
pub struct SoftPosePrior {
    pub image: ImageId,
    pub cam_from_world: Rigid3,
    pub position_weight: f64,
    pub rotation_weight: f64,
}

/// One solve, as reported.
#[derive(Clone, Debug, Serialize)]
pub struct SolveRecord {
    pub kind: SolveKind,
    /// Registered images when the solve ran.
    pub num_registered: usize,
    pub num_variable_poses: usize,
    pub num_constant_poses: usize,
    pub num_points: usize,
    pub num_observations: usize,
    /// Planes by kind (`num_planes` = projection + nearest + ground).
    pub num_planes: usize,
    pub num_projection_planes: usize,
    pub num_nearest_planes: usize,
    pub num_ground_planes: usize,
    /// Point-to-plane distances of the associated points before and after the solve.
    pub plane_distance_before_m: DistanceStats,
    pub plane_distance_after_m: DistanceStats,
    /// Reprojection errors of the solve's observations before and after.
    pub reprojection_before_px: ErrorStats,
    pub reprojection_after_px: ErrorStats,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
    pub usable: bool,
    /// The mapper went back to the state before this solve (the probe of
    /// given focal lengths that kept them held): its result is not in the
    /// model.
    pub discarded: bool,
    /// Cameras (intrinsics owners) this solve held because refining them
    /// left them implausible in a first solve, which was thrown away; its
    /// time is included.
    pub intrinsics_held: Vec<u32>,
    /// Ceres time, seconds.
    pub time_s: f64,
    /// Time of the association (projection and nearest-neighbour search), seconds.
    pub association_time_s: f64,
    /// The bridge's and Ceres' split of the solve's time.
    pub solver_times: SolveTimes,
    /// Ceres' Schur eliminator block sizes, "row,e,f" ("d": dynamic).
    pub schur_structure: String,
    /// The whole call: building the problem, association, the solve, the
    /// statistics before and after, writing the result back; seconds.
    pub wall_s: f64,
    /// How far the initial image was from its given pose after the solve
    /// (with LiDAR constraints): how a model slides along a direction the
    /// map holds only weakly, solve by solve.
    pub initial_image_change: Option<PoseChangeRecord>,
    /// [`crate::sfm::align::SimilarityConstraint::ratio`] of the model's
    /// planes after the solve (with LiDAR constraints).
    pub similarity_constraint_ratio: Option<f64>,
}

impl SolveRecord {
    /// A solve of `kind` at `num_registered` images that had nothing to
    /// solve: no poses, points, planes or time.
    pub fn empty(kind: SolveKind, num_registered: usize) -> Self {
        Self {
            kind,
            num_registered,
            num_variable_poses: 0,
            num_constant_poses: 0,
            num_points: 0,
            num_observations: 0,
            num_planes: 0,
            num_projection_planes: 0,
            num_nearest_planes: 0,
            num_ground_planes: 0,
            plane_distance_before_m: DistanceStats::default(),
            plane_distance_after_m: DistanceStats::default(),
            reprojection_before_px: ErrorStats::default(),
            reprojection_after_px: ErrorStats::default(),
            initial_cost: 0.0,
            final_cost: 0.0,
            iterations: 0,
            usable: true,
            discarded: false,
            intrinsics_held: Vec::new(),
            time_s: 0.0,
            association_time_s: 0.0,
            solver_times: SolveTimes::default(),
            schur_structure: String::new(),
            wall_s: 0.0,
            initial_image_change: None,
            similarity_constraint_ratio: None,
        }
    }
}

/// Mean and median of unsigned distances.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct DistanceStats {
    pub mean: f64,
    pub median: f64,
}

impl DistanceStats {
    fn of(values: Vec<f64>) -> Self {
        let Some(stats) = crate::eval::Stats::of(&values) else {
            return Self::default();
        };
        Self {
            mean: values.iter().sum::<f64>() / values.len() as f64,
            median: stats.median,
        }
    }
}

/// Mean and standard deviation of errors.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct ErrorStats {
    pub mean: f64,
    pub std: f64,
    pub count: usize,
}

impl ErrorStats {
    fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Self::default();
        }
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
            count: values.len(),
        }
    }
}

/// Reprojection errors (pixels) of every observation of `points` by a registered image.
fn reprojection_errors(state: &MapState, points: &[Point3DId]) -> Vec<f64> {
    // In parallel, in the points' order.
    points
        .par_iter()
        .map(|pid| {
            let Some(p) = state.points.get(pid) else {
                return Vec::new();
            };
            p.track
                .iter()
                .filter_map(|e| {
                    let pose = state.pose(e.image_id)?;
                    super::geometry::reprojection_error_sq(
                        state.camera_of(e.image_id),
                        &pose,
                        &p.xyz,
                        &state.keypoint(*e),
                    )
                    .map(f64::sqrt)
                })
                .collect::<Vec<f64>>()
        })
        .collect::<Vec<_>>()
        .concat()
}

/// A solve's problem with what maps it back onto the state.
struct BuiltBundle {
    problem: BundleAdjustmentProblem,
    pose_idx: BTreeMap<ImageId, u32>,
    camera_idx: BTreeMap<CameraId, u32>,
    point_list: Vec<Point3DId>,
    queries: Vec<AssociationQuery>,
    /// The solve's local frame: `X_local = X_world - origin`.
    origin: Vector3<f64>,
    /// The intrinsics refined ([`refined_intrinsics`]).
    refined: BTreeSet<CameraId>,
}

/// The problem of one solve, without planes. The variable points are those
/// observed by a variable image; every other registered image observing them
/// joins as a constant pose.
fn build_bundle(state: &MapState, config: &BundleConfig) -> BuiltBundle {
    let point_ids: BTreeSet<Point3DId> = config
        .variable_images
        .iter()
        .filter_map(|i| state.images.get(i))
        .filter(|img| img.is_registered())
        .flat_map(|img| img.point3d.iter().flatten().copied())
        .collect();
    let mut problem = BundleAdjustmentProblem::default();
    let mut pose_idx: BTreeMap<ImageId, u32> = BTreeMap::new();
    let mut camera_idx: BTreeMap<CameraId, u32> = BTreeMap::new();
    let mut point_list: Vec<Point3DId> = Vec::with_capacity(point_ids.len());
    let mut queries = Vec::with_capacity(point_ids.len());
    // Poses and cameras in image-id order for determinism.
    let mut images_needed: BTreeSet<ImageId> = BTreeSet::new();
    for pid in &point_ids {
        for e in &state.points[pid].track {
            if state.pose(e.image_id).is_some() {
                images_needed.insert(e.image_id);
            }
        }
    }
    // The problem is solved in a local frame `X_local = X_world - origin`
    // (origin: the mean camera centre), so that georeferenced coordinates
    // (10^5..10^6 m) do not wreck the conditioning.
    let origin = if images_needed.is_empty() {
        Vector3::zeros()
    } else {
        images_needed
            .iter()
            .map(|&i| state.pose(i).expect("registered").camera_center())
            .sum::<Vector3<f64>>()
            / images_needed.len() as f64
    };
    let to_local =
        |pose: &Rigid3| Rigid3::new(pose.rotation, pose.translation + pose.rotation * origin);
    let refined = refined_intrinsics(state, config);
    for &image in &images_needed {
        let variable =
            config.variable_images.contains(&image) && !config.fixed_images.contains(&image);
        let pose = state.pose(image).expect("registered, checked above");
        pose_idx.insert(image, problem.poses.len() as u32);
        problem.poses.push(BaPose::new(&to_local(&pose), !variable));
        // Cameras with the same intrinsics in the database share one block.
        let cam_id = state.intrinsics_of(state.images[&image].camera_id);
        if let std::collections::btree_map::Entry::Vacant(slot) = camera_idx.entry(cam_id) {
            slot.insert(problem.cameras.len() as u32);
            // Refined: focal length and distortion; the principal point stays
            // (COLMAP's default: it is poorly determined by BA) unless the
            // state lists the camera.
            let constant = if refined.contains(&cam_id)
                && state.principal_point_refined.contains(&cam_id)
            {
                ConstantParams::None
            } else if refined.contains(&cam_id) {
                let camera = &state.cameras[&cam_id];
                let pp = camera.model.principal_point_idxs();
                ConstantParams::Mask((0..camera.params.len()).map(|k| pp.contains(&k)).collect())
            } else {
                ConstantParams::All
            };
            problem
                .cameras
                .push(BaCamera::new(&state.cameras[&cam_id], constant));
        }
    }
    for pid in &point_ids {
        let p = &state.points[pid];
        let idx = problem.points.len() as u32;
        problem.points.push(BaPoint::new(&(p.xyz - origin), false));
        point_list.push(*pid);
        for e in &p.track {
            let Some(&pi) = pose_idx.get(&e.image_id) else {
                continue;
            };
            let xy = state.keypoint(*e);
            problem.observations.push(BaObservation::new(
                pi,
                camera_idx[&state.intrinsics_of(state.images[&e.image_id].camera_id)],
                idx,
                [xy.x, xy.y],
            ));
        }
        queries.push(AssociationQuery {
            point_idx: idx,
            point_id: *pid,
            position_in_world: p.xyz,
            num_global_ba: p.num_global_ba,
            track_len: p.track.len(),
        });
    }
    for prior in &config.pose_priors {
        let Some(&pi) = pose_idx.get(&prior.image) else {
            continue;
        };
        if problem.poses[pi as usize].constant {
            continue;
        }
        let c = prior.cam_from_world.camera_center() - origin;
        problem.pose_priors.push(PosePrior {
            pose_idx: pi,
            position_in_world: Some([c.x, c.y, c.z]),
            cam_from_world_rotation: (prior.rotation_weight > 0.0)
                .then(|| prior.cam_from_world.quaternion_wxyz()),
            position_weight: prior.position_weight,
            rotation_weight: prior.rotation_weight,
        });
    }
    BuiltBundle {
        problem,
        pose_idx,
        camera_idx,
        point_list,
        queries,
        origin,
        refined,
    }
}

/// The solve's planes from `associator`, moved into the solve's local frame,
/// and each point's plane in the world frame.
fn add_planes(
    built: &mut BuiltBundle,
    state: &MapState,
    kind: SolveKind,
    associator: &dyn PlaneAssociator,
) -> BTreeMap<u32, PointPlane> {
    let origin = built.origin;
    built.problem.planes = associator.associate(kind, state, &built.queries);
    for plane in &mut built.problem.planes {
        plane.offset_m -= Vector3::from(plane.normal).dot(&origin);
    }
    built
        .problem
        .planes
        .iter()
        .map(|p| {
            let normal = Vector3::from(p.normal);
            (
                p.point_idx,
                PointPlane {
                    family: p.family,
                    normal,
                    // Back from the solve's local frame to the world frame.
                    offset_m: p.offset_m + normal.dot(&origin),
                },
            )
        })
        .collect()
}

/// The solver options of a solve of `kind`.
fn solver_options(
    kind: SolveKind,
    associator: &dyn PlaneAssociator,
    options: &BundleOptions,
) -> SolverOptions {
    SolverOptions {
        reprojection_loss: LossFunction::SoftL1 {
            scale: options.reprojection_loss_px,
        },
        plane_loss: LossFunction::Trivial,
        plane_family_losses: associator.losses(kind),
        max_iterations: match kind {
            SolveKind::Local | SolveKind::LocalRefine => options.local_max_iterations,
            _ => options.global_max_iterations,
        },
        num_threads: options.num_threads,
        function_tolerance: options.function_tolerance,
        ..Default::default()
    }
}

/// Runs one bundle adjustment on `state` (see [`build_bundle`] for what varies).
pub fn bundle_adjust(
    state: &mut MapState,
    config: &BundleConfig,
    kind: SolveKind,
    associator: &dyn PlaneAssociator,
    options: &BundleOptions,
) -> Result<SolveRecord, SolverError> {
    let started = std::time::Instant::now();
    let mut built = build_bundle(state, config);
    let num_variable_poses = built.problem.poses.iter().filter(|p| !p.constant).count();
    if built.problem.observations.is_empty()
        || num_variable_poses == 0 && built.point_list.is_empty()
    {
        return Ok(SolveRecord {
            num_variable_poses,
            num_constant_poses: built.problem.poses.len() - num_variable_poses,
            wall_s: started.elapsed().as_secs_f64(),
            ..SolveRecord::empty(kind, state.num_registered())
        });
    }
    let association_start = std::time::Instant::now();
    let plane_of_point = add_planes(&mut built, state, kind, associator);
    let association_time_s = association_start.elapsed().as_secs_f64();
    let BuiltBundle {
        mut problem,
        pose_idx,
        camera_idx,
        point_list,
        origin,
        refined,
        ..
    } = built;
    let plane_distances = |state: &MapState| -> Vec<f64> {
        plane_of_point
            .iter()
            .map(|(&i, plane)| plane.distance_m(&state.points[&point_list[i as usize]].xyz))
            .collect()
    };
    let plane_distance_before_m = DistanceStats::of(plane_distances(state));
    let reprojection_before_px = ErrorStats::of(&reprojection_errors(state, &point_list));
    let solver_options = solver_options(kind, associator, options);
    let summary = solve(&mut problem, &solver_options)?;
    // Refined intrinsics outside COLMAP's bounds make the whole solve
    // suspect (its poses and points went with them): it is run again with
    // those cameras held.
    if summary.usable {
        let implausible: BTreeSet<CameraId> = camera_idx
            .iter()
            .filter(|(id, _)| refined.contains(id))
            .filter_map(|(&id, &ci)| {
                let camera = Camera {
                    params: problem.cameras[ci as usize].params.clone(),
                    ..state.cameras[&id].clone()
                };
                let why =
                    implausible_intrinsics(&camera, state.principal_point_refined.contains(&id))?;
                log::warn!(
                    "{kind:?} bundle adjustment: the refined intrinsics of camera {} are implausible ({why}): {:?}; solving again with them held",
                    id.0,
                    camera.params
                );
                Some(id)
            })
            .collect();
        if !implausible.is_empty() {
            for &id in &implausible {
                let count = state.implausible_refinements.entry(id).or_default();
                *count += 1;
                if *count == MAX_IMPLAUSIBLE_REFINEMENTS {
                    log::warn!(
                        "camera {}: refined out of bounds in {count} solves; its intrinsics are held at {:?} for the rest of the run",
                        id.0,
                        state.cameras[&id].params
                    );
                }
            }
            let held = BundleConfig {
                refine_cameras: config
                    .refine_cameras
                    .iter()
                    .copied()
                    .filter(|&id| !implausible.contains(&state.intrinsics_of(id)))
                    .collect(),
                ..config.clone()
            };
            let mut record = bundle_adjust(state, &held, kind, associator, options)?;
            record.time_s += summary.time_s;
            record.association_time_s += association_time_s;
            record.solver_times += summary.times;
            record.wall_s = started.elapsed().as_secs_f64();
            record
                .intrinsics_held
                .extend(implausible.iter().map(|id| id.0));
            record.intrinsics_held.sort_unstable();
            return Ok(record);
        }
    }
    if summary.usable {
        for (&image, &pi) in &pose_idx {
            if !problem.poses[pi as usize].constant {
                let local = problem.poses[pi as usize].rigid();
                let pose = Rigid3::new(local.rotation, local.translation - local.rotation * origin);
                state.register(image, pose);
            }
        }
        for (i, pid) in point_list.iter().enumerate() {
            if let Some(p) = state.points.get_mut(pid) {
                p.xyz = problem.points[i].position() + origin;
                p.plane = plane_of_point.get(&(i as u32)).copied();
                p.anchored = p.plane.is_some();
                if kind == SolveKind::Global || kind.is_final() {
                    p.num_global_ba += 1;
                }
            }
        }
        for (cam_id, &ci) in &camera_idx {
            if !refined.contains(cam_id) {
                continue;
            }
            // Every camera sharing this one's intrinsics takes them.
            let params = &problem.cameras[ci as usize].params;
            for id in state.cameras_sharing(*cam_id) {
                if let Some(member) = state.cameras.get_mut(&id) {
                    member.params.clone_from(params);
                }
            }
        }
    } else {
        log::warn!("{kind:?} bundle adjustment not usable: {}", summary.message);
    }
    let count = |family: PlaneFamily| problem.planes.iter().filter(|p| p.family == family).count();
    Ok(SolveRecord {
        kind,
        num_registered: state.num_registered(),
        num_variable_poses,
        num_constant_poses: problem.poses.len() - num_variable_poses,
        num_points: point_list.len(),
        num_observations: problem.observations.len(),
        num_planes: problem.planes.len(),
        num_projection_planes: count(PlaneFamily::Projection),
        num_nearest_planes: count(PlaneFamily::Nearest),
        num_ground_planes: count(PlaneFamily::Ground),
        plane_distance_before_m,
        plane_distance_after_m: DistanceStats::of(plane_distances(state)),
        reprojection_before_px,
        reprojection_after_px: ErrorStats::of(&reprojection_errors(state, &point_list)),
        initial_cost: summary.initial_cost,
        final_cost: summary.final_cost,
        iterations: summary.num_iterations,
        usable: summary.usable,
        discarded: false,
        intrinsics_held: Vec::new(),
        time_s: summary.time_s,
        association_time_s,
        solver_times: summary.times,
        schur_structure: summary.schur_structure.clone(),
        wall_s: started.elapsed().as_secs_f64(),
        initial_image_change: None,
        similarity_constraint_ratio: None,
    })
}

/// One image's pose uncertainty (one standard deviation) at the final
/// state: first-order, from the information the final solve's residuals hold
/// there (planes associated afresh, then held fixed), every residual scaled by
/// the residual variance the fit estimates (pose priors too: their weights
/// are pixel equivalents like the planes'); see [`crate::solver::covariance`].
#[derive(Clone, Debug, Serialize)]
pub struct PoseUncertainty {
    /// Camera centre along the map's x, y and z axes, metres.
    pub centre_sigma_m: [f64; 3],
    /// Along the centre's least determined direction, metres.
    pub centre_sigma_major_m: f64,
    /// That direction (unit, map frame; sign: largest component positive).
    pub centre_major_axis: [f64; 3],
    /// The centre's full covariance in the map frame, square metres (rows).
    pub centre_covariance_m2: [[f64; 3]; 3],
    /// About the rotation's least determined axis, degrees.
    pub rotation_sigma_deg: f64,
    /// The cluster-robust estimate (`bundle.uncertainty_cluster_m`; see
    /// [`crate::solver::clustered_pose_covariances`]): the centre along its
    /// least determined direction, metres; absent when turned off.
    pub clustered_centre_sigma_major_m: Option<f64>,
    /// Its centre covariance in the map frame, square metres (rows).
    pub clustered_centre_covariance_m2: Option<[[f64; 3]; 3]>,
    /// Its rotation about the least determined axis, degrees.
    pub clustered_rotation_sigma_deg: Option<f64>,
}

/// A 3x3 matrix as its rows (as `report.json` writes covariances).
fn rows(m: &nalgebra::Matrix3<f64>) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)]])
}

/// Cluster ids of points at `positions` (world frame): the cube of side
/// `cell_m` each lies in, numbered in the order first met.
fn cell_clusters(positions: impl Iterator<Item = Vector3<f64>>, cell_m: f64) -> Vec<u32> {
    let mut ids: BTreeMap<[i64; 3], u32> = BTreeMap::new();
    positions
        .map(|x| {
            let cell = (x / cell_m).map(|v| v.floor() as i64);
            let next = ids.len() as u32;
            *ids.entry([cell.x, cell.y, cell.z]).or_insert(next)
        })
        .collect()
}

/// Pose uncertainties of the variable images of `config`, from a solve of
/// `kind` at the current state (planes associated afresh), and of the
/// intrinsics it refines; also the residual standard deviation (pixels) and
/// the number of points whose own position was not fully determined.
pub fn pose_uncertainty(
    state: &MapState,
    config: &BundleConfig,
    kind: SolveKind,
    associator: &dyn PlaneAssociator,
    options: &BundleOptions,
) -> Result<Uncertainties, CovarianceError> {
    let (built, cov) = covariances_at(state, config, kind, associator, options)?;
    let mut out = BTreeMap::new();
    for (&image, &pi) in &built.pose_idx {
        let pi = pi as usize;
        let (Some(centre), Some(rotation)) =
            (cov.centre_covariance(pi), cov.rotation_covariance(pi))
        else {
            continue;
        };
        let sigma = cov.centre_sigma_m(pi).unwrap_or_default();
        let eig = centre.symmetric_eigen();
        let k = eig.eigenvalues.imax();
        let mut axis: Vector3<f64> = eig.eigenvectors.column(k).into_owned();
        if axis[axis.iamax()] < 0.0 {
            axis = -axis;
        }
        let rotation_max = rotation.symmetric_eigen().eigenvalues.max();
        let clustered_centre = cov.clustered_centre_covariance(pi);
        let clustered_rotation = cov.clustered_rotation_covariance(pi);
        out.insert(
            image,
            PoseUncertainty {
                clustered_centre_sigma_major_m: clustered_centre
                    .map(|c| sigma_of_variance(c.symmetric_eigen().eigenvalues.max())),
                clustered_centre_covariance_m2: clustered_centre.as_ref().map(rows),
                clustered_rotation_sigma_deg: clustered_rotation
                    .map(|r| sigma_of_variance(r.symmetric_eigen().eigenvalues.max()).to_degrees()),
                centre_sigma_m: [sigma.x, sigma.y, sigma.z],
                centre_sigma_major_m: sigma_of_variance(eig.eigenvalues[k]),
                centre_major_axis: [axis.x, axis.y, axis.z],
                centre_covariance_m2: rows(&centre),
                rotation_sigma_deg: sigma_of_variance(rotation_max).to_degrees(),
            },
        );
    }
    Ok(Uncertainties {
        poses: out,
        intrinsics: intrinsics_uncertainties(state, &built, &cov),
        residual_sigma_px: cov.residual_variance.sqrt(),
        num_degenerate_points: cov.num_degenerate_points,
    })
}

/// The problem of a solve of `kind` at the current state (planes
/// associated afresh, then held) and its covariances: cluster-robust too
/// when `options.uncertainty_cluster_m` is set.
fn covariances_at(
    state: &MapState,
    config: &BundleConfig,
    kind: SolveKind,
    associator: &dyn PlaneAssociator,
    options: &BundleOptions,
) -> Result<(BuiltBundle, PoseCovariances), CovarianceError> {
    let mut built = build_bundle(state, config);
    add_planes(&mut built, state, kind, associator);
    let solver_options = solver_options(kind, associator, options);
    let cov = if options.uncertainty_cluster_m > 0.0 {
        let clusters = cell_clusters(
            built.point_list.iter().map(|pid| state.points[pid].xyz),
            options.uncertainty_cluster_m,
        );
        clustered_pose_covariances(&built.problem, &solver_options, &clusters)?
    } else {
        pose_covariances(&built.problem, &solver_options)?
    };
    Ok((built, cov))
}

/// How well the data fix a refined camera's intrinsics: one standard
/// deviation of its mean focal length (fx and fy averaged where the model
/// has both), pixels, and of each parameter.
#[derive(Clone, Debug, PartialEq)]
pub struct IntrinsicsUncertainty {
    /// From the residuals' own variance (as [`PoseUncertainty`]).
    pub focal_sigma_px: f64,
    /// Cluster-robust (`bundle.uncertainty_cluster_m`); `None` when off.
    pub clustered_focal_sigma_px: Option<f64>,
    /// Per parameter in the model's order: its sigma, `None` where held
    /// (the principal point unless it is refined).
    pub params_sigma: Vec<Option<f64>>,
    /// The same, cluster-robust; `None` when off.
    pub clustered_params_sigma: Option<Vec<Option<f64>>>,
}

/// What [`pose_uncertainty`] finds.
#[derive(Clone, Debug)]
pub struct Uncertainties {
    /// Per variable image.
    pub poses: BTreeMap<ImageId, PoseUncertainty>,
    /// Per camera whose focal length varies in the solve (the owner of
    /// shared intrinsics).
    pub intrinsics: BTreeMap<CameraId, IntrinsicsUncertainty>,
    /// Standard deviation of a unit-weight residual, pixels.
    pub residual_sigma_px: f64,
    /// Points whose own position was not fully determined.
    pub num_degenerate_points: usize,
}

/// The intrinsics' uncertainties of the cameras whose focal length varies
/// in `built`, from its covariances `cov`.
fn intrinsics_uncertainties(
    state: &MapState,
    built: &BuiltBundle,
    cov: &PoseCovariances,
) -> BTreeMap<CameraId, IntrinsicsUncertainty> {
    let mut out = BTreeMap::new();
    for (&id, &ci) in &built.camera_idx {
        let ci = ci as usize;
        let camera = &built.problem.cameras[ci];
        let (Some(model), Some(Some(block))) =
            (state.cameras.get(&id).map(|c| c.model), cov.cameras.get(ci))
        else {
            continue;
        };
        // The covariance's rows are the variable parameters in order.
        let variable: Vec<usize> = (0..camera.params.len())
            .filter(|&k| !camera.is_param_constant(k))
            .collect();
        let Some(rows) = model
            .focal_idxs()
            .iter()
            .map(|k| variable.iter().position(|v| v == k))
            .collect::<Option<Vec<usize>>>()
        else {
            continue;
        };
        let n = rows.len() as f64;
        let focal = |block: &DMatrix<f64>| {
            let variance = rows
                .iter()
                .flat_map(|&a| rows.iter().map(move |&b| block[(a, b)]))
                .sum::<f64>()
                / (n * n);
            sigma_of_variance(variance)
        };
        let params = |block: &DMatrix<f64>| {
            (0..camera.params.len())
                .map(|k| {
                    let row = variable.iter().position(|&v| v == k)?;
                    Some(sigma_of_variance(block[(row, row)]))
                })
                .collect::<Vec<_>>()
        };
        let clustered = cov.clustered_cameras.get(ci).and_then(Option::as_ref);
        out.insert(
            id,
            IntrinsicsUncertainty {
                focal_sigma_px: focal(block),
                clustered_focal_sigma_px: clustered.map(focal),
                params_sigma: params(block),
                clustered_params_sigma: clustered.map(params),
            },
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::CameraModel;

    #[test]
    fn implausible_intrinsics_uses_colmaps_bounds() {
        let camera = |model: CameraModel, params: Vec<f64>| Camera {
            id: CameraId(1),
            model,
            width: 640,
            height: 480,
            params,
        };
        let radial = |f: f64, k: f64| camera(CameraModel::SimpleRadial, vec![f, 320.0, 240.0, k]);
        let radial_at =
            |cx: f64, cy: f64| camera(CameraModel::SimpleRadial, vec![512.0, cx, cy, 0.0]);
        assert_eq!(implausible_intrinsics(&radial(512.0, -0.04), false), None);
        // 0.1 and 10 times the larger side (640 px) are the limits.
        assert_eq!(implausible_intrinsics(&radial(64.0, 0.0), false), None);
        assert_eq!(implausible_intrinsics(&radial(6400.0, 0.0), false), None);
        let low = implausible_intrinsics(&radial(63.0, 0.0), false).unwrap();
        assert!(low.contains("63.0 px") && low.contains("0.098"), "{low}");
        assert!(implausible_intrinsics(&radial(6500.0, 0.0), false).is_some());
        let k = implausible_intrinsics(&radial(512.0, -1.5), false).unwrap();
        assert!(k.contains("parameter 3 is -1.500"), "{k}");
        assert!(implausible_intrinsics(&radial(f64::NAN, 0.0), false).is_some());
        // A principal point far outside 1 is not a distortion parameter; fy counts as a focal.
        let pinhole = camera(CameraModel::Pinhole, vec![500.0, 20.0, 320.0, 240.0]);
        assert!(implausible_intrinsics(&pinhole, false)
            .unwrap()
            .contains("20.0 px"));
        let opencv = camera(
            CameraModel::OpenCv,
            vec![500.0, 500.0, 320.0, 240.0, -0.1, 0.01, 0.0, 0.0],
        );
        assert_eq!(implausible_intrinsics(&opencv, false), None);
        // A refined principal point outside the 640 x 480 image (on its edge
        // is not); one held there is the database's and not questioned.
        assert_eq!(implausible_intrinsics(&radial_at(640.0, 0.0), true), None);
        let outside = implausible_intrinsics(&radial_at(320.0, 481.0), true).unwrap();
        assert!(outside.contains("(320.0, 481.0)"), "{outside}");
        assert!(implausible_intrinsics(&radial_at(-0.5, 240.0), true).is_some());
        assert_eq!(implausible_intrinsics(&radial_at(-0.5, 240.0), false), None);
    }

    /// Three images 0.5 m apart, fixed, of a 5 x 5 grid of points at three
    /// depths, with keypoints projected by `truth` and the database holding
    /// `database_camera` (camera 1, refined); the points start 2.4 cm off.
    /// The cameras stand at different depths and off one line: were they side
    /// by side, a principal point moved by `d` px would be matched exactly by
    /// the points sheared by `d z / f`; on one line, by another affinity.
    fn grid_seen_through(truth: &Camera, database_camera: Camera) -> (MapState, BundleConfig) {
        use crate::io::database::DatabaseSnapshot;
        use crate::scene::TrackElement;
        use crate::sfm::associate::tests::add_test_image;
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(CameraId(1), database_camera);
        let points: Vec<Vector3<f64>> = (0..25)
            .map(|k| {
                let (i, j) = ((k % 5) as f64, (k / 5) as f64);
                Vector3::new(i - 2.0, j - 2.0, 3.0 + 0.5 * ((k % 3) as f64))
            })
            .collect();
        let poses: Vec<(ImageId, Rigid3)> = (0..3)
            .map(|i| {
                let i = i as f64;
                let centre = Vector3::new(0.5 * (i - 1.0), 0.1 * i, 0.4 * (i - 1.0).powi(2));
                (
                    ImageId(i as u32 + 1),
                    Rigid3::new(nalgebra::UnitQuaternion::identity(), -centre),
                )
            })
            .collect();
        for (id, pose) in &poses {
            let keypoints = points
                .iter()
                .map(|x| truth.project(&pose.transform_point(x)).expect("in front"))
                .collect();
            add_test_image(&mut db, *id, keypoints);
        }
        let mut state = MapState::new(&db, 1);
        for (id, pose) in &poses {
            state.register(*id, *pose);
        }
        for (k, x) in points.iter().enumerate() {
            let track = poses
                .iter()
                .map(|(id, _)| TrackElement {
                    image_id: *id,
                    point2d_idx: k as u32,
                })
                .collect();
            state.add_point(x + Vector3::new(0.01, -0.01, 0.02), track);
        }
        let images: BTreeSet<ImageId> = poses.iter().map(|(id, _)| *id).collect();
        let config = BundleConfig {
            variable_images: images.clone(),
            fixed_images: images,
            refine_cameras: BTreeSet::from([CameraId(1)]),
            pose_priors: Vec::new(),
        };
        (state, config)
    }

    /// Keypoints seen with the principal point 6 px right of and 4 px above
    /// the database's (the image centre, as COLMAP guesses it): a refined
    /// camera's principal point stays unless the state lists it in
    /// `principal_point_refined`, and then goes where the keypoints put it.
    #[test]
    fn the_principal_point_is_refined_only_when_asked() {
        use crate::sfm::associate::tests::test_camera;
        use crate::sfm::associate::NoAssociation;
        let truth = Camera {
            params: vec![500.0, 326.0, 236.0],
            ..test_camera()
        };
        for refine_principal_point in [false, true] {
            let (mut state, config) = grid_seen_through(&truth, test_camera());
            if refine_principal_point {
                state.principal_point_refined.insert(CameraId(1));
            }
            let options = BundleOptions::default();
            bundle_adjust(
                &mut state,
                &config,
                SolveKind::Global,
                &NoAssociation,
                &options,
            )
            .expect("solves");
            let params = &state.cameras[&CameraId(1)].params;
            if refine_principal_point {
                for (k, want) in [(0, 500.0), (1, 326.0), (2, 236.0)] {
                    assert!((params[k] - want).abs() < 0.01, "{params:?}");
                }
            } else {
                assert_eq!(params[1..], [320.0, 240.0], "{params:?}");
            }
        }
    }

    /// Keypoints of a 40 px focal length (below COLMAP's bound of 64 px for a
    /// 640 px wide image), a camera that says 45: every solve that refines it
    /// ends out of bounds and is solved again with it held; after the second
    /// such solve it is no longer refined at all.
    #[test]
    fn intrinsics_refined_out_of_bounds_twice_are_held_for_the_rest_of_the_run() {
        use crate::sfm::associate::tests::test_camera;
        use crate::sfm::associate::NoAssociation;
        let truth = Camera {
            params: vec![40.0, 320.0, 240.0],
            ..test_camera()
        };
        let database_camera = Camera {
            params: vec![45.0, 320.0, 240.0],
            ..truth.clone()
        };
        let (mut state, config) = grid_seen_through(&truth, database_camera);
        let options = BundleOptions::default();
        let solve = |state: &mut MapState| {
            bundle_adjust(state, &config, SolveKind::Global, &NoAssociation, &options)
                .expect("solves")
        };
        for n in 1..=MAX_IMPLAUSIBLE_REFINEMENTS {
            let record = solve(&mut state);
            assert_eq!(record.intrinsics_held, vec![1], "solve {n}");
            assert_eq!(state.implausible_refinements[&CameraId(1)], n);
            assert_eq!(state.cameras[&CameraId(1)].params[0], 45.0);
        }
        assert!(!state.intrinsics_refinable(CameraId(1)));
        // Held from now on: one solve, nothing thrown away, the count stays.
        let record = solve(&mut state);
        assert!(record.intrinsics_held.is_empty(), "{record:?}");
        assert_eq!(
            state.implausible_refinements[&CameraId(1)],
            MAX_IMPLAUSIBLE_REFINEMENTS
        );
        assert_eq!(state.cameras[&CameraId(1)].params[0], 45.0);
    }
}
