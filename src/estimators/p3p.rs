//! Minimal absolute pose (P3P) by Lambda Twist (Persson & Nordberg, ECCV 2018),
//! written from the paper's mathematics.
//!
//! Given unit bearings `y_i` (rays in the camera frame) and world points `x_i`,
//! the depths `λ_i` with `λ_i y_i = R x_i + t` satisfy, for each pair,
//! `|λ_i y_i - λ_j y_j|² = |x_i - x_j|²`, i.e. `Λᵀ M_ij Λ = a_ij` with
//! `a_ij = |x_i - x_j|²`, `b_ij = y_i·y_j` and `M_ij` the quadratic form
//! `λ_i² + λ_j² - 2 b_ij λ_i λ_j`. Eliminating the right-hand sides gives two
//! homogeneous conics `D1 = a23 M12 - a12 M23`, `D2 = a23 M13 - a13 M23` whose
//! common zeros contain every solution. A degenerate member `D0 = D1 + γ D2`
//! (a real root of the cubic `det(D1 + γ D2) = 0`) has rank 2 and factors into
//! two planes through the origin, read off its eigen-decomposition
//! `D0 = σa ea eaᵀ + σb eb ebᵀ`: `(ea ± s eb)·Λ = 0`, `s = sqrt(-σb/σa)`. On each
//! plane a second conic gives a quadratic with up to two rays; the scale comes
//! from one `a_ij`. The depths are polished by Gauss-Newton on the three
//! distance equations, and the pose is the rigid (Kabsch) fit of `x_i` to
//! `λ_i y_i`.
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::similarity::umeyama;
use crate::scene::Rigid3;

/// Gauss-Newton iterations polishing the depths.
const DEPTH_REFINEMENT_ITERATIONS: usize = 5;
/// A solution is kept when every distance equation holds to this relative error.
const MAX_RELATIVE_DISTANCE_ERROR: f64 = 1e-6;

/// Up to 4 poses `cam_from_world` such that each `points_in_world[i]` lies on the
/// ray `bearings[i]` (any positive length; normalised here) in front of the
/// camera. Empty for degenerate input: non-finite values, coincident or
/// collinear world points, zero bearings.
pub fn p3p(bearings: &[Vector3<f64>; 3], points_in_world: &[Vector3<f64>; 3]) -> Vec<Rigid3> {
    let mut y = [Vector3::zeros(); 3];
    for (yi, b) in y.iter_mut().zip(bearings) {
        let norm = b.norm();
        if !(norm.is_finite() && norm > 0.0) {
            return vec![];
        }
        *yi = b / norm;
    }
    let x = points_in_world;
    if !x.iter().all(|p| p.iter().all(|c| c.is_finite())) {
        return vec![];
    }
    let a12 = (x[0] - x[1]).norm_squared();
    let a13 = (x[0] - x[2]).norm_squared();
    let a23 = (x[1] - x[2]).norm_squared();
    let area_sq = (x[1] - x[0]).cross(&(x[2] - x[0])).norm_squared();
    // sin² of the angle at x0 below 1e-20: collinear; the pose is undetermined.
    if !(area_sq > 1e-20 * a12 * a13) {
        return vec![];
    }
    let (b12, b13, b23) = (y[0].dot(&y[1]), y[0].dot(&y[2]), y[1].dot(&y[2]));

    let m12 = Matrix3::new(1.0, -b12, 0.0, -b12, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, -b13, 0.0, 0.0, 0.0, -b13, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, -b23, 0.0, -b23, 1.0);
    let d1 = m12 * a23 - m23 * a12;
    let d2 = m13 * a23 - m23 * a13;

    let Some((d0, d_other)) = degenerate_conic(&d1, &d2) else {
        return vec![];
    };
    let Some(eigen) = symmetric_eigen(d0) else {
        return vec![];
    };
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| {
        eigen.eigenvalues[j]
            .abs()
            .total_cmp(&eigen.eigenvalues[i].abs())
    });
    let (sigma_a, sigma_b) = (eigen.eigenvalues[order[0]], eigen.eigenvalues[order[1]]);
    let e_a: Vector3<f64> = eigen.eigenvectors.column(order[0]).into();
    let e_b: Vector3<f64> = eigen.eigenvectors.column(order[1]).into();
    let e_null: Vector3<f64> = eigen.eigenvectors.column(order[2]).into();
    if sigma_a == 0.0 || !sigma_a.is_finite() {
        return vec![];
    }
    // Same signs (only possible through rounding when a solution exists): s = 0.
    let s = (-sigma_b / sigma_a).max(0.0).sqrt();

    let a = [a12, a13, a23];
    let b = [b12, b13, b23];
    let mut solutions: Vec<Rigid3> = Vec::with_capacity(4);
    let scale_sq = a12.max(a13).max(a23);
    for plane_normal in [e_a + s * e_b, e_a - s * e_b] {
        let u = e_null;
        let v = plane_normal.cross(&u);
        let v_norm = v.norm();
        if !(v_norm > 0.0) {
            continue;
        }
        let v = v / v_norm;
        for direction in rays_on_plane(&d_other, &u, &v) {
            let Some(depths) = depths_along(&direction, &a, &b) else {
                continue;
            };
            let camera_points = [depths[0] * y[0], depths[1] * y[1], depths[2] * y[2]];
            let pairs = [
                (x[0], camera_points[0]),
                (x[1], camera_points[1]),
                (x[2], camera_points[2]),
            ];
            let Some(fit) = umeyama(&pairs, false) else {
                continue;
            };
            let pose = fit.rigid();
            let duplicate = solutions.iter().any(|p| {
                p.rotation.angle_to(&pose.rotation) < 1e-12
                    && (p.translation - pose.translation).norm_squared() < 1e-24 * scale_sq
            });
            if !duplicate {
                solutions.push(pose);
            }
        }
    }
    solutions
}

