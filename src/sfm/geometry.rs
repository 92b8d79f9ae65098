//! Small geometric solvers the mapper needs: minimal P3P (Grunert), rigid
//! alignment of three points, Gauss-Newton pose refinement through the real
//! camera model, multi-view DLT triangulation, triangulation angle, ray-plane
//! intersection.
//!
//! These are kept local and small on purpose: the `estimators` module (written
//! in parallel) will offer tested general versions; the mapper calls only the
//! functions below, so switching is a local change.
use nalgebra::{Matrix3, Matrix4, Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};

use crate::scene::{Camera, Rigid3};

/// Real roots of `c[0] x^4 + c[1] x^3 + c[2] x^2 + c[3] x + c[4]` (companion
/// matrix eigenvalues, polished by Newton steps).
fn quartic_real_roots(c: [f64; 5]) -> Vec<f64> {
    if c[0].abs() < 1e-14 * c.iter().fold(0.0_f64, |m, v| m.max(v.abs())) {
        return Vec::new();
    }
    let a = [c[1] / c[0], c[2] / c[0], c[3] / c[0], c[4] / c[0]];
    let mut m = Matrix4::zeros();
    m[(0, 0)] = -a[0];
    m[(0, 1)] = -a[1];
    m[(0, 2)] = -a[2];
    m[(0, 3)] = -a[3];
    m[(1, 0)] = 1.0;
    m[(2, 1)] = 1.0;
    m[(3, 2)] = 1.0;
    let eig = m.complex_eigenvalues();
    let poly = |x: f64| (((x + a[0]) * x + a[1]) * x + a[2]) * x + a[3];
    let dpoly = |x: f64| ((4.0 * x + 3.0 * a[0]) * x + 2.0 * a[1]) * x + a[2];
    let mut roots = Vec::new();
    for z in eig.iter() {
        if z.im.abs() > 1e-6 * (1.0 + z.re.abs()) {
            continue;
        }
        let mut x = z.re;
        for _ in 0..3 {
            let d = dpoly(x);
            if d.abs() < 1e-300 {
                break;
            }
            x -= poly(x) / d;
        }
        if x.is_finite() {
            roots.push(x);
        }
    }
    roots
}

/// Orthonormal frame (columns) of three non-collinear points.
fn triangle_frame(p: &[Vector3<f64>; 3]) -> Option<Matrix3<f64>> {
    let e1 = (p[1] - p[0]).try_normalize(1e-12)?;
    let e3 = e1.cross(&(p[2] - p[0])).try_normalize(1e-12)?;
    let e2 = e3.cross(&e1);
    Some(Matrix3::from_columns(&[e1, e2, e3]))
}

/// Minimal absolute pose (Grunert's solution, as reviewed by Haralick et al.
/// 1994): three unit bearings in the camera frame and their world points give
/// up to four `cam_from_world` poses.
pub fn p3p(bearings: &[Vector3<f64>; 3], points_in_world: &[Vector3<f64>; 3]) -> Vec<Rigid3> {
    let [p1, p2, p3] = points_in_world;
    let a2 = (p2 - p3).norm_squared();
    let b2 = (p1 - p3).norm_squared();
    let c2 = (p1 - p2).norm_squared();
    if a2 < 1e-18 || b2 < 1e-18 || c2 < 1e-18 {
        return Vec::new();
    }
    let j: Vec<Vector3<f64>> = bearings.iter().map(|b| b.normalize()).collect();
    let cos_a = j[1].dot(&j[2]);
    let cos_b = j[0].dot(&j[2]);
    let cos_g = j[0].dot(&j[1]);
    let amc = (a2 - c2) / b2;
    let apc = (a2 + c2) / b2;
    let bmc = (b2 - c2) / b2;
    let bma = (b2 - a2) / b2;
    let coeffs = [
        (amc - 1.0).powi(2) - 4.0 * c2 / b2 * cos_a * cos_a,
        4.0 * (amc * (1.0 - amc) * cos_b - (1.0 - apc) * cos_a * cos_g
            + 2.0 * c2 / b2 * cos_a * cos_a * cos_b),
        2.0 * (amc * amc - 1.0 + 2.0 * amc * amc * cos_b * cos_b + 2.0 * bmc * cos_a * cos_a
            - 4.0 * apc * cos_a * cos_b * cos_g
            + 2.0 * bma * cos_g * cos_g),
        4.0 * (-amc * (1.0 + amc) * cos_b + 2.0 * a2 / b2 * cos_g * cos_g * cos_b
            - (1.0 - apc) * cos_a * cos_g),
        (1.0 + amc).powi(2) - 4.0 * a2 / b2 * cos_g * cos_g,
    ];
    let Some(world_frame) = triangle_frame(&[*p1, *p2, *p3]) else {
        return Vec::new();
    };
    let mut poses = Vec::new();
    for v in quartic_real_roots(coeffs) {
        if v <= 0.0 {
            continue;
        }
        let denom = 2.0 * (cos_g - v * cos_a);
        if denom.abs() < 1e-12 {
            continue;
        }
        let u = ((-1.0 + amc) * v * v - 2.0 * amc * cos_b * v + 1.0 + amc) / denom;
        if u <= 0.0 {
            continue;
        }
        let s1_sq = c2 / (1.0 + u * u - 2.0 * u * cos_g);
        if s1_sq.is_nan() || s1_sq <= 0.0 {
            continue;
        }
        let s1 = s1_sq.sqrt();
        let cam = [j[0] * s1, j[1] * (u * s1), j[2] * (v * s1)];
        let Some(cam_frame) = triangle_frame(&cam) else {
            continue;
        };
        let rotation = cam_frame * world_frame.transpose();
        let translation = cam[0] - rotation * p1;
        let pose = Rigid3::from_rotation_matrix(&rotation, translation);
        if pose.translation.iter().all(|x| x.is_finite()) {
            poses.push(pose);
        }
    }
    poses
}

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
    Rigid3::new(rotation, -(rotation * centre))
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

