//! Integration tests: the Ceres bundle-adjustment bridge on synthetic scenes
//! with known ground truth (a room: floor and three walls, cameras along one
//! side looking across it).
use colmap_lidar::scene::{Camera, CameraId, CameraModel, Rigid3};
use colmap_lidar::solver::{
    self, reference, BaCamera, BaObservation, BaPoint, BaPose, BundleAdjustmentProblem,
    ConstantParams, LinearSolver, LossFunction, PlaneConstraint, PlaneFamily, PosePrior,
    ResidualFamily, SolverError, SolverOptions, TerminationType,
};
use std::collections::BTreeMap;

use nalgebra::{Matrix3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const WIDTH: u32 = 800;
const HEIGHT: u32 = 600;

/// The room's planes `n . X = d`: floor, back wall, left wall, right wall.
/// Floor + two side walls meet in a point; the back wall does not pass through
/// it, so the four together fix the scale.
fn room_planes() -> Vec<(Vector3<f64>, f64)> {
    vec![
        (Vector3::new(0.0, 0.0, 1.0), 0.0),
        (Vector3::new(0.0, 1.0, 0.0), 8.0),
        (Vector3::new(1.0, 0.0, 0.0), 0.0),
        (Vector3::new(1.0, 0.0, 0.0), 8.0),
    ]
}

fn test_cameras() -> Vec<Camera> {
    let make = |model, params: Vec<f64>| Camera {
        id: CameraId(1),
        model,
        width: WIDTH,
        height: HEIGHT,
        params,
    };
    vec![
        make(CameraModel::Pinhole, vec![400.0, 410.0, 400.0, 300.0]),
        make(CameraModel::SimpleRadial, vec![400.0, 400.0, 300.0, -0.05]),
        make(
            CameraModel::OpenCv,
            vec![405.0, 400.0, 398.0, 302.0, -0.03, 0.01, 0.001, -0.0005],
        ),
    ]
}

/// Ground truth: cameras, poses (`cam_from_world`), points, and for each point
/// the plane it lies on (if any).
struct Scene {
    cameras: Vec<Camera>,
    poses: Vec<Rigid3>,
    points: Vec<Vector3<f64>>,
    point_plane: Vec<Option<usize>>,
    planes: Vec<(Vector3<f64>, f64)>,
}

fn look_at(center: Vector3<f64>, target: Vector3<f64>) -> Rigid3 {
    let z = (target - center).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let world_from_cam = Matrix3::from_columns(&[x, y, z]);
    let r = world_from_cam.transpose();
    Rigid3::from_rotation_matrix(&r, -(r * center))
}

fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    rng.gen_range(lo..hi)
}

fn room_scene(num_poses: usize, points_per_plane: usize, free_points: usize, seed: u64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let planes = room_planes();
    let mut points = Vec::new();
    let mut point_plane = Vec::new();
    for (k, _) in planes.iter().enumerate() {
        for _ in 0..points_per_plane {
            let p = match k {
                0 => Vector3::new(
                    uniform(&mut rng, 1.0, 7.0),
                    uniform(&mut rng, 4.0, 7.5),
                    0.0,
                ),
                1 => Vector3::new(
                    uniform(&mut rng, 1.0, 7.0),
                    8.0,
                    uniform(&mut rng, 0.3, 2.7),
                ),
                2 => Vector3::new(
                    0.0,
                    uniform(&mut rng, 4.5, 7.5),
                    uniform(&mut rng, 0.3, 2.7),
                ),
                _ => Vector3::new(
                    8.0,
                    uniform(&mut rng, 4.5, 7.5),
                    uniform(&mut rng, 0.3, 2.7),
                ),
            };
            points.push(p);
            point_plane.push(Some(k));
        }
    }
    for _ in 0..free_points {
        points.push(Vector3::new(
            uniform(&mut rng, 2.0, 6.0),
            uniform(&mut rng, 5.0, 7.0),
            uniform(&mut rng, 0.5, 2.0),
        ));
        point_plane.push(None);
    }
    let poses = (0..num_poses)
        .map(|i| {
            let s = i as f64 / (num_poses.max(2) - 1) as f64;
            let center = Vector3::new(
                1.5 + 5.0 * s,
                1.5 + uniform(&mut rng, -0.3, 0.3),
                1.4 + uniform(&mut rng, -0.1, 0.1),
            );
            let target = Vector3::new(
                4.0 + uniform(&mut rng, -1.0, 1.0),
                6.0 + uniform(&mut rng, -0.5, 0.5),
                1.0 + uniform(&mut rng, -0.3, 0.3),
            );
            look_at(center, target)
        })
        .collect();
    Scene {
        cameras: test_cameras(),
        poses,
        points,
        point_plane,
        planes,
    }
}

fn camera_of_pose(scene: &Scene, pose: usize) -> usize {
    pose % scene.cameras.len()
}

/// Noise-free projection of a point into a pose, if in front and in the image.
fn observe(scene: &Scene, pose: usize, point: usize) -> Option<Vector2<f64>> {
    let in_cam = scene.poses[pose].transform_point(&scene.points[point]);
    if in_cam.z < 0.3 {
        return None;
    }
    let px = scene.cameras[camera_of_pose(scene, pose)].project(&in_cam)?;
    (px.x > 0.0 && px.y > 0.0 && px.x < f64::from(WIDTH) && px.y < f64::from(HEIGHT)).then_some(px)
}

/// The ground-truth problem (with `pixel_noise_px` on the observations), all
/// blocks variable, intrinsics constant, plane constraints of `plane_weight`
/// for points on planes (none if `plane_weight` is `None`).
fn problem_from_scene(
    scene: &Scene,
    pixel_noise_px: f64,
    plane_weight: Option<f64>,
    rng: &mut ChaCha8Rng,
) -> BundleAdjustmentProblem {
    let noise = Normal::new(0.0, pixel_noise_px.max(1e-300)).expect("valid sigma");
    let mut problem = BundleAdjustmentProblem {
        poses: scene.poses.iter().map(|p| BaPose::new(p, false)).collect(),
        cameras: scene
            .cameras
            .iter()
            .map(|c| BaCamera::new(c, ConstantParams::All))
            .collect(),
        points: scene
            .points
            .iter()
            .map(|p| BaPoint {
                position_in_world: [p.x, p.y, p.z],
                constant: false,
            })
            .collect(),
        ..Default::default()
    };
    for pose in 0..scene.poses.len() {
        for point in 0..scene.points.len() {
            if let Some(px) = observe(scene, pose, point) {
                let (dx, dy) = if pixel_noise_px > 0.0 {
                    (noise.sample(rng), noise.sample(rng))
                } else {
                    (0.0, 0.0)
                };
                problem.observations.push(BaObservation {
                    pose_idx: pose as u32,
                    camera_idx: camera_of_pose(scene, pose) as u32,
                    point_idx: point as u32,
                    pixel_px: [px.x + dx, px.y + dy],
                    weight: 1.0,
                });
            }
        }
    }
    if let Some(weight) = plane_weight {
        for (point, plane) in scene.point_plane.iter().enumerate() {
            if let Some(k) = plane {
                let (n, d) = scene.planes[*k];
                problem.planes.push(PlaneConstraint {
                    point_idx: point as u32,
                    normal: [n.x, n.y, n.z],
                    offset_m: d,
                    weight,
                    family: if *k == 0 {
                        PlaneFamily::Ground
                    } else {
                        PlaneFamily::Nearest
                    },
                });
            }
        }
    }
    problem
}

fn random_unit(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let n = Normal::new(0.0, 1.0).expect("valid sigma");
    Vector3::new(n.sample(rng), n.sample(rng), n.sample(rng)).normalize()
}

