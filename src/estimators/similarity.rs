//! Similarity transforms (Sim3) between point sets: Umeyama's closed form
//! (Umeyama 1991, "Least-squares estimation of transformation parameters between
//! two point patterns") and a RANSAC variant for sets with outliers.
//!
//! For pairs `(a_i, b_i)` the least-squares `b ≈ s R a + t` is: centroids `μa`, `μb`;
//! variance `σa² = mean |a_i - μa|²`; covariance `Σ = mean (b_i - μb)(a_i - μa)ᵀ =
//! U D Vᵀ`; `S = diag(1, 1, sign(det U det V))`; `R = U S Vᵀ`, `s = tr(D S) / σa²`,
//! `t = μb - s R μa`. Without scale (Kabsch), `s = 1`.
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use rand_chacha::ChaCha8Rng;

use super::ransac::{self, Estimator, RansacError, RansacOptions, RansacReport};
use crate::scene::Rigid3;

/// A similarity `b_from_a`: `x_b = scale * R x_a + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sim3 {
    pub scale: f64,
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Sim3 {
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
        }
    }

    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * p) + self.translation
    }

    /// `a_from_b` for a `b_from_a`.
    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        let scale = 1.0 / self.scale;
        Self {
            scale,
            rotation,
            translation: -(scale * (rotation * self.translation)),
        }
    }

    /// `c_from_a` for `self = c_from_b` and `b_from_a`.
    pub fn compose(&self, b_from_a: &Sim3) -> Self {
        Self {
            scale: self.scale * b_from_a.scale,
            rotation: self.rotation * b_from_a.rotation,
            translation: self.transform_point(&b_from_a.translation),
        }
    }

    /// A camera's `cam_from_a` as `cam_from_b` (`self = b_from_a`): the same
    /// view of the moved scene. For `x_b = s Q x_a + τ`: `R' = R Qᵀ`,
    /// `t' = s t - R Qᵀ τ` (the camera frame scaled by `s`, which projection
    /// ignores).
    pub fn transform_pose(&self, cam_from_a: &Rigid3) -> Rigid3 {
        let rotation = cam_from_a.rotation * self.rotation.inverse();
        Rigid3::new(
            rotation,
            self.scale * cam_from_a.translation - rotation * self.translation,
        )
    }

    /// The rigid part (rotation and translation; the scale is dropped).
    pub fn rigid(&self) -> Rigid3 {
        Rigid3::new(self.rotation, self.translation)
    }
}

/// Relative size below which the second singular value of the covariance makes
/// the rotation undetermined (collinear or coincident points).
const DEGENERACY_RATIO: f64 = 1e-10;

/// Least-squares similarity `b_from_a` with `b_i ≈ s R a_i + t` over `pairs` of
/// `(a_i, b_i)` (with `estimate_scale == false`, `s = 1`: a rigid fit).
///
/// `None` with fewer than 3 pairs, non-finite coordinates, or when the points
/// are collinear or coincident (rotation undetermined).
pub fn umeyama(pairs: &[(Vector3<f64>, Vector3<f64>)], estimate_scale: bool) -> Option<Sim3> {
    if pairs.len() < 3 {
        return None;
    }
    let n = pairs.len() as f64;
    let (sum_a, sum_b) = pairs
        .iter()
        .fold((Vector3::zeros(), Vector3::zeros()), |(sa, sb), (a, b)| {
            (sa + a, sb + b)
        });
    let (mean_a, mean_b) = (sum_a / n, sum_b / n);
    let mut cov = Matrix3::zeros();
    let mut var_a = 0.0;
    for (a, b) in pairs {
        let (da, db) = (a - mean_a, b - mean_b);
        cov += db * da.transpose();
        var_a += da.norm_squared();
    }
    cov /= n;
    var_a /= n;
    if !(cov.iter().all(|x| x.is_finite()) && var_a.is_finite() && var_a > 0.0) {
        return None;
    }
    let svd = cov.try_svd(true, true, f64::EPSILON, 1000)?;
    let (u, v_t) = (svd.u?, svd.v_t?);
    let d = svd.singular_values; // sorted in decreasing order
    if d[1] <= DEGENERACY_RATIO * d[0] || d[0] <= 0.0 {
        return None;
    }
    let mut s_diag = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s_diag[2] = -1.0;
    }
    let r = u * Matrix3::from_diagonal(&s_diag) * v_t;
    let scale = if estimate_scale {
        d.component_mul(&s_diag).sum() / var_a
    } else {
        1.0
    };
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let translation = mean_b - scale * (rotation * mean_a);
    Some(Sim3 {
        scale,
        rotation,
        translation,
    })
}

/// Minimal-sample Sim3 estimator for [`ransac::run`]: residual = distance (in
/// the units of `b`) between `b_i` and the transformed `a_i`.
pub struct Sim3Estimator {
    pub estimate_scale: bool,
}

impl Estimator for Sim3Estimator {
    type Datum = (Vector3<f64>, Vector3<f64>);
    type Model = Sim3;
    const MIN_SAMPLES: usize = 3;

    fn estimate(&self, sample: &[Self::Datum]) -> Vec<Sim3> {
        umeyama(sample, self.estimate_scale).into_iter().collect()
    }

    fn residual_sq(&self, model: &Sim3, (a, b): &Self::Datum) -> f64 {
        (model.transform_point(a) - b).norm_squared()
    }

    fn refine(&self, _model: &Sim3, inliers: &[Self::Datum]) -> Option<Sim3> {
        umeyama(inliers, self.estimate_scale)
    }
}

