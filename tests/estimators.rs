//! Integration tests: estimators (PnP, triangulation, Sim3, ray-plane) on
//! synthetic scenes with known ground truth, with noise and outliers, through
//! undistorted and distorted camera models.
use std::time::Instant;

use colmap_lidar::estimators::absolute_pose::reprojection_error_px;
use colmap_lidar::estimators::ray_plane::intersect_pixel_ray_plane;
use colmap_lidar::estimators::{
    estimate_absolute_pose, estimate_sim3_ransac, p3p, refine_absolute_pose, triangulate_point,
    triangulate_track_ransac, umeyama, AbsolutePoseOptions, AbsolutePoseOutcome,
    Correspondence2D3D, PointObservation, PoseRefinementOptions, RansacOptions, RayPlaneMiss,
    RayPlaneOptions, RegisteredPose, Sim3, TriangulationFailure, TriangulationOptions,
};
use colmap_lidar::scene::{Camera, CameraId, CameraModel, Rigid3};
use nalgebra::{Matrix3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

fn pinhole() -> Camera {
    Camera {
        id: CameraId(1),
        model: CameraModel::Pinhole,
        width: 1920,
        height: 1080,
        params: vec![1400.0, 1390.0, 960.0, 540.0],
    }
}

/// ~190 px of barrel distortion in the corners.
fn opencv() -> Camera {
    Camera {
        id: CameraId(2),
        model: CameraModel::OpenCv,
        width: 1920,
        height: 1080,
        params: vec![1400.0, 1390.0, 962.0, 538.0, -0.25, 0.08, 0.001, -0.0015],
    }
}

fn random_pose(rng: &mut ChaCha8Rng) -> Rigid3 {
    Rigid3::new(
        UnitQuaternion::from_euler_angles(
            rng.gen_range(-3.1..3.1),
            rng.gen_range(-1.5..1.5),
            rng.gen_range(-3.1..3.1),
        ),
        Vector3::new(
            rng.gen_range(-100.0..100.0),
            rng.gen_range(-100.0..100.0),
            rng.gen_range(-10.0..10.0),
        ),
    )
}

/// Rotation error (deg) and camera-centre error (m).
fn pose_error(estimate: &Rigid3, truth: &Rigid3) -> (f64, f64) {
    (
        estimate.rotation.angle_to(&truth.rotation).to_degrees(),
        (estimate.camera_center() - truth.camera_center()).norm(),
    )
}

/// `n` correspondences of points 5-15 m in front of the camera (10 m on
/// average); a fraction `outlier_ratio` gets a random pixel instead of its own;
/// Gaussian pixel noise `noise_px` on the others. Returns the data and which
/// ones are true inliers.
fn pnp_scene(
    camera: &Camera,
    truth: &Rigid3,
    n: usize,
    outlier_ratio: f64,
    noise_px: f64,
    rng: &mut ChaCha8Rng,
) -> (Vec<Correspondence2D3D>, Vec<bool>) {
    let world_from_cam = truth.inverse();
    let noise = Normal::new(0.0, noise_px.max(1e-300)).unwrap();
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let mut data = Vec::with_capacity(n);
    let mut is_inlier = Vec::with_capacity(n);
    for _ in 0..n {
        let pixel = Vector2::new(rng.gen_range(0.0..w), rng.gen_range(0.0..h));
        let ray = camera.unproject(&pixel).unwrap();
        let point_in_cam = ray.normalize() * rng.gen_range(5.0..15.0);
        let point_in_world = world_from_cam.transform_point(&point_in_cam);
        let outlier = rng.gen_bool(outlier_ratio);
        let observed = if outlier {
            Vector2::new(rng.gen_range(0.0..w), rng.gen_range(0.0..h))
        } else if noise_px > 0.0 {
            pixel + Vector2::new(noise.sample(rng), noise.sample(rng))
        } else {
            pixel
        };
        data.push(Correspondence2D3D {
            pixel: observed,
            point_in_world,
        });
        is_inlier.push(!outlier);
    }
    (data, is_inlier)
}

fn registered(outcome: AbsolutePoseOutcome) -> RegisteredPose {
    match outcome {
        AbsolutePoseOutcome::Registered(r) => r,
        other => panic!("not registered: {other:?}"),
    }
}

#[test]
fn p3p_true_pose_among_solutions_for_random_configurations() {
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let camera = opencv();
    let mut within = 0;
    let trials = 500;
    for _ in 0..trials {
        let truth = random_pose(&mut rng);
        let (data, _) = pnp_scene(&camera, &truth, 3, 0.0, 0.0, &mut rng);
        let bearings: Vec<Vector3<f64>> = data
            .iter()
            .map(|c| camera.unproject(&c.pixel).unwrap())
            .collect();
        let solutions = p3p(
            &[bearings[0], bearings[1], bearings[2]],
            &[
                data[0].point_in_world,
                data[1].point_in_world,
                data[2].point_in_world,
            ],
        );
        let best = solutions
            .iter()
            .map(|s| {
                let r_rad = s.rotation.angle_to(&truth.rotation);
                let t_m = (s.translation - truth.translation).norm();
                r_rad.max(t_m)
            })
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-6, "true pose missing: best error {best}");
        if best < 1e-9 {
            within += 1;
        }
    }
    // A few ill-conditioned random triples are only good to ~1e-8.
    assert!(
        within * 100 >= trials * 99,
        "{within} of {trials} within 1e-9"
    );
}

