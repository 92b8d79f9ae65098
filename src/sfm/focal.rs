//! A first focal length for a camera whose database value is a guess.
//!
//! COLMAP's extractor, finding no focal length, takes 1.2 times the larger
//! image side; its matcher then verifies such pairs with a fundamental matrix
//! (config 3, "uncalibrated"), stored with the pair. With the principal point
//! at its guess and both images sharing the intrinsics `K = [f 0 cx; 0 f cy;
//! 0 0 1]`, `E = K^T F K` is an essential matrix, with two equal singular
//! values, only at the true `f` (Mendonça and Cipolla's criterion). The
//! estimate is the `f` of a log-spaced grid (and a parabola through its
//! neighbours) that makes the pairs' matrices most nearly essential: the sum
//! over pairs of `(s1 - s2) / (s1 + s2)`. A pair seen in pure forward motion
//! holds no information on `f` (its cost is flat) and does not move the sum.
use nalgebra::{Matrix3, Vector2, Vector3};

use super::geometry::reprojection_error_sq;
use crate::scene::{Camera, Rigid3};

/// The grid spans `guess / GRID_SPAN .. guess * GRID_SPAN`.
const GRID_SPAN: f64 = 4.0;
const GRID_STEPS: usize = 561;
/// At most this many pairs enter the sum (the ones with most inliers).
pub const MAX_PAIRS: usize = 500;

/// What the fundamental matrices say about a camera's focal length.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FocalEstimate {
    pub focal_px: f64,
    pub num_pairs: usize,
    /// Mean cost per pair at the estimate and at the guess (0: essential).
    pub cost: f64,
    pub cost_at_guess: f64,
}

/// Mean of `(s1 - s2) / (s1 + s2)` of `K^T F K` over the pairs.
fn cost(fundamentals: &[Matrix3<f64>], principal: &Vector2<f64>, f: f64) -> f64 {
    let k = Matrix3::new(f, 0.0, principal.x, 0.0, f, principal.y, 0.0, 0.0, 1.0);
    let sum: f64 = fundamentals
        .iter()
        .map(|fm| {
            let mut s = (k.transpose() * fm * k).singular_values();
            s.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
            if s[0] + s[1] > 0.0 {
                (s[0] - s[1]) / (s[0] + s[1])
            } else {
                1.0
            }
        })
        .sum();
    sum / fundamentals.len().max(1) as f64
}

