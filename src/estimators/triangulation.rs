//! Triangulation of a 3D point from its observations in posed images.
//!
//! * [`triangulate_dlt`]: linear triangulation from two or more views. Each view
//!   with `cam_from_world = [R | t]` and viewing ray `d` (camera frame) gives the
//!   constraint `d × (R X + t) = 0`, three rows (rank 2) of a homogeneous system
//!   `A [X; 1] = 0`, solved by the right singular vector of the smallest singular
//!   value. The world frame is first centred on the mean camera centre and scaled
//!   by the centres' mean distance to it (Hartley-style conditioning).
//! * [`triangulate_point`]: DLT over all views, then the checks of incremental
//!   SfM: positive depth in every view (cheirality), reprojection error in pixels
//!   through each view's camera model, and triangulation angle (the largest angle
//!   at the point between the rays of any two views).
//! * [`triangulate_track_ransac`]: the same for tracks with outliers: RANSAC over
//!   view pairs (each pair's point must be in front of both views and have the
//!   minimum angle), inliers by reprojection error, DLT on the inliers as the
//!   local optimisation.
use nalgebra::{DMatrix, Vector2, Vector3};
use rand_chacha::ChaCha8Rng;

use super::ransac::{self, Estimator, RansacError, RansacOptions};
use super::InvalidOptions;
use crate::scene::{Camera, Rigid3};

/// One observation of a point: the image's camera and pose, and the keypoint.
#[derive(Clone, Copy, Debug)]
pub struct PointObservation<'a> {
    pub camera: &'a Camera,
    pub cam_from_world: Rigid3,
    /// Keypoint, pixels (COLMAP convention: the top-left pixel's centre is (0.5, 0.5)).
    pub pixel: Vector2<f64>,
    /// Viewing ray in the camera frame, `camera.unproject(pixel)` (any positive scale).
    pub ray_in_cam: Vector3<f64>,
}

impl<'a> PointObservation<'a> {
    /// Unprojects `pixel`; `None` when it has no viewing ray (outside the
    /// model's domain, or not finite).
    pub fn new(camera: &'a Camera, cam_from_world: Rigid3, pixel: Vector2<f64>) -> Option<Self> {
        let ray_in_cam = camera.unproject(&pixel)?;
        ray_in_cam.iter().all(|x| x.is_finite()).then_some(Self {
            camera,
            cam_from_world,
            pixel,
            ray_in_cam,
        })
    }

    /// Depth (z in the camera frame, metres) of a world point.
    pub fn depth_m(&self, point_in_world: &Vector3<f64>) -> f64 {
        self.cam_from_world.transform_point(point_in_world).z
    }

    /// Reprojection error (px) of a world point; `None` behind the camera.
    pub fn reprojection_error_px(&self, point_in_world: &Vector3<f64>) -> Option<f64> {
        let point_in_cam = self.cam_from_world.transform_point(point_in_world);
        self.camera
            .project(&point_in_cam)
            .map(|p| (p - self.pixel).norm())
    }
}

/// Options of [`triangulate_point`] and [`triangulate_track_ransac`].
#[derive(Clone, Debug, PartialEq)]
pub struct TriangulationOptions {
    /// Largest reprojection error (px) of an accepted observation; also the
    /// RANSAC inlier threshold. Default: 4.0 (COLMAP's `filter_max_reproj_error`).
    pub max_reprojection_error_px: f64,
    /// Smallest triangulation angle (degrees): the largest angle between the rays
    /// of two accepted views, at the point. Default: 1.5 (COLMAP's `tri_min_angle`).
    pub min_angle_deg: f64,
    /// RANSAC confidence. Default: 0.9999.
    pub ransac_confidence: f64,
    /// RANSAC iterations at most. Default: 10000.
    pub ransac_max_iterations: usize,
}

impl Default for TriangulationOptions {
    fn default() -> Self {
        Self {
            max_reprojection_error_px: 4.0,
            min_angle_deg: 1.5,
            ransac_confidence: 0.9999,
            ransac_max_iterations: 10000,
        }
    }
}