fn check_pnp_with_outliers(camera: &Camera, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = random_pose(&mut rng);
    let (data, is_inlier) = pnp_scene(camera, &truth, 2000, 0.4, 1.0, &mut rng);
    let options = AbsolutePoseOptions::default();
    let start = Instant::now();
    let outcome = estimate_absolute_pose(
        camera,
        &data,
        None,
        &options,
        &mut ChaCha8Rng::seed_from_u64(1),
    )
    .unwrap();
    let elapsed = start.elapsed();
    let r = registered(outcome.clone());
    let (rot_deg, pos_m) = pose_error(&r.cam_from_world, &truth);
    eprintln!(
        "{}: PnP 2000 corr. 40% outliers: {:.2?}, {} iterations, {} inliers, rot {:.4} deg, pos {:.4} m, mean err {:.3} px",
        camera.model.name(),
        elapsed,
        r.num_ransac_iterations,
        r.num_inliers,
        rot_deg,
        pos_m,
        r.mean_inlier_error_px
    );
    assert!(rot_deg < 0.05, "rotation error {rot_deg} deg");
    assert!(pos_m < 0.01, "position error {pos_m} m");
    // The inlier mask agrees with the truth (a random outlier pixel lands
    // within 12 px of its point's projection with probability ~2e-4; a 1 px
    // Gaussian inlier exceeds 12 px never in practice).
    let wrong = r
        .inlier_mask
        .iter()
        .zip(&is_inlier)
        .filter(|(a, b)| a != b)
        .count();
    assert!(wrong <= 3, "{wrong} misclassified");
    assert!(
        r.refinement.as_ref().unwrap().final_cost <= r.refinement.as_ref().unwrap().initial_cost
    );
    // Same seed, same bits.
    let again = estimate_absolute_pose(
        camera,
        &data,
        None,
        &options,
        &mut ChaCha8Rng::seed_from_u64(1),
    )
    .unwrap();
    assert_eq!(outcome, again);
    let q1 = r.cam_from_world.quaternion_wxyz().map(f64::to_bits);
    let q2 = registered(again)
        .cam_from_world
        .quaternion_wxyz()
        .map(f64::to_bits);
    assert_eq!(q1, q2);
}

#[test]
fn pnp_recovers_pose_with_40_percent_outliers_pinhole() {
    check_pnp_with_outliers(&pinhole(), 10);
}

#[test]
fn pnp_recovers_pose_with_40_percent_outliers_opencv() {
    check_pnp_with_outliers(&opencv(), 11);
}

#[test]
fn pnp_many_random_scenes() {
    // Smaller scenes, many seeds: every one registers accurately.
    let camera = opencv();
    for seed in 0..20 {
        let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
        let truth = random_pose(&mut rng);
        let (data, _) = pnp_scene(&camera, &truth, 200, 0.4, 1.0, &mut rng);
        let r = registered(
            estimate_absolute_pose(&camera, &data, None, &Default::default(), &mut rng).unwrap(),
        );
        let (rot_deg, pos_m) = pose_error(&r.cam_from_world, &truth);
        assert!(
            rot_deg < 0.2 && pos_m < 0.05,
            "seed {seed}: {rot_deg} deg, {pos_m} m"
        );
    }
}