/// Eigen-decomposition with a bounded iteration count (nalgebra's `new` iterates
/// without limit); `None` for non-finite input or no convergence.
fn symmetric_eigen(m: Matrix3<f64>) -> Option<SymmetricEigen<f64, nalgebra::U3>> {
    if !m.iter().all(|x| x.is_finite()) {
        return None;
    }
    SymmetricEigen::try_new(m, f64::EPSILON, 1000)
}

fn det3(c0: &Vector3<f64>, c1: &Vector3<f64>, c2: &Vector3<f64>) -> f64 {
    c0.dot(&c1.cross(c2))
}

/// A rank-2 member `D0 = w1 D1 + w2 D2` of the pencil, and the member (`D1` or
/// `D2`) to intersect its planes with. Of the cubic's real roots, the one whose
/// `D0` is closest to rank 2 (smallest |σ_null| / |σ_b|) is taken.
fn degenerate_conic(d1: &Matrix3<f64>, d2: &Matrix3<f64>) -> Option<(Matrix3<f64>, Matrix3<f64>)> {
    let c1s: [Vector3<f64>; 3] = [
        d1.column(0).into(),
        d1.column(1).into(),
        d1.column(2).into(),
    ];
    let c2s: [Vector3<f64>; 3] = [
        d2.column(0).into(),
        d2.column(1).into(),
        d2.column(2).into(),
    ];
    // det(D1 + g D2) = k3 g³ + k2 g² + k1 g + k0 (multilinearity in the columns).
    let k0 = det3(&c1s[0], &c1s[1], &c1s[2]);
    let k3 = det3(&c2s[0], &c2s[1], &c2s[2]);
    let k1 = det3(&c2s[0], &c1s[1], &c1s[2])
        + det3(&c1s[0], &c2s[1], &c1s[2])
        + det3(&c1s[0], &c1s[1], &c2s[2]);
    let k2 = det3(&c1s[0], &c2s[1], &c2s[2])
        + det3(&c2s[0], &c1s[1], &c2s[2])
        + det3(&c2s[0], &c2s[1], &c1s[2]);
    // Parametrise so that the leading coefficient is the larger of det(D2), det(D1).
    let swap = k0.abs() > k3.abs();
    let (roots, count) = if swap {
        real_cubic_roots(k0, k1, k2, k3) // det(D2 + g D1)
    } else {
        real_cubic_roots(k3, k2, k1, k0) // det(D1 + g D2)
    };
    let mut best: Option<(f64, Matrix3<f64>, Matrix3<f64>)> = None;
    for &g in &roots[..count] {
        let (w1, w2) = if swap { (g, 1.0) } else { (1.0, g) };
        let d0 = d1 * w1 + d2 * w2;
        let Some(eigen) = symmetric_eigen(d0) else {
            continue;
        };
        let mut ev: Vec<f64> = eigen.eigenvalues.iter().map(|e| e.abs()).collect();
        ev.sort_by(|p, q| q.total_cmp(p));
        let quality = ev[2] / ev[1];
        if !quality.is_finite() {
            continue;
        }
        let other = if w1.abs() >= w2.abs() { *d2 } else { *d1 };
        if best.as_ref().is_none_or(|b| quality < b.0) {
            best = Some((quality, d0, other));
        }
    }
    best.map(|(_, d0, other)| (d0, other))
}