impl TriangulationOptions {
    pub fn validate(&self) -> Result<(), InvalidOptions> {
        if !(self.min_angle_deg >= 0.0 && self.min_angle_deg < 180.0) {
            return Err(InvalidOptions::new(
                "min_angle_deg",
                format!("must be in [0, 180), got {}", self.min_angle_deg),
            ));
        }
        self.ransac_options().validate()
    }

    fn ransac_options(&self) -> RansacOptions {
        RansacOptions {
            max_error: self.max_reprojection_error_px,
            confidence: self.ransac_confidence,
            min_iterations: 0,
            max_iterations: self.ransac_max_iterations,
            local_optimization: true,
            max_local_iterations: 10,
        }
    }
}

/// A triangulated point.
#[derive(Clone, Debug, PartialEq)]
pub struct TriangulatedPoint {
    pub point_in_world: Vector3<f64>,
    /// Per observation: used (in front, reprojection error within the threshold).
    /// All true from [`triangulate_point`].
    pub inlier_mask: Vec<bool>,
    pub num_inliers: usize,
    /// Largest triangulation angle over pairs of inlier views (degrees).
    pub max_angle_deg: f64,
    /// Mean reprojection error over the inliers (px).
    pub mean_reprojection_error_px: f64,
}

/// Why a point was not triangulated.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TriangulationFailure {
    #[error(transparent)]
    InvalidOptions(#[from] InvalidOptions),
    #[error("triangulation needs at least 2 observations, got {got}")]
    TooFewObservations { got: usize },
    #[error("degenerate triangulation (parallel rays, point at infinity or non-finite input)")]
    Degenerate,
    #[error("point behind the camera of observation {observation}")]
    NegativeDepth { observation: usize },
    #[error("reprojection error {error_px:.2} px in observation {observation}")]
    LargeReprojectionError { observation: usize, error_px: f64 },
    #[error("triangulation angle {angle_deg:.3} deg below the minimum")]
    SmallAngle { angle_deg: f64 },
    #[error("no pair of observations gave a point with 2 inliers")]
    RansacFailed,
}

/// Angle (degrees) at `point` between the rays from `center1` and `center2`
/// (camera centres in the world frame). 0 when the point coincides with a centre.
pub fn triangulation_angle_deg(
    center1: &Vector3<f64>,
    center2: &Vector3<f64>,
    point: &Vector3<f64>,
) -> f64 {
    let (a, b) = (point - center1, point - center2);
    a.cross(&b).norm().atan2(a.dot(&b)).to_degrees()
}

/// Largest angle (degrees) at `point` between the rays of any two of `centers`.
fn max_pairwise_angle_deg(centers: &[Vector3<f64>], point: &Vector3<f64>) -> f64 {
    let dirs: Vec<Vector3<f64>> = centers
        .iter()
        .filter_map(|c| (point - c).try_normalize(0.0))
        .collect();
    let mut max_rad: f64 = 0.0;
    for (i, a) in dirs.iter().enumerate() {
        for b in &dirs[i + 1..] {
            // For unit vectors, 2 atan2(|a - b|, |a + b|) is precise at all angles.
            max_rad = max_rad.max(2.0 * (a - b).norm().atan2((a + b).norm()));
        }
    }
    max_rad.to_degrees()
}