/// Robust Sim3 (`b_from_a`) over `pairs` of `(a_i, b_i)` with outliers: LO-RANSAC
/// over 3-point Umeyama fits, residual `|b_i - (s R a_i + t)|` in the units of `b`
/// against `options.max_error` (the default of 4.0 suits pixels, not metres: set
/// it). The reported model is the Umeyama fit on the final inliers.
pub fn estimate_sim3_ransac(
    pairs: &[(Vector3<f64>, Vector3<f64>)],
    estimate_scale: bool,
    options: &RansacOptions,
    rng: &mut ChaCha8Rng,
) -> Result<RansacReport<Sim3>, RansacError> {
    let estimator = Sim3Estimator { estimate_scale };
    ransac::run(&estimator, pairs, &[], options, rng)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_sim3(rng: &mut ChaCha8Rng) -> Sim3 {
        Sim3 {
            scale: rng.gen_range(0.1..10.0),
            rotation: UnitQuaternion::from_euler_angles(
                rng.gen_range(-3.0..3.0),
                rng.gen_range(-1.5..1.5),
                rng.gen_range(-3.0..3.0),
            ),
            translation: Vector3::new(
                rng.gen_range(-100.0..100.0),
                rng.gen_range(-100.0..100.0),
                rng.gen_range(-100.0..100.0),
            ),
        }
    }

    #[test]
    fn recovers_known_sim3_exactly() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..50 {
            let truth = random_sim3(&mut rng);
            let n = rng.gen_range(3..30);
            let pairs: Vec<_> = (0..n)
                .map(|_| {
                    let a = Vector3::new(
                        rng.gen_range(-10.0..10.0),
                        rng.gen_range(-10.0..10.0),
                        rng.gen_range(-10.0..10.0),
                    );
                    (a, truth.transform_point(&a))
                })
                .collect();
            let est = umeyama(&pairs, true).unwrap();
            assert!((est.scale - truth.scale).abs() < 1e-9 * truth.scale);
            assert!(est.rotation.angle_to(&truth.rotation) < 1e-9);
            assert!((est.translation - truth.translation).norm() < 1e-8);
            // The inverse maps back.
            let inv = est.inverse();
            assert!((inv.transform_point(&pairs[0].1) - pairs[0].0).norm() < 1e-9);
        }
    }

    #[test]
    fn rigid_fit_and_reflection_case() {
        // Coplanar points (rank-2 covariance): the determinant correction must
        // give a rotation, not a reflection.
        let rotation = UnitQuaternion::from_euler_angles(0.3, -0.2, 2.0);
        let truth = Sim3 {
            scale: 1.0,
            rotation,
            translation: Vector3::new(1.0, 2.0, 3.0),
        };
        let a = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 2.0, 0.0),
            Vector3::new(3.0, 1.0, 0.0),
        ];
        let pairs: Vec<_> = a.iter().map(|a| (*a, truth.transform_point(a))).collect();
        let est = umeyama(&pairs, false).unwrap();
        assert_eq!(est.scale, 1.0);
        assert!(est.rotation.angle_to(&rotation) < 1e-12);
        assert!(est.rigid().rotation_matrix().determinant() > 0.0);
    }

    #[test]
    fn degenerate_inputs() {
        let line: Vec<_> = (0..5)
            .map(|i| {
                let a = Vector3::new(i as f64, 2.0 * i as f64, 0.0);
                (a, a)
            })
            .collect();
        assert!(umeyama(&line, true).is_none());
        assert!(umeyama(&line[..2], true).is_none());
        let same = vec![(Vector3::new(1.0, 1.0, 1.0), Vector3::zeros()); 5];
        assert!(umeyama(&same, true).is_none());
        let nan = vec![(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::zeros()); 5];
        assert!(umeyama(&nan, true).is_none());
    }

    #[test]
    fn ransac_with_outliers() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let truth = random_sim3(&mut rng);
        let mut pairs = Vec::new();
        for i in 0..100 {
            let a = Vector3::new(
                rng.gen_range(-10.0..10.0),
                rng.gen_range(-10.0..10.0),
                rng.gen_range(-10.0..10.0),
            );
            let b = if i % 2 == 0 {
                truth.transform_point(&a) + Vector3::new(500.0, rng.gen_range(0.0..100.0), 0.0)
            } else {
                truth.transform_point(&a)
            };
            pairs.push((a, b));
        }
        let options = RansacOptions {
            max_error: 0.01,
            ..Default::default()
        };
        let report = estimate_sim3_ransac(&pairs, true, &options, &mut rng).unwrap();
        assert_eq!(report.num_inliers, 50);
        for (i, &inlier) in report.inlier_mask.iter().enumerate() {
            assert_eq!(inlier, i % 2 == 1);
        }
        assert!((report.model.scale - truth.scale).abs() < 1e-9 * truth.scale);
        assert!(report.model.rotation.angle_to(&truth.rotation) < 1e-9);
    }

    #[test]
    fn compose_applies_right_then_left() {
        let a = Sim3 {
            scale: 0.9,
            rotation: UnitQuaternion::from_euler_angles(0.3, 0.0, -0.1),
            translation: Vector3::new(1.0, 2.0, 3.0),
        };
        let b = Sim3 {
            scale: 1.1,
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.5, 0.2),
            translation: Vector3::new(-2.0, 0.0, 1.0),
        };
        let x = Vector3::new(0.3, -0.7, 4.0);
        let ab = a.compose(&b);
        assert!(
            (ab.transform_point(&x) - a.transform_point(&b.transform_point(&x))).norm() < 1e-12
        );
    }
}