/// The focal length (pixels) that makes `fundamentals` (row-major, pixel
/// coordinates, pairs of images with the same intrinsics) most nearly
/// essential, searched within 1/4 to 4 times `guess`; `None` with fewer than
/// `min_pairs` pairs or when the best value lies on the edge of the search.
pub fn focal_from_fundamentals(
    fundamentals: &[[f64; 9]],
    principal: &Vector2<f64>,
    guess: f64,
    min_pairs: usize,
) -> Option<FocalEstimate> {
    if fundamentals.len() < min_pairs.max(1) || !(guess.is_finite() && guess > 0.0) {
        return None;
    }
    let mats: Vec<Matrix3<f64>> = fundamentals
        .iter()
        .map(|f| {
            let m = Matrix3::from_row_slice(f);
            m / m.norm()
        })
        .collect();
    let at = |i: f64| guess * GRID_SPAN.powf(2.0 * i / (GRID_STEPS - 1) as f64 - 1.0);
    let costs: Vec<f64> = (0..GRID_STEPS)
        .map(|i| cost(&mats, principal, at(i as f64)))
        .collect();
    let best = (0..GRID_STEPS).min_by(|&a, &b| costs[a].total_cmp(&costs[b]).then(a.cmp(&b)))?;
    if best == 0 || best == GRID_STEPS - 1 {
        return None;
    }
    // Parabola through the best grid point and its neighbours (in grid index).
    let (l, c, r) = (costs[best - 1], costs[best], costs[best + 1]);
    let curvature = l - 2.0 * c + r;
    let offset = if curvature > 0.0 {
        (0.5 * (l - r) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    let focal_px = at(best as f64 + offset);
    Some(FocalEstimate {
        focal_px,
        num_pairs: mats.len(),
        cost: cost(&mats, principal, focal_px),
        cost_at_guess: cost(&mats, principal, guess),
    })
}

/// Truncation of the focal-length sweeps' score, pixels.
pub const SWEEP_TRUNCATION_PX: f64 = 2.0;

/// `camera` with every focal length parameter set to `f`.
pub fn with_focal(camera: &Camera, f: f64) -> Camera {
    let mut c = camera.clone();
    for &k in c.model.focal_idxs() {
        c.params[k] = f;
    }
    c
}

/// Mean over the correspondences of `min(e^2, t^2) / t^2`, `e` the
/// reprojection error at `cam_from_world` and `t` [`SWEEP_TRUNCATION_PX`]
/// (a point behind the camera counts 1): 0 when every correspondence is
/// exact, 1 when none is within `t`, and 1 for no correspondences.
pub fn truncated_reprojection_score(
    camera: &Camera,
    cam_from_world: &Rigid3,
    pixels: &[Vector2<f64>],
    points_in_world: &[Vector3<f64>],
) -> f64 {
    if pixels.is_empty() {
        return 1.0;
    }
    let t_sq = SWEEP_TRUNCATION_PX * SWEEP_TRUNCATION_PX;
    pixels
        .iter()
        .zip(points_in_world)
        .map(|(px, x)| {
            reprojection_error_sq(camera, cam_from_world, x, px).map_or(1.0, |e| e.min(t_sq) / t_sq)
        })
        .sum::<f64>()
        / pixels.len() as f64
}

/// A focal length (pixels) minimising `score` (0 best, 1 worst): a log grid
/// from a third to three times `centre` in 8 % steps, then 1 % steps within
/// one coarse step of the best. Returns (focal length, its score), `None`
/// when the best coarse value lies on the edge of the grid or scores 1.
pub fn sweep_focal(centre: f64, mut score: impl FnMut(f64) -> f64) -> Option<(f64, f64)> {
    if !(centre.is_finite() && centre > 0.0) {
        return None;
    }
    let coarse_steps = (9f64.ln() / 1.08f64.ln()).ceil() as i32;
    let coarse: Vec<(f64, f64)> = (0..=coarse_steps)
        .map(|i| {
            let f = centre / 3.0 * 1.08f64.powi(i);
            let s = score(f);
            log::debug!("focal sweep: {f:.1} px -> {s:.4}");
            (f, s)
        })
        .collect();
    let best = (0..coarse.len()).min_by(|&a, &b| coarse[a].1.total_cmp(&coarse[b].1))?;
    if best == 0 || best == coarse.len() - 1 || coarse[best].1 >= 1.0 {
        return None;
    }
    let (f_best, s_best) = coarse[best];
    (-8..=8)
        .map(|i| {
            let f = f_best * 1.01f64.powi(i);
            (f, if i == 0 { s_best } else { score(f) })
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraId, CameraModel};
    use nalgebra::Rotation3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// `F = K^-T [t]x R K^-1` of two views with intrinsics K.
    fn fundamental(f: f64, c: &Vector2<f64>, r: &Rotation3<f64>, t: &Vector3<f64>) -> [f64; 9] {
        let k = Matrix3::new(f, 0.0, c.x, 0.0, f, c.y, 0.0, 0.0, 1.0);
        let k_inv = k.try_inverse().unwrap();
        let m = k_inv.transpose() * t.cross_matrix() * r.matrix() * k_inv;
        let mut out = [0.0; 9];
        for (i, v) in out.iter_mut().enumerate() {
            *v = m[(i / 3, i % 3)];
        }
        out
    }

    fn project(f: f64, c: &Vector2<f64>, x: &Vector3<f64>) -> Option<Vector2<f64>> {
        (x.z > 0.1).then(|| Vector2::new(f * x.x / x.z + c.x, f * x.y / x.z + c.y))
    }

    /// Hartley's normalised eight-point algorithm with the rank-2 step
    /// (`x2^T F x1 = 0`), row-major.
    fn eight_point(matches: &[(Vector2<f64>, Vector2<f64>)]) -> [f64; 9] {
        let normaliser = |pts: Vec<Vector2<f64>>| {
            let mean = pts.iter().sum::<Vector2<f64>>() / pts.len() as f64;
            let spread = pts.iter().map(|p| (p - mean).norm()).sum::<f64>() / pts.len() as f64;
            let s = std::f64::consts::SQRT_2 / spread;
            Matrix3::new(s, 0.0, -s * mean.x, 0.0, s, -s * mean.y, 0.0, 0.0, 1.0)
        };
        let t1 = normaliser(matches.iter().map(|m| m.0).collect());
        let t2 = normaliser(matches.iter().map(|m| m.1).collect());
        let rows: Vec<f64> = matches
            .iter()
            .flat_map(|(a, b)| {
                let p = t1 * Vector3::new(a.x, a.y, 1.0);
                let q = t2 * Vector3::new(b.x, b.y, 1.0);
                [
                    q.x * p.x,
                    q.x * p.y,
                    q.x,
                    q.y * p.x,
                    q.y * p.y,
                    q.y,
                    p.x,
                    p.y,
                    1.0,
                ]
            })
            .collect();
        let a = nalgebra::DMatrix::from_row_slice(matches.len(), 9, &rows);
        let svd = (a.transpose() * &a).svd(true, true);
        let (k, _) = svd.singular_values.argmin();
        let v = svd.v_t.unwrap().row(k).transpose();
        let f = Matrix3::from_row_slice(v.as_slice());
        let mut f_svd = f.svd(true, true);
        f_svd.singular_values[2] = 0.0;
        let f = t2.transpose() * f_svd.recompose().unwrap() * t1;
        let mut out = [0.0; 9];
        for (i, x) in out.iter_mut().enumerate() {
            *x = f[(i / 3, i % 3)];
        }
        out
    }

    #[test]
    fn recovers_the_focal_length_of_exact_and_noisy_pairs() {
        let c = Vector2::new(320.0, 240.0);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let pairs: Vec<[f64; 9]> = (0..40)
            .map(|_| {
                let r = Rotation3::from_euler_angles(
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-0.6..0.6),
                    rng.gen_range(-0.2..0.2),
                );
                let t = Vector3::new(
                    rng.gen_range(-1.0..1.0),
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-1.0..1.0),
                );
                fundamental(512.0, &c, &r, &t)
            })
            .collect();
        // From COLMAP's guess for 640 x 480 (768 px) and from below.
        for guess in [768.0, 300.0] {
            let e = focal_from_fundamentals(&pairs, &c, guess, 8).unwrap();
            assert!((e.focal_px / 512.0 - 1.0).abs() < 1e-3, "{e:?}");
            assert!(e.cost < 1e-4 && e.cost_at_guess > 0.05, "{e:?}");
            assert_eq!(e.num_pairs, 40);
        }
        // F from 60 correspondences with 0.5 px of noise (normalised eight-point
        // algorithm), as a matcher estimates it: still within 2 %.
        let noisy: Vec<[f64; 9]> = (0..40)
            .map(|_| {
                let r = Rotation3::from_euler_angles(
                    rng.gen_range(-0.3..0.3),
                    rng.gen_range(-0.6..0.6),
                    rng.gen_range(-0.2..0.2),
                );
                let t = Vector3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-0.3..0.3), 0.5);
                let matches: Vec<(Vector2<f64>, Vector2<f64>)> = (0..60)
                    .filter_map(|_| {
                        let x = Vector3::new(
                            rng.gen_range(-3.0..3.0),
                            rng.gen_range(-2.0..2.0),
                            rng.gen_range(4.0..12.0),
                        );
                        let a = project(512.0, &c, &x)?;
                        let b = project(512.0, &c, &(r * x + t))?;
                        let mut noise =
                            || Vector2::new(rng.gen_range(-0.5..0.5), rng.gen_range(-0.5..0.5));
                        Some((a + noise(), b + noise()))
                    })
                    .collect();
                eight_point(&matches)
            })
            .collect();
        let e = focal_from_fundamentals(&noisy, &c, 768.0, 8).unwrap();
        eprintln!("0.5 px noise: {e:?}");
        assert!((e.focal_px / 512.0 - 1.0).abs() < 0.02, "{e:?}");
        // Too few pairs, and a focal length outside the search: no estimate.
        assert_eq!(focal_from_fundamentals(&pairs[..5], &c, 768.0, 8), None);
        let far: Vec<[f64; 9]> = pairs.iter().take(10).copied().collect();
        assert_eq!(focal_from_fundamentals(&far, &c, 5000.0, 8), None);
    }

    #[test]
    fn truncated_score_by_hand() {
        let camera = Camera {
            id: CameraId(1),
            model: CameraModel::from_name("SIMPLE_PINHOLE").unwrap(),
            width: 100,
            height: 100,
            params: vec![100.0, 50.0, 50.0],
        };
        let pose = Rigid3::identity();
        // (0.1, 0, 1) projects to (60, 50); errors 0, 1 and 3 px (2 px
        // truncation: 0, 1/4 and 1); a point behind the camera counts 1.
        let points = [
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.1, 0.0, 1.0),
            Vector3::new(0.1, 0.0, -1.0),
        ];
        let pixels = [
            Vector2::new(60.0, 50.0),
            Vector2::new(60.0, 51.0),
            Vector2::new(57.0, 50.0),
            Vector2::new(60.0, 50.0),
        ];
        let score = truncated_reprojection_score(&camera, &pose, &pixels, &points);
        assert!(
            (score - (0.0 + 0.25 + 1.0 + 1.0) / 4.0).abs() < 1e-12,
            "{score}"
        );
        assert_eq!(truncated_reprojection_score(&camera, &pose, &[], &[]), 1.0);
        assert_eq!(with_focal(&camera, 80.0).params, [80.0, 50.0, 50.0]);
    }

    #[test]
    fn sweep_finds_the_minimum_and_refuses_the_edge() {
        // A V-shaped score with its minimum at 500 px, searched around 768.
        let v = |best: f64| move |f: f64| ((f / best).ln().abs() * 3.0).min(1.0);
        let mut calls = 0;
        let (f, score) = sweep_focal(768.0, |f| {
            calls += 1;
            v(500.0)(f)
        })
        .unwrap();
        assert!((f / 500.0 - 1.0).abs() < 0.005, "{f}");
        assert!(score < 0.015, "{score}");
        assert_eq!(calls, 30 + 16, "coarse grid and fine steps");
        // Minima outside a third to three times the centre: no estimate.
        assert_eq!(sweep_focal(768.0, v(200.0)), None);
        assert_eq!(sweep_focal(768.0, v(2500.0)), None);
        // Nothing placed anywhere: no estimate.
        assert_eq!(sweep_focal(768.0, |_| 1.0), None);
        assert_eq!(sweep_focal(f64::NAN, v(500.0)), None);
    }
}