/// Linear (DLT) triangulation from `(cam_from_world, ray_in_cam)` pairs, two or
/// more. `None` for fewer than 2 views, non-finite input, or a solution at
/// infinity (parallel rays). No checks of depth or angle: see
/// [`triangulate_point`].
pub fn triangulate_dlt(views: &[(Rigid3, Vector3<f64>)]) -> Option<Vector3<f64>> {
    if views.len() < 2 {
        return None;
    }
    let centers: Vec<Vector3<f64>> = views.iter().map(|(p, _)| p.camera_center()).collect();
    let origin = centers.iter().sum::<Vector3<f64>>() / centers.len() as f64;
    let mut scale = centers.iter().map(|c| (c - origin).norm()).sum::<f64>() / centers.len() as f64;
    if !(scale.is_finite() && scale > 0.0) {
        scale = 1.0;
    }
    let mut a = DMatrix::<f64>::zeros(3 * views.len(), 4);
    for (k, (pose, ray)) in views.iter().enumerate() {
        let d = ray.try_normalize(0.0)?;
        let r = pose.rotation_matrix();
        // World X = origin + scale X': R X + t = scale (R X' + (R origin + t) / scale).
        let t = (r * origin + pose.translation) / scale;
        let cross = d.cross_matrix();
        let block_r = cross * r;
        let block_t = cross * t;
        for row in 0..3 {
            for col in 0..3 {
                a[(3 * k + row, col)] = block_r[(row, col)];
            }
            a[(3 * k + row, 3)] = block_t[row];
        }
    }
    if !a.iter().all(|x| x.is_finite()) {
        return None;
    }
    let svd = a.try_svd(false, true, f64::EPSILON, 1000)?;
    let v_t = svd.v_t?;
    // Singular values are sorted decreasingly: the last row of Vᵀ is the null vector.
    let h = v_t.row(3);
    let xyz = Vector3::new(h[0], h[1], h[2]);
    let w = h[3];
    if !(w.abs() > 1e-12 * xyz.norm()) {
        return None;
    }
    let point = origin + scale * (xyz / w);
    point.iter().all(|x| x.is_finite()).then_some(point)
}

fn dlt_of(observations: &[PointObservation]) -> Option<Vector3<f64>> {
    let views: Vec<(Rigid3, Vector3<f64>)> = observations
        .iter()
        .map(|o| (o.cam_from_world, o.ray_in_cam))
        .collect();
    triangulate_dlt(&views)
}

/// Triangulates from all `observations` and checks the result: positive depth
/// in every view, reprojection error <= `max_reprojection_error_px` in every
/// view, largest pairwise triangulation angle >= `min_angle_deg`.
pub fn triangulate_point(
    observations: &[PointObservation],
    options: &TriangulationOptions,
) -> Result<TriangulatedPoint, TriangulationFailure> {
    options.validate()?;
    if observations.len() < 2 {
        return Err(TriangulationFailure::TooFewObservations {
            got: observations.len(),
        });
    }
    let point = dlt_of(observations).ok_or(TriangulationFailure::Degenerate)?;
    let mut error_sum_px = 0.0;
    for (i, o) in observations.iter().enumerate() {
        if !(o.depth_m(&point) > 0.0) {
            return Err(TriangulationFailure::NegativeDepth { observation: i });
        }
        let error_px = o.reprojection_error_px(&point).unwrap_or(f64::INFINITY);
        if !(error_px <= options.max_reprojection_error_px) {
            return Err(TriangulationFailure::LargeReprojectionError {
                observation: i,
                error_px,
            });
        }
        error_sum_px += error_px;
    }
    let centers: Vec<Vector3<f64>> = observations
        .iter()
        .map(|o| o.cam_from_world.camera_center())
        .collect();
    let angle_deg = max_pairwise_angle_deg(&centers, &point);
    if !(angle_deg >= options.min_angle_deg) {
        return Err(TriangulationFailure::SmallAngle { angle_deg });
    }
    Ok(TriangulatedPoint {
        point_in_world: point,
        inlier_mask: vec![true; observations.len()],
        num_inliers: observations.len(),
        max_angle_deg: angle_deg,
        mean_reprojection_error_px: error_sum_px / observations.len() as f64,
    })
}

/// Two-view DLT models with depth and angle checks; residual = reprojection
/// error (px).
struct PairEstimator<'a> {
    min_angle_deg: f64,
    _camera: std::marker::PhantomData<&'a Camera>,
}

impl<'a> Estimator for PairEstimator<'a> {
    type Datum = PointObservation<'a>;
    type Model = Vector3<f64>;
    const MIN_SAMPLES: usize = 2;