/// Perturbs every non-constant pose (rotation by `angle_deg`, centre by
/// `offset_m`, random directions) and point (by `offset_m`).
fn perturb(
    problem: &mut BundleAdjustmentProblem,
    angle_deg: f64,
    offset_m: f64,
    rng: &mut ChaCha8Rng,
) {
    for pose in problem.poses.iter_mut().filter(|p| !p.constant) {
        let rigid = pose.rigid();
        let rotation = UnitQuaternion::from_scaled_axis(random_unit(rng) * angle_deg.to_radians())
            * rigid.rotation;
        let center = rigid.camera_center() + random_unit(rng) * offset_m;
        *pose = BaPose::new(&Rigid3::from_rotation_and_center(rotation, &center), false);
    }
    for point in problem.points.iter_mut().filter(|p| !p.constant) {
        let d = random_unit(rng) * offset_m;
        for k in 0..3 {
            point.position_in_world[k] += d[k];
        }
    }
}

/// Applies the world similarity `X' = s R X + t` to every pose and point.
fn apply_similarity(
    problem: &mut BundleAdjustmentProblem,
    s: f64,
    r: UnitQuaternion<f64>,
    t: Vector3<f64>,
) {
    for pose in &mut problem.poses {
        let rigid = pose.rigid();
        let center = r * rigid.camera_center() * s + t;
        let rotation = rigid.rotation * r.inverse();
        *pose = BaPose::new(
            &Rigid3::from_rotation_and_center(rotation, &center),
            pose.constant,
        );
    }
    for point in &mut problem.points {
        let x = r * Vector3::from(point.position_in_world) * s + t;
        point.position_in_world = [x.x, x.y, x.z];
    }
}

/// Largest camera-centre error (m), largest rotation error (deg) and RMS point
/// error (m) against the scene's truth.
fn errors(problem: &BundleAdjustmentProblem, scene: &Scene) -> (f64, f64, f64) {
    let mut center_m: f64 = 0.0;
    let mut angle_deg: f64 = 0.0;
    for (pose, truth) in problem.poses.iter().zip(&scene.poses) {
        let rigid = pose.rigid();
        center_m = center_m.max((rigid.camera_center() - truth.camera_center()).norm());
        angle_deg = angle_deg.max(rigid.rotation.angle_to(&truth.rotation).to_degrees());
    }
    let sq: f64 = problem
        .points
        .iter()
        .zip(&scene.points)
        .map(|(p, t)| (Vector3::from(p.position_in_world) - t).norm_squared())
        .sum();
    (center_m, angle_deg, (sq / scene.points.len() as f64).sqrt())
}

/// RMS of the reprojection residual per coordinate, pixels.
fn rms_reprojection_px(problem: &BundleAdjustmentProblem) -> f64 {
    let sq: f64 = problem
        .observations
        .iter()
        .map(|o| {
            let r = reference::reprojection_residual(problem, o).expect("projectable");
            r[0] * r[0] + r[1] * r[1]
        })
        .sum();
    (sq / (2 * problem.observations.len()) as f64).sqrt()
}

fn check_every_point_seen_twice(problem: &BundleAdjustmentProblem) {
    let mut seen = vec![0; problem.points.len()];
    for o in &problem.observations {
        seen[o.point_idx as usize] += 1;
    }
    let min = seen.iter().min().copied().unwrap_or(0);
    assert!(min >= 2, "synthetic scene: a point is seen {min} times");
}

#[test]
fn synthetic_ba_converges_to_ground_truth() {
    let scene = room_scene(12, 20, 30, 1);
    for (pixel_noise_px, tol_center_m, tol_deg, tol_point_m) in
        [(0.0, 1e-6, 1e-6, 1e-6), (0.5, 0.02, 0.15, 0.04)]
    {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut problem = problem_from_scene(&scene, pixel_noise_px, None, &mut rng);
        check_every_point_seen_twice(&problem);
        // Two fixed poses fix the gauge including the scale.
        problem.poses[0].constant = true;
        problem.poses[11].constant = true;
        perturb(&mut problem, 1.0, 0.1, &mut rng);
        let before = errors(&problem, &scene);
        assert!(
            before.0 > 0.05 && before.2 > 0.05,
            "perturbation too small: {before:?}"
        );

        let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
        let after = errors(&problem, &scene);
        eprintln!(
            "BA noise {pixel_noise_px} px: {} obs, {} points, {:.3} s, {} iterations, \
             cost {:.3e} -> {:.3e}, errors before {before:?} after {after:?}",
            problem.observations.len(),
            problem.points.len(),
            summary.time_s,
            summary.num_iterations,
            summary.initial_cost,
            summary.final_cost
        );
        assert!(summary.usable, "{}", summary.message);
        assert_eq!(
            summary.termination,
            TerminationType::Convergence,
            "{}",
            summary.message
        );
        assert_eq!(summary.linear_solver, Some(LinearSolver::DenseSchur));
        assert!(after.0 < tol_center_m, "centre error {} m", after.0);
        assert!(after.1 < tol_deg, "rotation error {} deg", after.1);
        assert!(after.2 < tol_point_m, "point RMS error {} m", after.2);
        // The residual at the optimum matches the noise level.
        let rms = rms_reprojection_px(&problem);
        if pixel_noise_px > 0.0 {
            assert!(
                rms > 0.7 * pixel_noise_px && rms < 1.2 * pixel_noise_px,
                "rms {rms} px"
            );
        } else {
            assert!(rms < 1e-6, "rms {rms} px");
        }
        // Ceres' final cost is the sum of the per-family costs.
        let sum: f64 = summary.families.iter().map(|f| f.final_cost).sum();
        assert!((sum - summary.final_cost).abs() <= 1e-9 * summary.final_cost.max(1e-12) + 1e-15);
        assert_eq!(
            summary
                .family(ResidualFamily::Reprojection)
                .map(|f| f.num_residual_blocks),
            Some(problem.observations.len())
        );
    }
}

#[test]
fn solves_are_deterministic() {
    let scene = room_scene(8, 10, 10, 26);
    let mut rng = ChaCha8Rng::seed_from_u64(27);
    let mut problem = problem_from_scene(&scene, 0.5, Some(100.0), &mut rng);
    perturb(&mut problem, 0.5, 0.05, &mut rng);
    let mut first = problem.clone();
    let mut second = problem.clone();
    let summary = solver::solve(&mut first, &SolverOptions::default()).expect("solve");
    solver::solve(&mut second, &SolverOptions::default()).expect("solve");
    assert!(first == second, "two identical solves differ");
    assert!(first != problem);
    eprintln!("deterministic: {summary}");
}