#[test]
fn refinement_reduces_error() {
    let camera = opencv();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let truth = random_pose(&mut rng);
    let (data, _) = pnp_scene(&camera, &truth, 500, 0.3, 1.0, &mut rng);
    // Minimal-sample pose only: no local optimisation, no refinement.
    let mut options = AbsolutePoseOptions::default();
    options.ransac.local_optimization = false;
    options.refine = false;
    let raw = registered(
        estimate_absolute_pose(
            &camera,
            &data,
            None,
            &options,
            &mut ChaCha8Rng::seed_from_u64(5),
        )
        .unwrap(),
    );
    options.refine = true;
    let refined = registered(
        estimate_absolute_pose(
            &camera,
            &data,
            None,
            &options,
            &mut ChaCha8Rng::seed_from_u64(5),
        )
        .unwrap(),
    );
    let (raw_rot, raw_pos) = pose_error(&raw.cam_from_world, &truth);
    let (rot, pos) = pose_error(&refined.cam_from_world, &truth);
    eprintln!("P3P-only: {raw_rot:.4} deg {raw_pos:.4} m; refined: {rot:.4} deg {pos:.4} m");
    assert!(rot < raw_rot && pos < raw_pos);
    assert!(refined.mean_inlier_error_px < raw.mean_inlier_error_px);
    // Mean error of a 1 px Gaussian in 2D: sqrt(pi/2) = 1.25 px.
    assert!(
        refined.mean_inlier_error_px < 1.4,
        "{}",
        refined.mean_inlier_error_px
    );

    // Direct refinement from a perturbed pose on the true inliers.
    let start = Rigid3::new(
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015) * truth.rotation,
        truth.translation + Vector3::new(0.2, -0.1, 0.3),
    );
    let inliers: Vec<_> = data
        .iter()
        .filter(|c| reprojection_error_px(&camera, &truth, c).is_some_and(|e| e < 5.0))
        .copied()
        .collect();
    let summary =
        refine_absolute_pose(&camera, &start, &inliers, &PoseRefinementOptions::default()).unwrap();
    let (rot0, pos0) = pose_error(&start, &truth);
    let (rot1, pos1) = pose_error(&summary.cam_from_world, &truth);
    assert!(summary.final_cost < summary.initial_cost);
    assert!(rot1 < rot0 / 10.0 && pos1 < pos0 / 10.0, "{rot1} {pos1}");
    assert!(summary.converged);
}

#[test]
fn pnp_prior_pose_is_used() {
    let camera = pinhole();
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let truth = random_pose(&mut rng);
    let (data, _) = pnp_scene(&camera, &truth, 300, 0.6, 0.5, &mut rng);
    // 60 % outliers: without prior the adaptive count is ~140 iterations; the
    // true pose as prior gives the support at once.
    let mut options = AbsolutePoseOptions::default();
    options.ransac.min_iterations = 0;
    let with_prior = registered(
        estimate_absolute_pose(&camera, &data, Some(&truth), &options, &mut rng).unwrap(),
    );
    let without =
        registered(estimate_absolute_pose(&camera, &data, None, &options, &mut rng).unwrap());
    assert!(with_prior.num_ransac_iterations <= without.num_ransac_iterations);
    let (rot, pos) = pose_error(&with_prior.cam_from_world, &truth);
    assert!(rot < 0.05 && pos < 0.02, "{rot} {pos}");
}