    fn estimate(&self, sample: &[PointObservation<'a>]) -> Vec<Vector3<f64>> {
        let Some(point) = dlt_of(sample) else {
            return vec![];
        };
        let in_front = sample.iter().all(|o| o.depth_m(&point) > 0.0);
        let angle_deg = triangulation_angle_deg(
            &sample[0].cam_from_world.camera_center(),
            &sample[1].cam_from_world.camera_center(),
            &point,
        );
        if in_front && angle_deg >= self.min_angle_deg {
            vec![point]
        } else {
            vec![]
        }
    }

    fn residual_sq(&self, point: &Vector3<f64>, o: &PointObservation<'a>) -> f64 {
        o.reprojection_error_px(point)
            .map_or(f64::INFINITY, |e| e * e)
    }

    fn refine(
        &self,
        _point: &Vector3<f64>,
        inliers: &[PointObservation<'a>],
    ) -> Option<Vector3<f64>> {
        dlt_of(inliers)
    }
}

/// Triangulates a track with possible outlier observations: RANSAC over pairs of
/// views, inliers by reprojection error (<= `max_reprojection_error_px`, in front
/// of the camera), the point re-estimated by DLT from the inliers; then the
/// angle check over the inlier views.
pub fn triangulate_track_ransac(
    observations: &[PointObservation],
    options: &TriangulationOptions,
    rng: &mut ChaCha8Rng,
) -> Result<TriangulatedPoint, TriangulationFailure> {
    options.validate()?;
    if observations.len() < 2 {
        return Err(TriangulationFailure::TooFewObservations {
            got: observations.len(),
        });
    }
    let estimator = PairEstimator {
        min_angle_deg: options.min_angle_deg,
        _camera: std::marker::PhantomData,
    };
    let report = match ransac::run(
        &estimator,
        observations,
        &[],
        &options.ransac_options(),
        rng,
    ) {
        Ok(report) => report,
        Err(RansacError::InvalidOptions(e)) => return Err(e.into()),
        Err(RansacError::NotEnoughData { got, .. }) => {
            return Err(TriangulationFailure::TooFewObservations { got })
        }
        Err(RansacError::NoModel { .. }) => return Err(TriangulationFailure::RansacFailed),
    };
    let point = report.model;
    let mut centers = Vec::with_capacity(report.num_inliers);
    let mut error_sum_px = 0.0;
    for (o, &inlier) in observations.iter().zip(&report.inlier_mask) {
        if inlier {
            centers.push(o.cam_from_world.camera_center());
            error_sum_px += o.reprojection_error_px(&point).unwrap_or(f64::INFINITY);
        }
    }
    let angle_deg = max_pairwise_angle_deg(&centers, &point);
    if !(angle_deg >= options.min_angle_deg) {
        return Err(TriangulationFailure::SmallAngle { angle_deg });
    }
    Ok(TriangulatedPoint {
        point_in_world: point,
        num_inliers: report.num_inliers,
        inlier_mask: report.inlier_mask,
        max_angle_deg: angle_deg,
        mean_reprojection_error_px: error_sum_px / centers.len() as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraId, CameraModel};
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng};

    fn camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::SimpleRadial,
            width: 1000,
            height: 800,
            params: vec![800.0, 500.0, 400.0, -0.1],
        }
    }

    /// A camera at `center` looking at `target` (z forward), as `cam_from_world`.
    fn look_at(center: Vector3<f64>, target: Vector3<f64>) -> Rigid3 {
        let z = (target - center).normalize();
        let up = if z.z.abs() > 0.9 {
            Vector3::new(0.0, 1.0, 0.0)
        } else {
            Vector3::new(0.0, 0.0, 1.0)
        };
        let x = up.cross(&z).normalize();
        let y = z.cross(&x);
        let r_cam_from_world =
            nalgebra::Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        Rigid3::from_rotation_matrix(&r_cam_from_world, -(r_cam_from_world * center))
    }