/// Real roots of `c3 x³ + c2 x² + c1 x + c0` (degree reduced when leading
/// coefficients vanish), polished by Newton's method.
fn real_cubic_roots(c3: f64, c2: f64, c1: f64, c0: f64) -> ([f64; 3], usize) {
    let mut roots = [0.0; 3];
    let max_coeff = c3.abs().max(c2.abs()).max(c1.abs()).max(c0.abs());
    if !(max_coeff > 0.0 && max_coeff.is_finite()) {
        return (roots, 0);
    }
    let count;
    if c3.abs() <= 1e-14 * max_coeff {
        // Quadratic c2 x² + c1 x + c0.
        if c2.abs() <= 1e-14 * max_coeff {
            if c1 == 0.0 {
                return (roots, 0);
            }
            roots[0] = -c0 / c1;
            return (roots, 1);
        }
        let disc = c1 * c1 - 4.0 * c2 * c0;
        if disc < 0.0 {
            return (roots, 0);
        }
        let q = -0.5 * (c1 + c1.signum() * disc.sqrt());
        roots[0] = q / c2;
        if q == 0.0 {
            return (roots, 1);
        }
        roots[1] = c0 / q;
        return (roots, 2);
    }
    let (a, b, c) = (c2 / c3, c1 / c3, c0 / c3);
    // x = t - a/3: t³ + p t + q = 0.
    let p = b - a * a / 3.0;
    let q = 2.0 * a * a * a / 27.0 - a * b / 3.0 + c;
    let disc = 0.25 * q * q + p * p * p / 27.0;
    if disc > 0.0 {
        let u = (-0.5 * q - q.signum() * disc.sqrt()).cbrt();
        let t = if u != 0.0 { u - p / (3.0 * u) } else { 0.0 };
        roots[0] = t - a / 3.0;
        count = 1;
    } else if p == 0.0 {
        roots[0] = -a / 3.0;
        count = 1;
    } else {
        let r = 2.0 * (-p / 3.0).sqrt();
        let arg = (3.0 * q / (p * r)).clamp(-1.0, 1.0);
        let phi = arg.acos() / 3.0;
        for (k, root) in roots.iter_mut().enumerate() {
            *root = r * (phi - 2.0 * std::f64::consts::PI * k as f64 / 3.0).cos() - a / 3.0;
        }
        count = 3;
    }
    for root in &mut roots[..count] {
        for _ in 0..3 {
            let x = *root;
            let f = ((x + a) * x + b) * x + c;
            let df = (3.0 * x + 2.0 * a) * x + b;
            if df == 0.0 {
                break;
            }
            let next = x - f / df;
            if next.is_finite() {
                *root = next;
            }
        }
    }
    (roots, count)
}

/// Directions `α u + β v` (up to scale) on which the conic `d` vanishes:
/// `A α² + 2B αβ + C β² = 0`. At most two.
fn rays_on_plane(d: &Matrix3<f64>, u: &Vector3<f64>, v: &Vector3<f64>) -> Vec<Vector3<f64>> {
    let aa = u.dot(&(d * u));
    let bb = u.dot(&(d * v));
    let cc = v.dot(&(d * v));
    let scale = aa.abs().max(bb.abs()).max(cc.abs());
    if !(scale > 0.0 && scale.is_finite()) {
        return vec![];
    }
    let mut disc = bb * bb - aa * cc;
    if disc < -1e-12 * scale * scale {
        return vec![];
    }
    disc = disc.max(0.0);
    let q = -(bb + if bb >= 0.0 { 1.0 } else { -1.0 } * disc.sqrt());
    let mut out = Vec::with_capacity(2);
    if aa.abs() >= cc.abs() {
        // t = α/β: A t² + 2B t + C = 0, roots q/A and C/q.
        out.push((q / aa) * u + v);
        if q != 0.0 {
            out.push((cc / q) * u + v);
        }
    } else {
        // r = β/α: C r² + 2B r + A = 0, roots q/C and A/q.
        out.push(u + (q / cc) * v);
        if q != 0.0 {
            out.push(u + (aa / q) * v);
        }
    }
    out
}