#[test]
fn pnp_degenerate_inputs_give_outcomes_not_panics() {
    let camera = pinhole();
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let options = AbsolutePoseOptions::default();
    let truth = random_pose(&mut rng);

    // Too few.
    let (few, _) = pnp_scene(&camera, &truth, 29, 0.0, 0.0, &mut rng);
    assert_eq!(
        estimate_absolute_pose(&camera, &few, None, &options, &mut rng).unwrap(),
        AbsolutePoseOutcome::NotEnoughCorrespondences {
            usable: 29,
            needed: 30
        }
    );
    assert!(matches!(
        estimate_absolute_pose(&camera, &[], None, &options, &mut rng).unwrap(),
        AbsolutePoseOutcome::NotEnoughCorrespondences { usable: 0, .. }
    ));

    // All world points on one line: the pose is undetermined.
    let world_from_cam = truth.inverse();
    let collinear: Vec<_> = (0..100)
        .map(|i| {
            let p_cam = Vector3::new(-2.0 + 0.04 * f64::from(i), 0.5, 10.0);
            Correspondence2D3D {
                pixel: camera.project(&p_cam).unwrap(),
                point_in_world: world_from_cam.transform_point(&p_cam),
            }
        })
        .collect();
    let outcome = estimate_absolute_pose(&camera, &collinear, None, &options, &mut rng).unwrap();
    assert!(
        matches!(outcome, AbsolutePoseOutcome::RansacFailed { .. }),
        "{outcome:?}"
    );

    // NaNs mixed in: flagged as outliers, the rest still registers.
    let (mut data, _) = pnp_scene(&camera, &truth, 200, 0.0, 0.5, &mut rng);
    for c in data.iter_mut().step_by(10) {
        c.pixel.x = f64::NAN;
    }
    data[1].point_in_world.z = f64::INFINITY;
    let r = registered(estimate_absolute_pose(&camera, &data, None, &options, &mut rng).unwrap());
    assert!(r.inlier_mask.iter().step_by(10).all(|&inlier| !inlier));
    assert!(!r.inlier_mask[1]);
    assert_eq!(r.num_inliers, 179);

    // All NaN.
    let nan = vec![
        Correspondence2D3D {
            pixel: Vector2::new(f64::NAN, 0.0),
            point_in_world: Vector3::zeros()
        };
        50
    ];
    assert!(matches!(
        estimate_absolute_pose(&camera, &nan, None, &options, &mut rng).unwrap(),
        AbsolutePoseOutcome::NotEnoughCorrespondences { usable: 0, .. }
    ));

    // Pure noise: no consistent pose.
    let (mut noise, _) = pnp_scene(&camera, &truth, 200, 1.0, 0.0, &mut rng);
    for c in noise.iter_mut() {
        c.point_in_world += Vector3::new(
            rng.gen_range(-50.0..50.0),
            rng.gen_range(-50.0..50.0),
            rng.gen_range(-50.0..50.0),
        );
    }
    let outcome = estimate_absolute_pose(&camera, &noise, None, &options, &mut rng).unwrap();
    assert!(
        matches!(
            outcome,
            AbsolutePoseOutcome::TooFewInliers { .. } | AbsolutePoseOutcome::RansacFailed { .. }
        ),
        "{outcome:?}"
    );
}

/// A camera at `center` looking at `target` (z forward), as `cam_from_world`.
fn look_at(center: Vector3<f64>, target: Vector3<f64>) -> Rigid3 {
    let z = (target - center).normalize();
    let up = if z.z.abs() > 0.9 {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let x = up.cross(&z).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    Rigid3::from_rotation_matrix(&r, -(r * center))
}

fn observe<'a>(camera: &'a Camera, pose: Rigid3, point: &Vector3<f64>) -> PointObservation<'a> {
    // The tests aim every camera at the point: it projects near the centre.
    let pixel = camera.project(&pose.transform_point(point)).unwrap();
    PointObservation::new(camera, pose, pixel).unwrap()
}