    /// The observation of `point`; `None` when it falls outside the image.
    fn try_observe<'a>(
        camera: &'a Camera,
        pose: Rigid3,
        point: &Vector3<f64>,
    ) -> Option<PointObservation<'a>> {
        let pixel = camera.project(&pose.transform_point(point))?;
        let inside = pixel.x >= 0.0
            && pixel.y >= 0.0
            && pixel.x <= f64::from(camera.width)
            && pixel.y <= f64::from(camera.height);
        if inside {
            PointObservation::new(camera, pose, pixel)
        } else {
            None
        }
    }

    fn observe<'a>(camera: &'a Camera, pose: Rigid3, point: &Vector3<f64>) -> PointObservation<'a> {
        // The tests aim the cameras at the point.
        try_observe(camera, pose, point).unwrap()
    }

    #[test]
    fn angle_helper_hand_cases() {
        let p = Vector3::new(0.0, 0.0, 10.0);
        let a = triangulation_angle_deg(
            &Vector3::new(-10.0, 0.0, 0.0),
            &Vector3::new(10.0, 0.0, 0.0),
            &p,
        );
        assert!((a - 90.0).abs() < 1e-12);
        let a = triangulation_angle_deg(&Vector3::zeros(), &Vector3::new(0.0, 0.0, 5.0), &p);
        assert!(a.abs() < 1e-12);
        let a = triangulation_angle_deg(&Vector3::zeros(), &Vector3::new(0.0, 0.0, 20.0), &p);
        assert!((a - 180.0).abs() < 1e-12);
    }

    #[test]
    fn dlt_exact_on_noiseless_data() {
        let cam = camera();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (mut checked, mut worst_m) = (0, 0.0f64);
        for _ in 0..200 {
            let point = Vector3::new(
                rng.gen_range(-50.0..50.0),
                rng.gen_range(-50.0..50.0),
                rng.gen_range(-5.0..5.0),
            ) + Vector3::new(1e5, 2e5, 50.0) * rng.gen_range(0.0..1.0);
            let n = rng.gen_range(2..6);
            let obs: Vec<_> = (0..n)
                .filter_map(|_| {
                    let center = point
                        + Vector3::new(
                            rng.gen_range(-20.0..20.0),
                            rng.gen_range(-20.0..20.0),
                            rng.gen_range(-3.0..3.0),
                        );
                    let aim = point
                        + Vector3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), 0.0);
                    try_observe(&cam, look_at(center, aim), &point)
                })
                .collect();
            if obs.len() < 2 {
                continue;
            }
            let tri = triangulate_point(
                &obs,
                &TriangulationOptions {
                    min_angle_deg: 0.0,
                    ..Default::default()
                },
            )
            .unwrap();
            checked += 1;
            // Cameras within ~20 m of the point, coordinates up to 2e5 m.
            worst_m = worst_m.max((tri.point_in_world - point).norm());
            assert!(
                (tri.point_in_world - point).norm() < 1e-8,
                "{:?} vs {:?}",
                tri.point_in_world,
                point
            );
            assert!(tri.mean_reprojection_error_px < 1e-6);
        }
        assert!(checked > 150, "{checked}");
        eprintln!("DLT worst error {worst_m:e} m");
    }

    #[test]
    fn degenerate_and_few() {
        let cam = camera();
        let p = Vector3::new(0.0, 0.0, 10.0);
        let pose = look_at(Vector3::zeros(), p);
        let o = observe(&cam, pose, &p);
        assert_eq!(
            triangulate_point(&[o], &Default::default()),
            Err(TriangulationFailure::TooFewObservations { got: 1 })
        );
        assert!(triangulate_dlt(&[]).is_none());
        // Same centre, same ray: no solution.
        assert!(matches!(
            triangulate_point(&[o, o], &Default::default()),
            Err(TriangulationFailure::Degenerate)
                | Err(TriangulationFailure::SmallAngle { .. })
                | Err(TriangulationFailure::NegativeDepth { .. })
        ));
        let mut bad = o;
        bad.ray_in_cam.x = f64::NAN;
        assert_eq!(
            triangulate_point(&[o, bad], &Default::default()),
            Err(TriangulationFailure::Degenerate)
        );
        assert!(PointObservation::new(&cam, pose, Vector2::new(f64::NAN, 1.0)).is_none());
        // Pure rotation: two cameras at the same centre seeing the same point.
        let pose2 = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.05, 0.0) * pose.rotation,
            Vector3::zeros(),
        );
        let o2 = observe(&cam, pose2, &p);
        assert!(triangulate_point(&[o, o2], &Default::default()).is_err());
    }
}