/// Linear (DLT) triangulation from two or more views: each view gives
/// `cam_from_world` and the ray direction `(x, y, 1)` on the normalised plane.
/// Minimises the algebraic error of `x * P3 - P1 = 0`, `y * P3 - P2 = 0` via
/// the smallest eigenvector of `A^T A`. `None` for a degenerate system or a
/// point at infinity.
pub fn triangulate_dlt(views: &[(Rigid3, Vector2<f64>)]) -> Option<Vector3<f64>> {
    if views.len() < 2 {
        return None;
    }
    // Solve in a frame centred on the first camera: with georeferenced
    // coordinates the world-frame system is hopelessly ill-conditioned.
    let origin = views[0].0.camera_center();
    let mut ata = Matrix4::<f64>::zeros();
    for (pose, x) in views {
        let r = pose.rotation_matrix();
        let t = pose.translation + r * origin;
        let row = |k: usize| nalgebra::RowVector4::new(r[(k, 0)], r[(k, 1)], r[(k, 2)], t[k]);
        for row_vec in [row(2) * x.x - row(0), row(2) * x.y - row(1)] {
            let n = row_vec.norm();
            if n < 1e-15 {
                continue;
            }
            let v = row_vec / n;
            ata += v.transpose() * v;
        }
    }
    let eig = ata.symmetric_eigen();
    let (mut k_min, mut v_min) = (0, f64::INFINITY);
    for k in 0..4 {
        if eig.eigenvalues[k] < v_min {
            v_min = eig.eigenvalues[k];
            k_min = k;
        }
    }
    let h = eig.eigenvectors.column(k_min);
    if h[3].abs() < 1e-12 {
        return None;
    }
    let p = Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]) + origin;
    p.iter().all(|v| v.is_finite()).then_some(p)
}

/// Angle (radians) at `point` between the rays to two camera centres.
pub fn triangulation_angle_rad(
    center1: &Vector3<f64>,
    center2: &Vector3<f64>,
    point: &Vector3<f64>,
) -> f64 {
    let a = center1 - point;
    let b = center2 - point;
    let denom = a.norm() * b.norm();
    if denom <= 0.0 {
        return 0.0;
    }
    (a.dot(&b) / denom).clamp(-1.0, 1.0).acos()
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
    fn p3p_recovers_random_poses() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut found = 0;
        for _ in 0..200 {
            let pose = random_pose(&mut rng);
            let pts = [
                point_in_front(&mut rng, &pose),
                point_in_front(&mut rng, &pose),
                point_in_front(&mut rng, &pose),
            ];
            let bearings = pts.map(|p| pose.transform_point(&p).normalize());
            let sols = p3p(&bearings, &pts);
            assert!(sols.len() <= 4);
            let best = sols
                .iter()
                .map(|s| {
                    s.rotation.angle_to(&pose.rotation) + (s.translation - pose.translation).norm()
                })
                .fold(f64::INFINITY, f64::min);
            if best < 1e-6 {
                found += 1;
            }
            // Every returned solution reprojects the three points exactly.
            for s in &sols {
                for (p, b) in pts.iter().zip(&bearings) {
                    let q = s.transform_point(p).normalize();
                    assert!((q - b).norm() < 1e-5, "solution does not fit its sample");
                }
            }
        }
        assert!(
            found >= 196,
            "true pose among the solutions in {found}/200 cases"
        );
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
    fn dlt_triangulates_exactly() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..50 {
            let poses: Vec<Rigid3> = (0..3).map(|_| random_pose(&mut rng)).collect();
            let x = Vector3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            );
            let views: Vec<(Rigid3, Vector2<f64>)> = poses
                .iter()
                .map(|p| {
                    let c = p.transform_point(&x);
                    (*p, Vector2::new(c.x / c.z, c.y / c.z))
                })
                .collect();
            let y = triangulate_dlt(&views).unwrap();
            assert!((y - x).norm() < 1e-8, "{y} vs {x}");
        }
    }

    #[test]
    fn dlt_and_refinement_with_georeferenced_coordinates() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let offset = Vector3::new(512_000.0, 5_400_000.0, 230.0);
        let cam = camera();
        for _ in 0..20 {
            let poses: Vec<Rigid3> = (0..3)
                .map(|_| {
                    let p = random_pose(&mut rng);
                    // Same camera, world shifted by `offset`.
                    Rigid3::new(p.rotation, p.translation - p.rotation * offset)
                })
                .collect();
            let x = offset
                + Vector3::new(
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-1.0..1.0),
                );
            let views: Vec<(Rigid3, Vector2<f64>)> = poses
                .iter()
                .map(|p| {
                    let c = p.transform_point(&x);
                    (*p, Vector2::new(c.x / c.z, c.y / c.z))
                })
                .collect();
            let y = triangulate_dlt(&views).unwrap();
            assert!((y - x).norm() < 1e-6, "{}", (y - x).norm());
        }
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
        let a = triangulation_angle_rad(
            &Vector3::new(-1.0, 0.0, 0.0),
            &Vector3::new(1.0, 0.0, 0.0),
            &Vector3::new(0.0, 1.0, 0.0),
        );
        assert!((a - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        let r = quartic_real_roots([1.0, -10.0, 35.0, -50.0, 24.0]);
        let mut r = r;
        r.sort_by(f64::total_cmp);
        assert_eq!(r.len(), 4);
        for (x, e) in r.iter().zip([1.0, 2.0, 3.0, 4.0]) {
            assert!((x - e).abs() < 1e-9);
        }
    }
}
