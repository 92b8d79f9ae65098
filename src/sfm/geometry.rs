//! Geometry specific to the mapper: reprojection error through the real camera
//! model, Gauss-Newton pose refinement, and the ray/tangent-plane intersection of
//! the initialisation. The minimal solvers (P3P, DLT, triangulation angle) come
//! from [`crate::estimators`].
use nalgebra::{Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};

use crate::scene::{Camera, Rigid3};

/// Squared reprojection error (px^2) of a world point, `None` when behind the
/// camera or not projectable.
pub fn reprojection_error_sq(
    camera: &Camera,
    cam_from_world: &Rigid3,
    point_in_world: &Vector3<f64>,
    pixel: &Vector2<f64>,
) -> Option<f64> {
    let p = cam_from_world.transform_point(point_in_world);
    if p.z <= 1e-9 {
        return None;
    }
    camera.project(&p).map(|q| (q - pixel).norm_squared())
}

/// `cam_from_world` perturbed by `delta = [omega; dc]`: rotation exp(omega)
/// applied on the left, camera centre moved by `dc` (world frame). Rotating
/// about the camera centre, not the world origin, keeps the problem well
/// conditioned for georeferenced coordinates (10^6 m).
fn perturb(pose: &Rigid3, delta: &Vector6<f64>) -> Rigid3 {
    let omega = Vector3::new(delta[0], delta[1], delta[2]);
    let dq = UnitQuaternion::from_scaled_axis(omega);
    let rotation = dq * pose.rotation;
    let centre = pose.camera_center() + Vector3::new(delta[3], delta[4], delta[5]);
    Rigid3::from_rotation_and_center(rotation, &centre)
}