#[test]
fn triangulation_track_with_outliers_and_noise() {
    let camera = opencv();
    let mut rng = ChaCha8Rng::seed_from_u64(51);
    let noise = Normal::new(0.0, 0.5).unwrap();
    let mut worst_m = 0.0f64;
    for _ in 0..50 {
        let point = Vector3::new(
            rng.gen_range(-1e3..1e3),
            rng.gen_range(-1e3..1e3),
            rng.gen_range(0.0..20.0),
        );
        let mut obs: Vec<PointObservation> = (0..8)
            .map(|_| {
                let center = point
                    + Vector3::new(
                        rng.gen_range(-8.0..8.0),
                        rng.gen_range(-8.0..8.0),
                        rng.gen_range(-1.0..1.0),
                    )
                    .normalize()
                        * 10.0;
                let aim =
                    point + Vector3::new(rng.gen_range(-2.0..2.0), rng.gen_range(-2.0..2.0), 0.5);
                let mut o = observe(&camera, look_at(center, aim), &point);
                o.pixel += Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
                PointObservation::new(&camera, o.cam_from_world, o.pixel).unwrap()
            })
            .collect();
        // Two wrong matches.
        for k in [2, 5] {
            obs[k].pixel += Vector2::new(80.0, -60.0);
            obs[k] = PointObservation::new(&camera, obs[k].cam_from_world, obs[k].pixel).unwrap();
        }
        let options = TriangulationOptions::default();
        let tri = triangulate_track_ransac(&obs, &options, &mut rng).unwrap();
        let expected: Vec<bool> = (0..8).map(|k| k != 2 && k != 5).collect();
        assert_eq!(tri.inlier_mask, expected);
        assert_eq!(tri.num_inliers, 6);
        assert!(tri.max_angle_deg > 1.5);
        worst_m = worst_m.max((tri.point_in_world - point).norm());
        // The plain (all-views) triangulation refuses the track.
        assert!(matches!(
            triangulate_point(&obs, &options),
            Err(TriangulationFailure::LargeReprojectionError { .. })
        ));
    }
    // 0.5 px noise at 10 m with f = 1400: ~4 mm per view.
    assert!(worst_m < 0.02, "{worst_m}");
}

#[test]
fn triangulation_cheirality_and_angle_rejection() {
    let camera = pinhole();
    let (f, cx, cy) = (1400.0, 960.0, 540.0);
    let forward = Rigid3::identity(); // looks along +z
    let at = |x: f64| Rigid3::new(UnitQuaternion::identity(), Vector3::new(-x, 0.0, 0.0));
    // Rays from cameras at x = -1 and x = +1 (looking along +z) whose lines
    // meet at (0, 0, -10), behind both.
    let o1 = PointObservation::new(&camera, at(-1.0), Vector2::new(cx - 0.1 * f, cy)).unwrap();
    let o2 = PointObservation::new(&camera, at(1.0), Vector2::new(cx + 0.1 * f, cy)).unwrap();
    assert_eq!(
        triangulate_point(&[o1, o2], &Default::default()),
        Err(TriangulationFailure::NegativeDepth { observation: 0 })
    );
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    assert_eq!(
        triangulate_track_ransac(&[o1, o2], &Default::default(), &mut rng),
        Err(TriangulationFailure::RansacFailed)
    );
    // The mirrored pixels meet at (0, 0, +10): accepted, exactly.
    let p1 = PointObservation::new(&camera, at(-1.0), Vector2::new(cx + 0.1 * f, cy)).unwrap();
    let p2 = PointObservation::new(&camera, at(1.0), Vector2::new(cx - 0.1 * f, cy)).unwrap();
    let tri = triangulate_point(&[p1, p2], &Default::default()).unwrap();
    assert!((tri.point_in_world - Vector3::new(0.0, 0.0, 10.0)).norm() < 1e-12);
    // 2 atan(1/10) = 11.42 deg.
    assert!((tri.max_angle_deg - 2.0 * 0.1f64.atan().to_degrees()).abs() < 1e-9);

    // Baseline 0.2 m at 10 m: 1.146 deg < 1.5 deg.
    let point = Vector3::new(0.0, 0.0, 10.0);
    let q1 = observe(&camera, at(-0.1), &point);
    let q2 = observe(&camera, at(0.1), &point);
    let q0 = observe(&camera, forward, &point);
    match triangulate_point(&[q1, q0, q2], &Default::default()) {
        Err(TriangulationFailure::SmallAngle { angle_deg }) => {
            assert!((angle_deg - 2.0 * 0.01f64.atan().to_degrees()).abs() < 1e-9)
        }
        other => panic!("{other:?}"),
    }
    let relaxed = TriangulationOptions {
        min_angle_deg: 1.0,
        ..Default::default()
    };
    let tri = triangulate_point(&[q1, q0, q2], &relaxed).unwrap();
    assert!((tri.point_in_world - point).norm() < 1e-9);
    assert!(matches!(
        triangulate_track_ransac(&[q1, q0, q2], &Default::default(), &mut rng),
        Err(TriangulationFailure::RansacFailed | TriangulationFailure::SmallAngle { .. })
    ));
}