/// Positive depths `λ` along `direction` (up to scale) satisfying the three
/// distance equations, polished by Gauss-Newton; `None` if not all positive or
/// the equations do not hold.
fn depths_along(direction: &Vector3<f64>, a: &[f64; 3], b: &[f64; 3]) -> Option<Vector3<f64>> {
    let d = if direction.sum() < 0.0 {
        -direction
    } else {
        *direction
    };
    if !(d.x > 0.0 && d.y > 0.0 && d.z > 0.0) {
        return None;
    }
    const PAIRS: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];
    let form = |l: &Vector3<f64>, k: usize| {
        let (i, j) = PAIRS[k];
        l[i] * l[i] + l[j] * l[j] - 2.0 * b[k] * l[i] * l[j]
    };
    // Scale from the best-conditioned pair.
    let k_best = (0..3)
        .max_by(|&p, &q| form(&d, p).total_cmp(&form(&d, q)))
        .unwrap_or(0);
    let denom = form(&d, k_best);
    if !(denom > 0.0) {
        return None;
    }
    let mut lambda = d * (a[k_best] / denom).sqrt();
    let residuals =
        |l: &Vector3<f64>| Vector3::new(form(l, 0) - a[0], form(l, 1) - a[1], form(l, 2) - a[2]);
    let mut r = residuals(&lambda);
    for _ in 0..DEPTH_REFINEMENT_ITERATIONS {
        let mut jac = Matrix3::zeros();
        for (k, &(i, j)) in PAIRS.iter().enumerate() {
            jac[(k, i)] = 2.0 * lambda[i] - 2.0 * b[k] * lambda[j];
            jac[(k, j)] = 2.0 * lambda[j] - 2.0 * b[k] * lambda[i];
        }
        let Some(step) = jac.lu().solve(&(-r)) else {
            break;
        };
        let next = lambda + step;
        let r_next = residuals(&next);
        if !(r_next.norm_squared() < r.norm_squared()) {
            break;
        }
        lambda = next;
        r = r_next;
    }
    let ok = (0..3).all(|k| r[k].abs() <= MAX_RELATIVE_DISTANCE_ERROR * a[k]);
    (ok && lambda.iter().all(|&l| l > 0.0)).then_some(lambda)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_pose(rng: &mut ChaCha8Rng) -> Rigid3 {
        Rigid3::new(
            UnitQuaternion::from_euler_angles(
                rng.gen_range(-3.1..3.1),
                rng.gen_range(-1.5..1.5),
                rng.gen_range(-3.1..3.1),
            ),
            Vector3::new(
                rng.gen_range(-5.0..5.0),
                rng.gen_range(-5.0..5.0),
                rng.gen_range(-5.0..5.0),
            ),
        )
    }

    /// Points in front of the camera (within ~60° of the axis), in the world.
    fn random_scene(rng: &mut ChaCha8Rng, pose: &Rigid3) -> ([Vector3<f64>; 3], [Vector3<f64>; 3]) {
        let world_from_cam = pose.inverse();
        let mut bearings = [Vector3::zeros(); 3];
        let mut points = [Vector3::zeros(); 3];
        for i in 0..3 {
            let p_cam = Vector3::new(rng.gen_range(-1.5..1.5), rng.gen_range(-1.5..1.5), 1.0)
                * rng.gen_range(1.0..20.0);
            bearings[i] = p_cam.normalize();
            points[i] = world_from_cam.transform_point(&p_cam);
        }
        (bearings, points)
    }

    fn pose_error(a: &Rigid3, b: &Rigid3) -> (f64, f64) {
        (
            a.rotation.angle_to(&b.rotation),
            (a.translation - b.translation).norm(),
        )
    }

    #[test]
    fn true_pose_is_among_solutions() {
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        let mut worst = 0.0f64;
        let mut above_1e9 = 0;
        let trials = 2000;
        for _ in 0..trials {
            let truth = random_pose(&mut rng);
            let (bearings, points) = random_scene(&mut rng, &truth);
            let solutions = p3p(&bearings, &points);
            assert!(solutions.len() <= 4);
            // Rotation (rad) + translation (m, scene within 25 m) error of the best.
            let best = solutions
                .iter()
                .map(|s| {
                    let (r, t) = pose_error(s, &truth);
                    r.max(t)
                })
                .fold(f64::INFINITY, f64::min);
            worst = worst.max(best);
            if best > 1e-9 {
                above_1e9 += 1;
            }
            // Every solution reproduces the bearings.
            for s in &solutions {
                for i in 0..3 {
                    let ray = s.transform_point(&points[i]);
                    assert!(ray.z > 0.0);
                    assert!((ray.normalize() - bearings[i]).norm() < 1e-6);
                }
            }
        }
        // Random triples include ill-conditioned ones (near the danger
        // cylinder, where two solutions merge and the pose is sensitive to the
        // rounding of the input): a few are only good to ~1e-7.
        assert!(worst < 1e-6, "worst {worst}");
        assert!(
            above_1e9 * 100 <= trials,
            "{above_1e9} of {trials} above 1e-9"
        );
    }

    #[test]
    fn degenerate_inputs_give_no_solution() {
        let b = [
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.0, 0.1, 1.0),
        ];
        let collinear = [
            Vector3::new(0.0, 0.0, 5.0),
            Vector3::new(1.0, 0.0, 5.0),
            Vector3::new(2.0, 0.0, 5.0),
        ];
        assert!(p3p(&b, &collinear).is_empty());
        let coincident = [Vector3::new(1.0, 2.0, 3.0); 3];
        assert!(p3p(&b, &coincident).is_empty());
        let mut nan = collinear;
        nan[1].x = f64::NAN;
        assert!(p3p(&b, &nan).is_empty());
        let zero_bearing = [Vector3::zeros(), b[1], b[2]];
        let good = [
            Vector3::new(0.0, 0.0, 5.0),
            Vector3::new(1.0, 0.0, 5.0),
            Vector3::new(0.0, 1.0, 5.0),
        ];
        assert!(p3p(&zero_bearing, &good).is_empty());
        // Identical bearings for distinct points: no finite pose; must not panic.
        let _ = p3p(&[b[0], b[0], b[0]], &good);
    }

    #[test]
    fn hand_made_identity_case() {
        // Camera at the origin looking along +z: the bearings are the points.
        // (A symmetric triple such as (0,0,5), (1,0,5), (0,1,5) makes the
        // identity a double root, only good to sqrt(epsilon).)
        let points = [
            Vector3::new(0.0, 0.0, 5.0),
            Vector3::new(1.0, 0.0, 4.0),
            Vector3::new(0.0, 2.0, 6.0),
        ];
        let solutions = p3p(&points, &points);
        assert!(solutions
            .iter()
            .any(|s| s.rotation.angle() < 1e-12 && s.translation.norm() < 1e-12));
    }

    #[test]
    fn cubic_roots() {
        // (x - 1)(x - 2)(x + 3) = x³ - 7x + 6.
        let (r, n) = real_cubic_roots(1.0, 0.0, -7.0, 6.0);
        let mut r = r[..n].to_vec();
        r.sort_by(f64::total_cmp);
        assert_eq!(n, 3);
        for (got, want) in r.iter().zip([-3.0, 1.0, 2.0]) {
            assert!((got - want).abs() < 1e-14);
        }
        // x³ + x + 1: one real root near -0.6823278.
        let (r, n) = real_cubic_roots(2.0, 0.0, 2.0, 2.0);
        assert_eq!(n, 1);
        assert!((r[0] + 0.682_327_803_828_019_3).abs() < 1e-14);
        // Degree drops: 2x - 4.
        let (r, n) = real_cubic_roots(0.0, 0.0, 2.0, -4.0);
        assert_eq!((n, r[0]), (1, 2.0));
    }
}