/// Refines `cam_from_world` by Levenberg-Marquardt on the reprojection errors
/// of `pixels` / `points_in_world`, with a Huber weight of scale `huber_px`.
/// Numerical Jacobians (central differences). Returns the refined pose, or the
/// input when nothing could be evaluated.
pub fn refine_pose(
    camera: &Camera,
    cam_from_world: &Rigid3,
    pixels: &[Vector2<f64>],
    points_in_world: &[Vector3<f64>],
    huber_px: f64,
    max_iterations: usize,
) -> Rigid3 {
    let cost = |pose: &Rigid3| -> f64 {
        let mut total = 0.0;
        for (x, p) in pixels.iter().zip(points_in_world) {
            let e2 = reprojection_error_sq(camera, pose, p, x).unwrap_or(1e6);
            let e = e2.sqrt();
            total += if e <= huber_px {
                e2
            } else {
                2.0 * huber_px * e - huber_px * huber_px
            };
        }
        total
    };
    let residual = |pose: &Rigid3, p: &Vector3<f64>, x: &Vector2<f64>| -> Option<Vector2<f64>> {
        let pc = pose.transform_point(p);
        if pc.z <= 1e-9 {
            return None;
        }
        camera.project(&pc).map(|q| q - x)
    };
    let mut pose = *cam_from_world;
    let mut current = cost(&pose);
    let mut lambda = 1e-3;
    let h = 1e-6;
    for _ in 0..max_iterations {
        let mut jtj = Matrix6::<f64>::zeros();
        let mut jtr = Vector6::<f64>::zeros();
        let mut used = 0usize;
        let plus: Vec<Rigid3> = (0..6)
            .map(|k| {
                perturb(
                    &pose,
                    &Vector6::from_fn(|i, _| if i == k { h } else { 0.0 }),
                )
            })
            .collect();
        let minus: Vec<Rigid3> = (0..6)
            .map(|k| {
                perturb(
                    &pose,
                    &Vector6::from_fn(|i, _| if i == k { -h } else { 0.0 }),
                )
            })
            .collect();
        'obs: for (x, p) in pixels.iter().zip(points_in_world) {
            let Some(r) = residual(&pose, p, x) else {
                continue;
            };
            let mut jac = nalgebra::Matrix2x6::<f64>::zeros();
            for k in 0..6 {
                let (Some(rp), Some(rm)) = (residual(&plus[k], p, x), residual(&minus[k], p, x))
                else {
                    continue 'obs;
                };
                jac.set_column(k, &((rp - rm) / (2.0 * h)));
            }
            let e = r.norm();
            let w = if e <= huber_px { 1.0 } else { huber_px / e };
            jtj += jac.transpose() * jac * w;
            jtr += jac.transpose() * r * w;
            used += 1;
        }
        if used < 3 {
            break;
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj;
            for i in 0..6 {
                a[(i, i)] += lambda * (1.0 + jtj[(i, i)]);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = perturb(&pose, &step);
            let c = cost(&candidate);
            if c < current {
                let rel = (current - c) / current.max(1e-300);
                pose = candidate;
                current = c;
                lambda = (lambda * 0.1).max(1e-12);
                improved = true;
                if rel < 1e-10 || step.norm() < 1e-12 {
                    return pose;
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    pose
}

/// Intersection of the ray `origin + s * dir` (s > 0) with the plane
/// `normal . X = offset`. `None` when the ray is within `min_cos` of parallel
/// (`|cos(angle(dir, normal))| < min_cos`) or the hit is behind the origin.
pub fn intersect_ray_plane(
    origin: &Vector3<f64>,
    dir: &Vector3<f64>,
    normal: &Vector3<f64>,
    offset: f64,
    min_cos: f64,
) -> Option<Vector3<f64>> {
    let d = dir.normalize();
    let n = normal.normalize();
    let cos = n.dot(&d);
    if cos.abs() < min_cos {
        return None;
    }
    let s = (offset - n.dot(origin)) / cos;
    (s > 0.0 && s.is_finite()).then(|| origin + d * s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraId, CameraModel};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::from_name("SIMPLE_RADIAL").unwrap(),
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0, -0.05],
        }
    }

    fn random_pose(rng: &mut ChaCha8Rng) -> Rigid3 {
        let r = UnitQuaternion::from_euler_angles(
            rng.gen_range(-3.0..3.0),
            rng.gen_range(-1.5..1.5),
            rng.gen_range(-3.0..3.0),
        );
        Rigid3::new(
            r,
            Vector3::new(
                rng.gen_range(-2.0..2.0),
                rng.gen_range(-2.0..2.0),
                rng.gen_range(-2.0..2.0),
            ),
        )
    }

    fn point_in_front(rng: &mut ChaCha8Rng, pose: &Rigid3) -> Vector3<f64> {
        let pc = Vector3::new(
            rng.gen_range(-2.0..2.0),
            rng.gen_range(-2.0..2.0),
            rng.gen_range(2.0..8.0),
        );
        pose.inverse().transform_point(&pc)
    }

    #[test]
    fn refine_pose_converges_from_perturbation() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let cam = camera();
        let pose = random_pose(&mut rng);
        let points: Vec<Vector3<f64>> = (0..50).map(|_| point_in_front(&mut rng, &pose)).collect();
        let pixels: Vec<Vector2<f64>> = points
            .iter()
            .map(|p| cam.project(&pose.transform_point(p)).unwrap())
            .collect();
        let start = perturb(&pose, &Vector6::new(0.02, -0.01, 0.015, 0.05, -0.03, 0.02));
        let refined = refine_pose(&cam, &start, &pixels, &points, 2.0, 50);
        assert!(refined.rotation.angle_to(&pose.rotation) < 1e-8);
        assert!((refined.translation - pose.translation).norm() < 1e-7);
    }

    #[test]
    fn refinement_with_georeferenced_coordinates() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let offset = Vector3::new(512_000.0, 5_400_000.0, 230.0);
        let cam = camera();
        let pose = random_pose(&mut rng);
        let pose = Rigid3::new(pose.rotation, pose.translation - pose.rotation * offset);
        let points: Vec<Vector3<f64>> = (0..50).map(|_| point_in_front(&mut rng, &pose)).collect();
        let pixels: Vec<Vector2<f64>> = points
            .iter()
            .map(|p| cam.project(&pose.transform_point(p)).unwrap())
            .collect();
        let start = perturb(&pose, &Vector6::new(0.02, -0.01, 0.015, 0.05, -0.03, 0.02));
        let refined = refine_pose(&cam, &start, &pixels, &points, 2.0, 50);
        assert!(refined.rotation.angle_to(&pose.rotation) < 1e-7);
        assert!((refined.camera_center() - pose.camera_center()).norm() < 1e-6);
    }

    #[test]
    fn ray_plane_and_angle() {
        let hit = intersect_ray_plane(
            &Vector3::new(0.0, 0.0, 1.0),
            &Vector3::new(1.0, 0.0, -1.0),
            &Vector3::new(0.0, 0.0, 1.0),
            0.0,
            0.1,
        )
        .unwrap();
        assert!((hit - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        // Behind, and parallel.
        assert!(intersect_ray_plane(
            &Vector3::new(0.0, 0.0, 1.0),
            &Vector3::new(0.0, 0.0, 1.0),
            &Vector3::z(),
            0.0,
            0.1
        )
        .is_none());
        assert!(intersect_ray_plane(
            &Vector3::new(0.0, 0.0, 1.0),
            &Vector3::new(1.0, 0.0, 0.01),
            &Vector3::z(),
            0.0,
            0.1
        )
        .is_none());
    }
}