#[test]
fn umeyama_recovers_sim3_at_utm_scale() {
    let mut rng = ChaCha8Rng::seed_from_u64(61);
    let truth = Sim3 {
        scale: 3.7,
        rotation: UnitQuaternion::from_euler_angles(0.3, -0.4, 2.5),
        translation: Vector3::new(4.5e5, 5.3e6, 120.0),
    };
    let pairs: Vec<_> = (0..100)
        .map(|_| {
            let a = Vector3::new(
                rng.gen_range(-50.0..50.0),
                rng.gen_range(-50.0..50.0),
                rng.gen_range(-5.0..5.0),
            );
            (a, truth.transform_point(&a))
        })
        .collect();
    let est = umeyama(&pairs, true).unwrap();
    assert!((est.scale - truth.scale).abs() < 1e-12 * truth.scale);
    assert!(est.rotation.angle_to(&truth.rotation) < 1e-12);
    assert!((est.translation - truth.translation).norm() < 1e-6);
    // With outliers.
    let mut noisy = pairs.clone();
    for p in noisy.iter_mut().step_by(3) {
        p.1 += Vector3::new(rng.gen_range(5.0..50.0), 0.0, rng.gen_range(-50.0..-5.0));
    }
    let options = RansacOptions {
        max_error: 0.01,
        ..Default::default()
    };
    let report = estimate_sim3_ransac(&noisy, true, &options, &mut rng).unwrap();
    assert_eq!(report.num_inliers, 66);
    assert!((report.model.scale - truth.scale).abs() < 1e-9 * truth.scale);
}

#[test]
fn ray_plane_initialisation_for_any_pose() {
    // A wall and a floor seen by cameras with random poses: the feature's ray
    // meets the LiDAR tangent plane at the true surface point, which projects
    // back onto the feature.
    let camera = opencv();
    let mut rng = ChaCha8Rng::seed_from_u64(71);
    let mut hits = 0;
    for _ in 0..300 {
        let center = Vector3::new(
            rng.gen_range(-20.0..20.0) + 3.2e5,
            rng.gen_range(-20.0..20.0) + 4.1e6,
            rng.gen_range(0.5..3.0),
        );
        // A point on the floor z = 0 or on the wall x = 3.2e5 + 30.
        let (normal, surface_point) = if rng.gen_bool(0.5) {
            (
                Vector3::z(),
                Vector3::new(
                    center.x + rng.gen_range(-10.0..10.0),
                    center.y + rng.gen_range(-10.0..10.0),
                    0.0,
                ),
            )
        } else {
            (
                -Vector3::x(),
                Vector3::new(
                    3.2e5 + 30.0,
                    center.y + rng.gen_range(-10.0..10.0),
                    rng.gen_range(0.0..5.0),
                ),
            )
        };
        let pose = look_at(center, surface_point);
        let pixel = camera
            .project(&pose.transform_point(&surface_point))
            .unwrap();
        // The LiDAR point that "sees" the feature: elsewhere on the same plane.
        let lidar_point = surface_point + normal.cross(&Vector3::new(0.2, 0.7, 0.1)) * 0.3;
        match intersect_pixel_ray_plane(
            &camera,
            &pose,
            &pixel,
            &normal,
            &lidar_point,
            &RayPlaneOptions::default(),
        ) {
            Ok(hit) => {
                hits += 1;
                assert!(
                    (hit.point - surface_point).norm() < 1e-6,
                    "{:?}",
                    hit.point - surface_point
                );
                assert!((hit.range_m - (surface_point - center).norm()).abs() < 1e-6);
            }
            Err(RayPlaneMiss::NearlyParallel { incidence_deg }) => assert!(incidence_deg > 80.0),
            Err(e) => panic!("{e}"),
        }
    }
    assert!(hits > 200, "{hits}");
}