#[test]
fn planes_hold_gauge_and_metric_scale() {
    let scene = room_scene(12, 20, 20, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut problem = problem_from_scene(&scene, 0.3, Some(100.0), &mut rng);
    check_every_point_seen_twice(&problem);
    // No constant pose: the planes alone must hold position, orientation and
    // scale. Start 10% too large, rotated 2 deg, shifted ~0.4 m, plus noise.
    let r = UnitQuaternion::from_scaled_axis(
        Vector3::new(0.3, -0.5, 1.0).normalize() * 2f64.to_radians(),
    );
    apply_similarity(&mut problem, 1.1, r, Vector3::new(0.3, -0.2, 0.1));
    perturb(&mut problem, 0.5, 0.05, &mut rng);
    let before = errors(&problem, &scene);
    assert!(before.0 > 0.3, "start too close: {before:?}");

    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
    let after = errors(&problem, &scene);
    eprintln!(
        "planes BA: {} obs, {} planes, {:.3} s, {} iterations, errors before {before:?} after {after:?}",
        problem.observations.len(),
        problem.planes.len(),
        summary.time_s,
        summary.num_iterations
    );
    assert!(summary.usable, "{}", summary.message);
    assert!(after.0 < 0.01, "centre error {} m", after.0);
    assert!(after.1 < 0.1, "rotation error {} deg", after.1);
    assert!(after.2 < 0.02, "point RMS error {} m", after.2);
    // Metric scale: the spread of the camera centres matches the truth.
    let spread = |c: Vec<Vector3<f64>>| (c[0] - c[c.len() - 1]).norm();
    let solved = spread(problem.poses.iter().map(|p| p.center()).collect());
    let truth = spread(scene.poses.iter().map(|p| p.camera_center()).collect());
    assert!(
        (solved / truth - 1.0).abs() < 0.002,
        "scale {}",
        solved / truth
    );
    for family in [PlaneFamily::Ground, PlaneFamily::Nearest] {
        let cost = summary
            .family(ResidualFamily::Plane(family))
            .expect("family present");
        assert_eq!(
            cost.num_residual_blocks,
            if family == PlaneFamily::Ground {
                20
            } else {
                60
            }
        );
        assert!(cost.final_cost < 0.01 * cost.initial_cost, "{cost:?}");
    }
}

/// Plane residuals are padded to two rows, so with the intrinsics held every
/// row block on a point has 2 rows and every pose block 3 dimensions: Ceres
/// must pick its compiled 2,3,3 Schur eliminator, not the generic dynamic one
/// (about a quarter slower). Freeing the intrinsics gives pose and camera
/// blocks of different sizes, hence a dynamic f-block. Each solve reports
/// where its time went, Ceres' parts within its total.
#[test]
fn schur_structure_and_time_split_are_reported() {
    let scene = room_scene(12, 20, 20, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut problem = problem_from_scene(&scene, 0.3, Some(100.0), &mut rng);
    perturb(&mut problem, 0.2, 0.02, &mut rng);
    assert!(!problem.planes.is_empty());
    let options = SolverOptions {
        linear_solver: LinearSolver::DenseSchur,
        ..Default::default()
    };
    let summary = solver::solve(&mut problem.clone(), &options).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    assert_eq!(summary.schur_structure, "2,3,3");
    let t = summary.times;
    eprintln!("{t:?}, total {:.4} s", summary.time_s);
    for (name, v) in [
        ("build", t.build_s),
        ("family cost", t.family_cost_s),
        ("preprocessor", t.preprocessor_s),
        ("residual", t.residual_s),
        ("jacobian", t.jacobian_s),
        ("linear solver", t.linear_solver_s),
    ] {
        assert!(v > 0.0 && v.is_finite(), "{name}: {v}");
    }
    let inside = t.preprocessor_s + t.residual_s + t.jacobian_s + t.linear_solver_s;
    assert!(inside <= summary.time_s, "{inside} > {}", summary.time_s);

    for camera in &mut problem.cameras {
        camera.constant = ConstantParams::None;
    }
    let summary = solver::solve(&mut problem, &options).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    assert_eq!(summary.schur_structure, "2,3,d");
}

#[test]
fn three_planes_through_one_point_leave_scale_free() {
    // Floor, back wall and left wall meet in a point; scaling about it keeps all
    // three planes: the scale error of the start survives the solve. This
    // documents why a fourth plane is needed (the test above passes with it).
    let scene = room_scene(12, 20, 0, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut problem = problem_from_scene(&scene, 0.0, Some(100.0), &mut rng);
    // Drop the right wall's constraints (its points stay, unconstrained): floor,
    // back wall and left wall all pass through the corner (0, 8, 0).
    problem
        .planes
        .retain(|p| !(p.normal == [1.0, 0.0, 0.0] && p.offset_m == 8.0));
    // Scale by 1.1 about that corner: X' = 1.1 X - 0.1 corner.
    let corner = Vector3::new(0.0, 8.0, 0.0);
    apply_similarity(&mut problem, 1.1, UnitQuaternion::identity(), -0.1 * corner);
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
    assert!(summary.usable);
    // Already optimal: every residual is zero at the scaled start.
    assert!(
        summary.initial_cost < 1e-12,
        "cost {}",
        summary.initial_cost
    );
    let solved = (problem.poses[0].center() - problem.poses[11].center()).norm();
    let truth = (scene.poses[0].camera_center() - scene.poses[11].camera_center()).norm();
    assert!(
        (solved / truth - 1.1).abs() < 1e-9,
        "scale {}",
        solved / truth
    );
}

#[test]
fn point_exactly_on_its_plane_gives_no_nan() {
    let scene = room_scene(12, 20, 0, 5);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let mut problem = problem_from_scene(&scene, 0.0, Some(1000.0), &mut rng);
    // Everything at the truth: every plane residual is exactly zero.
    let evaluation = solver::evaluate_residuals(&problem, &SolverOptions::default()).expect("eval");
    let plane_start = 2 * problem.observations.len();
    for (i, r) in evaluation.residuals[plane_start..].iter().enumerate() {
        assert_eq!(*r, 0.0, "plane residual {i}");
    }
    // A solve from exactly there (with a robust loss too) stays finite and put.
    let options = SolverOptions {
        plane_loss: LossFunction::Huber { scale: 1.0 },
        ..Default::default()
    };
    let truth = problem.clone();
    let summary = solver::solve(&mut problem, &options).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    assert!(summary.final_cost.is_finite() && summary.final_cost < 1e-12);
    for (p, t) in problem.points.iter().zip(&truth.points) {
        for k in 0..3 {
            assert!(p.position_in_world[k].is_finite());
            assert!((p.position_in_world[k] - t.position_in_world[k]).abs() < 1e-9);
        }
    }
    // Perturb one point off its plane along the normal only: the solve pulls it back.
    problem.points[0].position_in_world[2] += 0.01;
    let summary = solver::solve(&mut problem, &options).expect("solve");
    assert!(summary.usable);
    assert!(problem.points[0].position_in_world[2].abs() < 1e-6);
}

#[test]
fn cpp_residuals_match_rust_reference() {
    let scene = room_scene(12, 10, 10, 7);
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let mut problem = problem_from_scene(&scene, 0.5, Some(50.0), &mut rng);
    problem.pose_priors = (0..4)
        .map(|i| {
            let truth = &scene.poses[i];
            let q = UnitQuaternion::from_scaled_axis(random_unit(&mut rng) * 0.05) * truth.rotation;
            let c = truth.camera_center() + random_unit(&mut rng) * 0.1;
            PosePrior {
                pose_idx: i as u32,
                position_in_world: (i != 1).then_some([c.x, c.y, c.z]),
                cam_from_world_rotation: (i != 2).then_some([q.w, q.i, q.j, q.k]),
                position_weight: 10.0,
                rotation_weight: 100.0 + i as f64,
            }
        })
        .collect();
    perturb(&mut problem, 0.5, 0.05, &mut rng);
    // Constant poses and intrinsics are held inside specialised cost
    // functions: every combination must evaluate alike.
    problem.poses[5].constant = true;
    problem.poses[9].constant = true;
    problem.cameras[1].constant = ConstantParams::None;
    // Distortion on every model so the intrinsics matter too.
    problem.observations[3].weight = 2.5;
    let options = SolverOptions {
        reprojection_loss: LossFunction::Cauchy { scale: 2.0 },
        pose_prior_loss: LossFunction::Huber { scale: 1.0 },
        plane_loss: LossFunction::SoftL1 { scale: 0.5 },
        plane_family_losses: vec![(PlaneFamily::Ground, LossFunction::Huber { scale: 3.0 })],
        ..Default::default()
    };
    let cpp = solver::evaluate_residuals(&problem, &options).expect("evaluate");
    let rust = reference::residuals(&problem);
    assert_eq!(cpp.residuals.len(), rust.len());
    assert_eq!(cpp.num_failed_blocks, 0);
    let mut max_diff: f64 = 0.0;
    for (i, (a, b)) in cpp.residuals.iter().zip(&rust).enumerate() {
        let diff = (a - b).abs();
        assert!(
            diff <= 1e-9 * (1.0 + b.abs()),
            "residual {i}: C++ {a} vs Rust {b}"
        );
        max_diff = max_diff.max(diff);
    }
    assert!(
        rust.iter().any(|r| r.abs() > 1.0),
        "residuals suspiciously small"
    );
    let rust_costs = reference::family_costs(&problem, &options);
    assert_eq!(rust_costs.len(), cpp.families.len());
    for ((family, cost), c) in rust_costs.iter().zip(&cpp.families) {
        assert_eq!(*family, c.family);
        assert!(
            (cost - c.initial_cost).abs() <= 1e-9 * cost.abs(),
            "{family:?}: {cost} vs {c:?}"
        );
    }
    eprintln!(
        "C++ vs Rust residuals: {} values, max diff {max_diff:.2e}",
        rust.len()
    );
}

#[test]
fn all_camera_models_evaluate_like_the_rust_reference() {
    // Every parameter-count specialisation of the C++ functor (3, 4, 5, 8, 12).
    let params = |model: CameraModel| -> Vec<f64> {
        let mut p = match model.param_names()[0] {
            "f" => vec![400.0, 400.0, 300.0],
            _ => vec![400.0, 405.0, 400.0, 300.0],
        };
        let extra = [0.02, -0.01, 0.003, -0.002, 0.001, 0.0005, 0.0002, 0.0001];
        let n = model.num_params() - p.len();
        if model == CameraModel::Fov {
            p.push(0.9);
        } else {
            p.extend_from_slice(&extra[..n]);
        }
        p
    };
    let mut problem = BundleAdjustmentProblem::default();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let pose = look_at(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.5, 5.0, 0.5));
    problem.poses.push(BaPose::new(&pose, false));
    for _ in 0..20 {
        let p = Vector3::new(
            uniform(&mut rng, -2.0, 2.0),
            uniform(&mut rng, 3.0, 7.0),
            uniform(&mut rng, -1.5, 1.5),
        );
        problem.points.push(BaPoint {
            position_in_world: [p.x, p.y, p.z],
            constant: false,
        });
    }
    for (c, model) in CameraModel::ALL.into_iter().enumerate() {
        problem.cameras.push(BaCamera {
            model_id: model.id(),
            params: params(model),
            constant: ConstantParams::None,
        });
        for point in 0..problem.points.len() {
            problem.observations.push(BaObservation {
                pose_idx: 0,
                camera_idx: c as u32,
                point_idx: point as u32,
                pixel_px: [400.0, 300.0],
                weight: 1.0,
            });
        }
    }
    let cpp = solver::evaluate_residuals(&problem, &SolverOptions::default()).expect("evaluate");
    let rust = reference::residuals(&problem);
    for (i, (a, b)) in cpp.residuals.iter().zip(&rust).enumerate() {
        let model = CameraModel::ALL[i / 2 / problem.points.len()];
        assert!(
            (a - b).abs() <= 1e-9 * (1.0 + b.abs()),
            "{model:?} residual {i}: {a} vs {b}"
        );
    }
}

#[test]
fn bad_input_is_an_error_not_a_crash() {
    let scene = room_scene(4, 5, 5, 10);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let good = problem_from_scene(&scene, 0.0, Some(10.0), &mut rng);
    good.validate().expect("the base problem is valid");
    type Mutation = fn(&mut BundleAdjustmentProblem);
    let cases: Vec<(&str, Mutation)> = vec![
        ("observation point out of range", |p| {
            p.observations[0].point_idx = 10_000
        }),
        ("observation pose out of range", |p| {
            p.observations[1].pose_idx = 4
        }),
        ("observation camera out of range", |p| {
            p.observations[2].camera_idx = 3
        }),
        ("plane point out of range", |p| {
            p.planes[0].point_idx = u32::MAX
        }),
        ("prior pose out of range", |p| {
            p.pose_priors.push(PosePrior {
                pose_idx: 9,
                position_in_world: Some([0.0; 3]),
                cam_from_world_rotation: None,
                position_weight: 1.0,
                rotation_weight: 0.0,
            })
        }),
        ("NaN point", |p| p.points[3].position_in_world[1] = f64::NAN),
        ("infinite pose", |p| {
            p.poses[1].cam_from_world[5] = f64::INFINITY
        }),
        ("NaN pixel", |p| p.observations[0].pixel_px[0] = f64::NAN),
        ("NaN intrinsic", |p| p.cameras[0].params[0] = f64::NAN),
        ("NaN plane offset", |p| p.planes[0].offset_m = f64::NAN),
        ("non-unit quaternion", |p| {
            p.poses[0].cam_from_world[0] *= 2.0
        }),
        ("zero quaternion", |p| {
            p.poses[0].cam_from_world[..4].fill(0.0)
        }),
        ("non-unit normal", |p| p.planes[0].normal = [0.0, 0.0, 2.0]),
        ("negative weight", |p| p.planes[0].weight = -1.0),
        ("NaN observation weight", |p| {
            p.observations[0].weight = f64::NAN
        }),
        ("unknown camera model", |p| p.cameras[0].model_id = 42),
        ("wrong parameter count", |p| p.cameras[1].params.push(0.0)),
        ("wrong mask length", |p| {
            p.cameras[2].constant = ConstantParams::Mask(vec![true])
        }),
        ("family out of range", |p| {
            p.planes[0].family = PlaneFamily::Other(200)
        }),
    ];
    for (name, mutate) in cases {
        let mut problem = good.clone();
        mutate(&mut problem);
        let before = problem.clone();
        match solver::solve(&mut problem, &SolverOptions::default()) {
            Err(SolverError::InvalidProblem(msg)) => eprintln!("{name}: {msg}"),
            other => panic!("{name}: expected InvalidProblem, got {other:?}"),
        }
        // Compared as Debug text, since NaN != NaN.
        assert_eq!(
            format!("{problem:?}"),
            format!("{before:?}"),
            "{name}: a rejected problem must stay unchanged"
        );
        assert!(matches!(
            solver::evaluate_residuals(&problem, &SolverOptions::default()),
            Err(SolverError::InvalidProblem(_))
        ));
    }
    let bad_options = [
        SolverOptions {
            reprojection_loss: LossFunction::Cauchy { scale: 0.0 },
            ..Default::default()
        },
        SolverOptions {
            plane_loss: LossFunction::Huber { scale: f64::NAN },
            ..Default::default()
        },
        SolverOptions {
            function_tolerance: -1.0,
            ..Default::default()
        },
        SolverOptions {
            num_threads: 0,
            ..Default::default()
        },
    ];
    for options in bad_options {
        let mut problem = good.clone();
        assert!(matches!(
            solver::solve(&mut problem, &options),
            Err(SolverError::InvalidOptions(_))
        ));
    }
}

#[test]
fn point_behind_a_camera_is_an_unusable_solve_not_a_crash() {
    let scene = room_scene(4, 5, 5, 12);
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut problem = problem_from_scene(&scene, 0.0, None, &mut rng);
    // Move an observed point behind its camera (a mirror through the centre).
    let obs = problem.observations[0].clone();
    let centre = problem.poses[obs.pose_idx as usize].center();
    let p = Vector3::from(problem.points[obs.point_idx as usize].position_in_world);
    let behind = centre * 2.0 - p;
    problem.points[obs.point_idx as usize].position_in_world = [behind.x, behind.y, behind.z];
    let evaluation = solver::evaluate_residuals(&problem, &SolverOptions::default()).expect("eval");
    assert!(evaluation.num_failed_blocks >= 1);
    assert!(evaluation.observation(0)[0].is_nan());
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("no error");
    assert!(!summary.usable);
    assert_eq!(summary.termination, TerminationType::Failure);
    eprintln!("behind camera: {}", summary.message);
}

#[test]
fn constant_blocks_do_not_move() {
    let scene = room_scene(9, 15, 15, 14);
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let mut problem = problem_from_scene(&scene, 0.0, None, &mut rng);
    problem.poses[0].constant = true;
    problem.poses[3].constant = true;
    problem.points[5].constant = true;
    problem.points[7].constant = true;
    // OPENCV: focal lengths refined, principal point and distortion fixed.
    problem.cameras[2].constant =
        ConstantParams::Mask(vec![false, false, true, true, true, true, true, true]);
    problem.cameras[2].params[0] *= 1.02;
    problem.cameras[2].params[1] *= 0.98;
    // PINHOLE fixed entirely; SIMPLE_RADIAL fully refined from the truth.
    problem.cameras[0].constant = ConstantParams::All;
    problem.cameras[1].constant = ConstantParams::None;
    perturb(&mut problem, 0.5, 0.05, &mut rng);
    let before = problem.clone();
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    // Bit-identical: Ceres never touches a constant block.
    assert_eq!(problem.poses[0], before.poses[0]);
    assert_eq!(problem.poses[3], before.poses[3]);
    assert_eq!(problem.points[5], before.points[5]);
    assert_eq!(problem.points[7], before.points[7]);
    assert_eq!(problem.cameras[0], before.cameras[0]);
    assert_eq!(
        problem.cameras[2].params[2..],
        before.cameras[2].params[2..]
    );
    // Variable ones moved back to the truth.
    assert_ne!(problem.poses[1], before.poses[1]);
    let truth = &scene.cameras[2].params;
    for (k, (solved, truth)) in problem.cameras[2]
        .params
        .iter()
        .zip(truth)
        .take(2)
        .enumerate()
    {
        assert!((solved / truth - 1.0).abs() < 1e-6, "focal {k}");
    }
    let (center_m, angle_deg, point_m) = errors(&problem, &scene);
    assert!(
        center_m < 1e-5 && angle_deg < 1e-4 && point_m < 1e-5,
        "{center_m} {angle_deg} {point_m}"
    );
}

#[test]
fn robust_loss_limits_gross_outliers() {
    let scene = room_scene(12, 20, 30, 16);
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut truth_problem = problem_from_scene(&scene, 0.3, None, &mut rng);
    truth_problem.poses[0].constant = true;
    truth_problem.poses[11].constant = true;
    // 3% of the observations off by 40 px in a random direction.
    let n = truth_problem.observations.len();
    for i in (0..n).step_by(33) {
        let angle = uniform(&mut rng, 0.0, std::f64::consts::TAU);
        let o = &mut truth_problem.observations[i];
        o.pixel_px[0] += 40.0 * angle.cos();
        o.pixel_px[1] += 40.0 * angle.sin();
    }
    perturb(&mut truth_problem, 0.5, 0.05, &mut rng);
    let mut results = Vec::new();
    for loss in [
        LossFunction::Trivial,
        LossFunction::Huber { scale: 1.0 },
        LossFunction::SoftL1 { scale: 1.0 },
        LossFunction::Cauchy { scale: 1.0 },
    ] {
        let mut problem = truth_problem.clone();
        let options = SolverOptions {
            reprojection_loss: loss,
            ..Default::default()
        };
        let summary = solver::solve(&mut problem, &options).expect("solve");
        assert!(summary.usable);
        let e = errors(&problem, &scene);
        eprintln!("outliers, {loss:?}: {:.3} s, errors {e:?}", summary.time_s);
        results.push(e);
    }
    let trivial = results[0];
    for robust in &results[1..] {
        assert!(
            robust.2 < 0.5 * trivial.2,
            "point error {} vs {}",
            robust.2,
            trivial.2
        );
        assert!(
            robust.0 < 0.5 * trivial.0,
            "centre error {} vs {}",
            robust.0,
            trivial.0
        );
    }
    let cauchy = results[3];
    assert!(cauchy.0 < 0.02 && cauchy.2 < 0.03, "{cauchy:?}");
}

#[test]
fn pose_priors_fix_the_gauge() {
    let scene = room_scene(12, 15, 15, 18);
    let mut rng = ChaCha8Rng::seed_from_u64(19);
    let mut problem = problem_from_scene(&scene, 0.3, None, &mut rng);
    let noise = Normal::new(0.0, 0.01).expect("valid sigma");
    problem.pose_priors = scene
        .poses
        .iter()
        .enumerate()
        .map(|(i, pose)| {
            let c = pose.camera_center()
                + Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                );
            PosePrior {
                pose_idx: i as u32,
                position_in_world: Some([c.x, c.y, c.z]),
                cam_from_world_rotation: Some(pose.quaternion_wxyz()),
                position_weight: 100.0,
                rotation_weight: 1000.0,
            }
        })
        .collect();
    let r = UnitQuaternion::from_scaled_axis(
        Vector3::new(1.0, 0.2, -0.4).normalize() * 3f64.to_radians(),
    );
    apply_similarity(&mut problem, 0.9, r, Vector3::new(-0.3, 0.4, 0.2));
    let before = errors(&problem, &scene);
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
    let after = errors(&problem, &scene);
    eprintln!(
        "priors BA: {:.3} s, errors before {before:?} after {after:?}",
        summary.time_s
    );
    assert!(summary.usable);
    assert!(before.0 > 0.3);
    assert!(
        after.0 < 0.02 && after.1 < 0.1 && after.2 < 0.05,
        "{after:?}"
    );
    assert!(summary
        .family(ResidualFamily::PosePrior)
        .is_some_and(|f| f.num_residual_blocks == 12));
}

#[test]
fn every_linear_solver_reaches_the_same_optimum() {
    let scene = room_scene(8, 10, 10, 20);
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut base = problem_from_scene(&scene, 0.3, Some(100.0), &mut rng);
    perturb(&mut base, 0.5, 0.05, &mut rng);
    let mut reference_solution: Option<BundleAdjustmentProblem> = None;
    for linear_solver in [
        LinearSolver::DenseSchur,
        LinearSolver::SparseSchur,
        LinearSolver::IterativeSchur,
        LinearSolver::DenseQr,
        LinearSolver::DenseNormalCholesky,
        LinearSolver::SparseNormalCholesky,
    ] {
        if linear_solver.needs_sparse_library() && !solver::sparse_linear_algebra_available() {
            eprintln!("skipping {linear_solver:?}: no sparse library");
            continue;
        }
        let mut problem = base.clone();
        let options = SolverOptions {
            linear_solver,
            function_tolerance: 1e-12,
            parameter_tolerance: 1e-12,
            ..Default::default()
        };
        let summary = solver::solve(&mut problem, &options).expect("solve");
        eprintln!(
            "{linear_solver:?}: {:.3} s, {} iterations",
            summary.time_s, summary.num_iterations
        );
        assert!(summary.usable, "{linear_solver:?}: {}", summary.message);
        assert_eq!(summary.linear_solver, Some(linear_solver));
        match &reference_solution {
            None => reference_solution = Some(problem),
            Some(r) => {
                for (a, b) in problem.points.iter().zip(&r.points) {
                    for k in 0..3 {
                        assert!(
                            (a.position_in_world[k] - b.position_in_world[k]).abs() < 1e-5,
                            "{linear_solver:?}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn unused_blocks_and_empty_problems_are_fine() {
    let scene = room_scene(4, 5, 5, 22);
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let mut problem = problem_from_scene(&scene, 0.0, None, &mut rng);
    // A variable point seen by a single image (its depth is unobservable).
    let single = Vector3::new(4.0, 6.5, 1.2);
    let px = scene.cameras[0]
        .project(&scene.poses[0].transform_point(&single))
        .expect("visible");
    let single_idx = problem.points.len();
    problem.points.push(BaPoint {
        position_in_world: [single.x, single.y, single.z],
        constant: false,
    });
    problem.observations.push(BaObservation {
        pose_idx: 0,
        camera_idx: 0,
        point_idx: single_idx as u32,
        pixel_px: [px.x, px.y],
        weight: 1.0,
    });
    // A pose, a camera and a point that no residual mentions.
    let lonely_pose = BaPose::new(&Rigid3::identity(), false);
    problem.poses.push(lonely_pose.clone());
    problem.cameras.push(BaCamera::new(
        &scene.cameras[0],
        ConstantParams::Mask(vec![true, false, true, false]),
    ));
    problem.points.push(BaPoint {
        position_in_world: [1.0, 2.0, 3.0],
        constant: true,
    });
    perturb(&mut problem, 0.2, 0.02, &mut rng);
    problem.poses[4] = lonely_pose.clone();
    problem
        .points
        .last_mut()
        .expect("just pushed")
        .position_in_world = [1.0, 2.0, 3.0];
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    assert!(problem.points[single_idx]
        .position_in_world
        .iter()
        .all(|v| v.is_finite()));
    assert!(problem.poses[4] == lonely_pose, "an unused pose moved");
    assert_eq!(
        problem.points.last().map(|p| p.position_in_world),
        Some([1.0, 2.0, 3.0])
    );

    let mut empty = BundleAdjustmentProblem::default();
    let summary = solver::solve(&mut empty, &SolverOptions::default()).expect("empty");
    assert!(summary.usable && summary.final_cost == 0.0 && summary.families.is_empty());

    // Everything constant: Ceres has nothing to vary.
    let mut frozen = problem_from_scene(&scene, 0.0, None, &mut rng);
    frozen.poses.iter_mut().for_each(|p| p.constant = true);
    frozen.points.iter_mut().for_each(|p| p.constant = true);
    let before = frozen.clone();
    let summary = solver::solve(&mut frozen, &SolverOptions::default()).expect("frozen");
    assert!(summary.usable, "{}", summary.message);
    assert!(frozen == before, "a fully constant problem changed");
}

#[test]
fn auto_linear_solver_follows_problem_size() {
    let options = SolverOptions::default();
    assert_eq!(
        options.resolve_linear_solver(10, true),
        LinearSolver::DenseSchur
    );
    assert_eq!(
        options.resolve_linear_solver(149, true),
        LinearSolver::DenseSchur
    );
    assert_eq!(
        options.resolve_linear_solver(150, true),
        LinearSolver::SparseSchur
    );
    assert_eq!(
        options.resolve_linear_solver(500, false),
        LinearSolver::IterativeSchur
    );
    assert_eq!(
        options.resolve_linear_solver(5000, true),
        LinearSolver::IterativeSchur
    );
    // Debian's Ceres 2.1 is built with SuiteSparse.
    assert!(solver::sparse_linear_algebra_available());
}

/// Timing of a medium problem: 160 poses along 5 m, each seeing the points
/// within 0.5 m of its own x (about 30 views a point). Auto picks sparse Schur
/// at >= 150 variable poses. Opt-in: `cargo test -- --ignored`.
#[test]
#[ignore]
fn medium_problem_timing() {
    let scene = room_scene(160, 250, 500, 24);
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    let mut problem = problem_from_scene(&scene, 0.5, Some(100.0), &mut rng);
    problem.observations.retain(|o| {
        let pose_x = scene.poses[o.pose_idx as usize].camera_center().x;
        (scene.points[o.point_idx as usize].x - pose_x).abs() < 0.5
    });
    // The side walls are out of view now: floor and back wall alone leave the
    // gauge free along x, so fix the end poses.
    problem.poses[0].constant = true;
    problem.poses[159].constant = true;
    perturb(&mut problem, 0.3, 0.03, &mut rng);
    for linear_solver in [LinearSolver::Auto, LinearSolver::DenseSchur] {
        let mut p = problem.clone();
        let options = SolverOptions {
            linear_solver,
            ..Default::default()
        };
        let summary = solver::solve(&mut p, &options).expect("solve");
        let e = errors(&p, &scene);
        eprintln!(
            "medium BA: {} poses, {} points, {} obs, {} planes: {:?}, {:.2} s, {} iterations, errors {e:?}",
            p.poses.len(),
            p.points.len(),
            p.observations.len(),
            p.planes.len(),
            summary.linear_solver,
            summary.time_s,
            summary.num_iterations
        );
        assert!(summary.usable, "{}", summary.message);
        assert!(e.0 < 0.02, "{e:?}");
    }
}

/// Residuals of `problem` with pose `pose`'s world-frame rotation turned by
/// `omega` and its centre moved by `dc`, point `point` moved by `dx`, and
/// intrinsic `k` of camera `c` moved by `dv`.
fn perturbed_residuals(
    problem: &BundleAdjustmentProblem,
    pose: Option<(usize, Vector3<f64>, Vector3<f64>)>,
    point: Option<(usize, Vector3<f64>)>,
    intrinsic: Option<(usize, usize, f64)>,
) -> Vec<f64> {
    let mut p = problem.clone();
    if let Some((c, k, dv)) = intrinsic {
        p.cameras[c].params[k] += dv;
    }
    if let Some((i, omega, dc)) = pose {
        let rigid = p.poses[i].rigid();
        // world_from_cam turns by exp(omega) on the left, so cam_from_world by
        // exp(-omega) on the right.
        let rotation = rigid.rotation * UnitQuaternion::from_scaled_axis(-omega);
        let centre = rigid.camera_center() + dc;
        p.poses[i] = BaPose::new(&Rigid3::from_rotation_and_center(rotation, &centre), false);
    }
    if let Some((i, dx)) = point {
        for k in 0..3 {
            p.points[i].position_in_world[k] += dx[k];
        }
    }
    reference::residuals(&p)
}

/// The covariance through the bridge (Ceres' Jacobian, Schur complement,
/// tangent-to-world conversion) against `(J^T J)^-1` from central differences
/// of the Rust reference residuals in world-frame rotation and centre
/// coordinates, with a pose prior, planes, a constant pose, a free focal
/// length and principal point x (marginalised like the points; their 2x2
/// block checked too) and a point seen once (no information: must not
/// change anything).
#[test]
fn pose_covariance_matches_finite_differences() {
    let scene = room_scene(6, 10, 6, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut problem = problem_from_scene(&scene, 0.3, Some(200.0), &mut rng);
    problem.poses[5].constant = true;
    // Camera 0 (pinhole): fx and cx refined, fy and cy held.
    problem.cameras[0].constant = ConstantParams::Mask(vec![false, true, false, true]);
    let c0 = scene.poses[0].camera_center();
    problem.pose_priors.push(PosePrior {
        pose_idx: 0,
        position_in_world: Some([c0.x + 0.01, c0.y, c0.z]),
        cam_from_world_rotation: Some(scene.poses[0].quaternion_wxyz()),
        position_weight: 100.0,
        rotation_weight: 50.0,
    });
    let options = SolverOptions::default();
    let summary = solver::solve(&mut problem, &options).expect("solve");
    assert!(summary.usable, "{}", summary.message);
    let cov = solver::pose_covariances(&problem, &options).expect("covariance");
    assert_eq!(cov.num_degenerate_points, 0);
    assert!(cov.poses[5].is_none(), "constant pose");

    // Numerical Jacobian over the variable poses (6 each) and all points.
    let variable: Vec<usize> = (0..problem.poses.len())
        .filter(|&i| !problem.poses[i].constant)
        .collect();
    let n = 6 * variable.len() + 3 * problem.points.len() + 2;
    let r0 = reference::residuals(&problem);
    let m = r0.len();
    let h = 1e-6;
    let mut jac = nalgebra::DMatrix::<f64>::zeros(m, n);
    let mut col = 0;
    let mut put = |jac: &mut nalgebra::DMatrix<f64>, plus: Vec<f64>, minus: Vec<f64>| {
        for r in 0..m {
            jac[(r, col)] = (plus[r] - minus[r]) / (2.0 * h);
        }
        col += 1;
    };
    for &i in &variable {
        for k in 0..6 {
            let mut d = [0.0; 6];
            d[k] = h;
            let omega = Vector3::new(d[0], d[1], d[2]);
            let dc = Vector3::new(d[3], d[4], d[5]);
            let plus = perturbed_residuals(&problem, Some((i, omega, dc)), None, None);
            let minus = perturbed_residuals(&problem, Some((i, -omega, -dc)), None, None);
            put(&mut jac, plus, minus);
        }
    }
    for p in 0..problem.points.len() {
        for k in 0..3 {
            let mut dx = Vector3::zeros();
            dx[k] = h;
            let plus = perturbed_residuals(&problem, None, Some((p, dx)), None);
            let minus = perturbed_residuals(&problem, None, Some((p, -dx)), None);
            put(&mut jac, plus, minus);
        }
    }
    for k in [0, 2] {
        let plus = perturbed_residuals(&problem, None, None, Some((0, k, h)));
        let minus = perturbed_residuals(&problem, None, None, Some((0, k, -h)));
        put(&mut jac, plus, minus);
    }
    let variance = r0.iter().map(|r| r * r).sum::<f64>() / (m - n) as f64;
    assert!(
        (cov.residual_variance - variance).abs() < 1e-9 * variance,
        "residual variance {} vs {variance}",
        cov.residual_variance
    );
    assert_eq!(cov.redundancy, m - n);
    let full = (jac.transpose() * &jac)
        .cholesky()
        .expect("full rank")
        .inverse()
        * variance;
    for (k, &i) in variable.iter().enumerate() {
        let expected = full.view((6 * k, 6 * k), (6, 6)).into_owned();
        let got = cov.poses[i].expect("variable pose");
        let diff = (got - &expected).norm() / expected.norm();
        assert!(
            diff < 1e-4,
            "pose {i}: relative difference {diff:.2e}\n{got}\n{expected}"
        );
    }
    let sigma = cov.centre_sigma_m(1).expect("pose 1");
    assert!(sigma.min() > 0.0 && sigma.max() < 0.05, "sigma {sigma}");
    // The free fx and cx: the last two columns, in the parameters' order;
    // the other cameras are constant.
    let intrinsics = cov.cameras[0].as_ref().expect("camera 0 varies");
    assert_eq!(intrinsics.shape(), (2, 2));
    let expected = full.view((n - 2, n - 2), (2, 2)).into_owned();
    let diff = (intrinsics - &expected).norm() / expected.norm();
    assert!(diff < 1e-4, "{intrinsics} vs {expected}");
    // Their variances differ (measured 0.035 and 0.053 px^2), so the
    // comparison above tells the parameters' order.
    assert!(
        (expected[(1, 1)] / expected[(0, 0)] - 1.0).abs() > 0.2,
        "{expected}"
    );
    assert!(cov.cameras[1..].iter().all(Option::is_none));
    assert!(cov.clustered_cameras.is_empty());

    // A point seen once, without a plane, adds no information.
    let mut with_single = problem.clone();
    with_single
        .points
        .push(BaPoint::new(&Vector3::new(4.0, 6.0, 1.0), false));
    let pixel = observe(&scene, 2, 0).expect("visible");
    with_single.observations.push(BaObservation::new(
        2,
        camera_of_pose(&scene, 2) as u32,
        (with_single.points.len() - 1) as u32,
        [pixel.x + 3.0, pixel.y - 2.0],
    ));
    let single = solver::pose_covariances(&with_single, &options).expect("covariance");
    assert_eq!(single.num_degenerate_points, 1);
    // 2 more rows, 2 more directions fitted (the third is not fixed).
    assert_eq!(single.redundancy, cov.redundancy);
    for &i in &variable {
        // Same information; the variance estimate differs through the new
        // residual (the point was not solved).
        let scale = cov.residual_variance / single.residual_variance;
        let a = cov.poses[i].expect("pose");
        let b = single.poses[i].expect("pose") * scale;
        assert!((a - b).norm() < 1e-8 * a.norm(), "pose {i}");
    }
}

/// Reprojections alone leave a similarity free: no covariance, an error
/// that says so; one constant pose still leaves the scale free.
#[test]
fn pose_covariance_of_a_free_gauge_is_an_error() {
    let scene = room_scene(6, 10, 6, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut problem = problem_from_scene(&scene, 0.3, None, &mut rng);
    let options = SolverOptions::default();
    let err = solver::pose_covariances(&problem, &options).unwrap_err();
    assert!(matches!(err, solver::CovarianceError::Singular), "{err}");
    problem.poses[0].constant = true;
    let err = solver::pose_covariances(&problem, &options).unwrap_err();
    assert!(matches!(err, solver::CovarianceError::Singular), "{err}");
    // Two constant poses fix it.
    problem.poses[5].constant = true;
    let cov = solver::pose_covariances(&problem, &options).expect("fixed gauge");
    assert!(cov.poses[0].is_none() && cov.poses[2].is_some());
}

/// Solver options for the Monte Carlo checks of the covariances: solved to
/// the optimum (a solve stopped early stays near its start, the truth here,
/// and would look more precise than it is).
fn to_the_optimum() -> SolverOptions {
    SolverOptions {
        function_tolerance: 1e-14,
        gradient_tolerance: 1e-16,
        parameter_tolerance: 1e-14,
        ..Default::default()
    }
}

/// The predicted centre and rotation covariances against the scatter of
/// solutions over many noise draws (the statistical meaning of the numbers
/// report.json gives the user).
#[test]
fn pose_covariance_predicts_the_scatter_of_solutions() {
    let scene = room_scene(6, 12, 0, 5);
    let options = to_the_optimum();
    let trials = 300;
    let mut chi2_centre = 0.0;
    let mut chi2_rotation = 0.0;
    let mut count = 0.0;
    let mut variance_sum = 0.0;
    for trial in 0..trials {
        let mut rng = ChaCha8Rng::seed_from_u64(100 + trial);
        let mut problem = problem_from_scene(&scene, 0.5, Some(100.0), &mut rng);
        // Map noise as the weights say: 0.5 px / 100 px per metre = 5 mm.
        let map_noise = Normal::new(0.0, 0.005).expect("valid sigma");
        for plane in &mut problem.planes {
            plane.offset_m += map_noise.sample(&mut rng);
        }
        let summary = solver::solve(&mut problem, &options).expect("solve");
        assert!(summary.usable, "{}", summary.message);
        let cov = solver::pose_covariances(&problem, &options).expect("covariance");
        variance_sum += cov.residual_variance;
        for (i, truth) in scene.poses.iter().enumerate() {
            let rigid = problem.poses[i].rigid();
            let dc = rigid.camera_center() - truth.camera_center();
            // World-frame rotation error of world_from_cam.
            let omega = (rigid.rotation.inverse() * truth.rotation).scaled_axis();
            let sc = cov.centre_covariance(i).expect("variable");
            let sr = cov.rotation_covariance(i).expect("variable");
            chi2_centre += dc.dot(&(sc.try_inverse().expect("invertible") * dc));
            chi2_rotation += omega.dot(&(sr.try_inverse().expect("invertible") * omega));
            count += 1.0;
        }
    }
    // Each is a 3-degree-of-freedom chi-square: mean 3.
    let (mc, mr) = (chi2_centre / count, chi2_rotation / count);
    eprintln!(
        "covariance check: mean chi2 centre {mc:.2}, rotation {mr:.2} (expected 3), residual variance {:.4} (0.25)",
        variance_sum / trials as f64
    );
    assert!((2.5..3.5).contains(&mc), "centre chi2 mean {mc}");
    assert!((2.5..3.5).contains(&mr), "rotation chi2 mean {mr}");
    let v = variance_sum / trials as f64;
    assert!((0.2..0.3).contains(&v), "residual variance {v}");
}

/// The cluster-robust covariance against the scatter of solutions when the
/// map's errors are shared. Each plane term's offset errs by a part common
/// to the 1 m cube its point lies in (4 mm) and a part of its own (3 mm):
/// 5 mm in all, as the weights say. The formal covariance counts every term
/// as independent and is too small (its chi-square mean well above 3); the
/// clustered one, given the cubes, predicts the scatter (a little low: the
/// walls that fix each direction hold only 12-24 cubes, and the fit absorbs
/// part of each cube's error; measured 4.1 against the formal 14.3). With
/// independent errors and every point its own cluster, both predict it
/// (3.3 and 3.25).
#[test]
fn clustered_covariance_predicts_the_scatter_of_shared_map_errors() {
    const CUBE_M: f64 = 1.0;
    let scene = room_scene(6, 400, 0, 5);
    let options = to_the_optimum();
    let mut ids: BTreeMap<[i64; 3], u32> = BTreeMap::new();
    let cubes: Vec<u32> = scene
        .points
        .iter()
        .map(|p| {
            let key = [p.x, p.y, p.z].map(|v| (v / CUBE_M).floor() as i64);
            let next = ids.len() as u32;
            *ids.entry(key).or_insert(next)
        })
        .collect();
    let singletons: Vec<u32> = (0..scene.points.len() as u32).collect();
    let trials = 120;
    let mut means = Vec::new();
    for shared in [false, true] {
        let (mut formal, mut clustered, mut count) = (0.0, 0.0, 0.0);
        for trial in 0..trials {
            let mut rng = ChaCha8Rng::seed_from_u64(500 + trial);
            let mut problem = problem_from_scene(&scene, 0.5, Some(100.0), &mut rng);
            let (common, own): (f64, f64) = if shared { (0.004, 0.003) } else { (0.0, 0.005) };
            let common_noise = Normal::new(0.0, common.max(1e-300)).expect("valid sigma");
            let own_noise = Normal::new(0.0, own).expect("valid sigma");
            let cube_offsets: Vec<f64> = (0..ids.len())
                .map(|_| {
                    if shared {
                        common_noise.sample(&mut rng)
                    } else {
                        0.0
                    }
                })
                .collect();
            for plane in &mut problem.planes {
                plane.offset_m += cube_offsets[cubes[plane.point_idx as usize] as usize]
                    + own_noise.sample(&mut rng);
            }
            let summary = solver::solve(&mut problem, &options).expect("solve");
            assert!(summary.usable, "{}", summary.message);
            let clusters = if shared { &cubes } else { &singletons };
            let cov = solver::clustered_pose_covariances(&problem, &options, clusters)
                .expect("covariance");
            for (i, truth) in scene.poses.iter().enumerate() {
                let dc = problem.poses[i].rigid().camera_center() - truth.camera_center();
                let chi2 = |c: Matrix3<f64>| dc.dot(&(c.try_inverse().expect("invertible") * dc));
                formal += chi2(cov.centre_covariance(i).expect("variable"));
                clustered += chi2(cov.clustered_centre_covariance(i).expect("variable"));
                count += 1.0;
            }
        }
        let (f, c) = (formal / count, clustered / count);
        eprintln!(
            "map errors {}: mean centre chi2 formal {f:.2}, clustered {c:.2} (expected 3)",
            if shared {
                "shared by 1 m cubes"
            } else {
                "independent"
            }
        );
        means.push((f, c));
    }
    let [(f_own, c_own), (f_shared, c_shared)] = [means[0], means[1]];
    assert!((2.5..3.5).contains(&f_own), "independent, formal: {f_own}");
    assert!(
        (2.3..3.9).contains(&c_own),
        "independent, clustered: {c_own}"
    );
    assert!(f_shared > 8.0, "shared, formal: {f_shared}");
    assert!(
        (2.0..5.0).contains(&c_shared),
        "shared, clustered: {c_shared}"
    );
}

/// A trial step that would put a point behind its camera cannot be evaluated
/// (the cost functions return false): Ceres counts it as a step of infinite
/// cost, rejects it and shrinks the trust region, more at each rejection in a
/// row. A point 5 cm in front of a held camera, observed 40x as far off-axis
/// as it is (a wildly wrong depth), has trial steps that cross the camera
/// plane until the region has shrunk six times in a row (see it with
/// `SolverOptions::logging`); the solve must still converge to the
/// observation with the point in front, not end in FAILURE (which would
/// discard every accepted step) nor cross to the mirrored solution behind.
/// These are not Ceres' "invalid steps" (a failed linear solve or a model
/// decrease <= 0), which `max_num_consecutive_invalid_steps` counts.
#[test]
fn steps_that_put_a_point_behind_its_camera_are_rejected() {
    let camera = test_cameras()[0].clone();
    let (f, cx, cy) = (camera.params[0], camera.params[2], camera.params[3]);
    let mut problem = BundleAdjustmentProblem {
        poses: vec![BaPose::new(&Rigid3::identity(), true)],
        cameras: vec![BaCamera::new(&camera, ConstantParams::All)],
        points: vec![BaPoint::new(&Vector3::new(0.05, 0.0, 0.05), false)],
        observations: vec![BaObservation::new(0, 0, 0, [cx + f * 40.0, cy])],
        ..Default::default()
    };
    let summary = solver::solve(&mut problem, &SolverOptions::default()).expect("no error");
    eprintln!("{} iterations: {}", summary.num_iterations, summary.message);
    assert!(
        summary.usable,
        "{:?}: {}",
        summary.termination, summary.message
    );
    assert_ne!(summary.termination, TerminationType::Failure);
    let [x, y, z] = problem.points[0].position_in_world;
    assert!(z > 0.0, "point behind the camera: {x} {y} {z}");
    assert!((x / z - 40.0).abs() < 1e-6 && y.abs() < 1e-9, "{x} {y} {z}");
    assert!(summary.final_cost < 1e-9 * summary.initial_cost);
}
