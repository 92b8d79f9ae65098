//! Ray / plane intersection in the world frame: the map initialisation of
//! method.md 4.4 (a feature's viewing ray meets the tangent plane `n·X = n·l` of
//! the LiDAR point `l` it sees).
//!
//! The ray `X(s) = o + s d` (unit `d`, range `s` in metres) meets the plane at
//! `s = n·(l - o) / n·d`. The angle of incidence `θ` between the ray and the
//! plane's normal (`cos θ = |n·d|`; 90° = grazing) governs the sensitivity: a
//! normal error `δ` moves the range by about `s tan θ δ`, so grazing rays are
//! rejected. The ray is taken **in the world frame**: for a camera, the origin is
//! its centre and the direction `Rᵀ ray_in_cam` ([`camera_ray_in_world`]); this
//! is right for any pose (the reference mixes frames and is right only for the
//! identity).
use nalgebra::{Vector2, Vector3};

use super::InvalidOptions;
use crate::scene::{Camera, Rigid3};

/// Options of [`intersect_ray_plane`].
#[derive(Clone, Debug, PartialEq)]
pub struct RayPlaneOptions {
    /// Largest angle (degrees) between the ray and the plane's normal; beyond it
    /// the ray is "nearly parallel" to the plane and rejected. Default: 80
    /// (`|cos| >= 0.174`: a 1° normal error moves the range by at most ~10%;
    /// at 85° it would be ~20%).
    pub max_incidence_deg: f64,
    /// Smallest accepted range (m); intersections at or behind it are rejected
    /// (0 rejects those behind or at the origin). Default: 0.
    pub min_range_m: f64,
    /// Largest accepted range (m). Default: infinity.
    pub max_range_m: f64,
}

impl Default for RayPlaneOptions {
    fn default() -> Self {
        Self {
            max_incidence_deg: 80.0,
            min_range_m: 0.0,
            max_range_m: f64::INFINITY,
        }
    }
}

impl RayPlaneOptions {
    pub fn validate(&self) -> Result<(), InvalidOptions> {
        if !(self.max_incidence_deg >= 0.0 && self.max_incidence_deg <= 90.0) {
            return Err(InvalidOptions::new(
                "max_incidence_deg",
                format!("must be in [0, 90], got {}", self.max_incidence_deg),
            ));
        }
        if !(self.min_range_m >= 0.0 && self.max_range_m > self.min_range_m) {
            return Err(InvalidOptions::new(
                "min_range_m/max_range_m",
                format!(
                    "need 0 <= min_range_m < max_range_m, got {} and {}",
                    self.min_range_m, self.max_range_m
                ),
            ));
        }
        Ok(())
    }
}

/// An intersection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayPlaneHit {
    /// The intersection, world frame.
    pub point: Vector3<f64>,
    /// Distance from the ray's origin along its (unit) direction, metres.
    pub range_m: f64,
    /// Angle between the ray and the plane's normal, degrees (0 = head-on).
    pub incidence_deg: f64,
}

/// Why a ray gave no intersection.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RayPlaneMiss {
    #[error(transparent)]
    InvalidOptions(#[from] InvalidOptions),
    #[error("non-finite or zero-length ray direction or plane normal, or non-finite point")]
    Degenerate,
    #[error("ray nearly parallel to the plane (incidence {incidence_deg:.2} deg)")]
    NearlyParallel { incidence_deg: f64 },
    #[error("intersection behind or too close to the ray's origin (range {range_m} m)")]
    Behind { range_m: f64 },
    #[error("intersection too far (range {range_m} m)")]
    TooFar { range_m: f64 },
}

/// Intersects the ray `origin + s direction` with the plane through
/// `plane_point` with normal `plane_normal` (neither direction nor normal need
/// be unit; all in one frame, normally the world).
pub fn intersect_ray_plane(
    origin: &Vector3<f64>,
    direction: &Vector3<f64>,
    plane_normal: &Vector3<f64>,
    plane_point: &Vector3<f64>,
    options: &RayPlaneOptions,
) -> Result<RayPlaneHit, RayPlaneMiss> {
    options.validate()?;
    let finite = |v: &Vector3<f64>| v.iter().all(|x| x.is_finite());
    if !(finite(origin) && finite(plane_point)) {
        return Err(RayPlaneMiss::Degenerate);
    }
    let (Some(d), Some(n)) = (
        direction.try_normalize(0.0).filter(finite),
        plane_normal.try_normalize(0.0).filter(finite),
    ) else {
        return Err(RayPlaneMiss::Degenerate);
    };
    let cos = n.dot(&d);
    let incidence_deg = cos.abs().min(1.0).acos().to_degrees();
    if !(incidence_deg <= options.max_incidence_deg) || cos == 0.0 {
        return Err(RayPlaneMiss::NearlyParallel { incidence_deg });
    }
    let range_m = n.dot(&(plane_point - origin)) / cos;
    if !(range_m > options.min_range_m) {
        return Err(RayPlaneMiss::Behind { range_m });
    }
    if range_m > options.max_range_m {
        return Err(RayPlaneMiss::TooFar { range_m });
    }
    Ok(RayPlaneHit {
        point: origin + range_m * d,
        range_m,
        incidence_deg,
    })
}

/// The viewing ray of a camera in the world frame: origin = camera centre,
/// direction = `Rᵀ ray_in_cam` (unit), for `X_cam = R X_world + t`.
pub fn camera_ray_in_world(
    cam_from_world: &Rigid3,
    ray_in_cam: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>) {
    let direction = cam_from_world.rotation.inverse() * ray_in_cam;
    (
        cam_from_world.camera_center(),
        direction.try_normalize(0.0).unwrap_or(direction),
    )
}

/// Intersects the viewing ray of `pixel` (COLMAP pixel convention) of a camera
/// with pose `cam_from_world` with a plane given in the world frame.
/// [`RayPlaneMiss::Degenerate`] when the pixel cannot be unprojected.
pub fn intersect_pixel_ray_plane(
    camera: &Camera,
    cam_from_world: &Rigid3,
    pixel: &Vector2<f64>,
    plane_normal: &Vector3<f64>,
    plane_point: &Vector3<f64>,
    options: &RayPlaneOptions,
) -> Result<RayPlaneHit, RayPlaneMiss> {
    let ray_in_cam = camera.unproject(pixel).ok_or(RayPlaneMiss::Degenerate)?;
    let (origin, direction) = camera_ray_in_world(cam_from_world, &ray_in_cam);
    intersect_ray_plane(&origin, &direction, plane_normal, plane_point, options)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn hand_computed() {
        let opts = RayPlaneOptions::default();
        // Straight down onto the ground z = 0 from 2 m.
        let hit = intersect_ray_plane(
            &Vector3::new(1.0, 2.0, 2.0),
            &Vector3::new(0.0, 0.0, -3.0),
            &Vector3::new(0.0, 0.0, 1.0),
            &Vector3::new(50.0, -7.0, 0.0),
            &opts,
        )
        .unwrap();
        assert_eq!(hit.point, Vector3::new(1.0, 2.0, 0.0));
        assert_eq!(hit.range_m, 2.0);
        assert_eq!(hit.incidence_deg, 0.0);
        // 45° onto the wall x = 5 from the origin: hit (5, 5, 0), range 5√2.
        let hit = intersect_ray_plane(
            &Vector3::zeros(),
            &Vector3::new(1.0, 1.0, 0.0),
            &Vector3::new(-2.0, 0.0, 0.0), // normal facing the ray, not unit
            &Vector3::new(5.0, 0.0, 9.0),
            &opts,
        )
        .unwrap();
        assert!((hit.point - Vector3::new(5.0, 5.0, 0.0)).norm() < 1e-12);
        assert!((hit.range_m - 50f64.sqrt()).abs() < 1e-12);
        assert!((hit.incidence_deg - 45.0).abs() < 1e-9);
        // Looking away from the wall: behind.
        assert!(matches!(
            intersect_ray_plane(
                &Vector3::zeros(),
                &Vector3::new(-1.0, 1.0, 0.0),
                &Vector3::new(1.0, 0.0, 0.0),
                &Vector3::new(5.0, 0.0, 0.0),
                &opts
            ),
            Err(RayPlaneMiss::Behind { range_m }) if (range_m + 50f64.sqrt()).abs() < 1e-12
        ));
        // 81° incidence: rejected at the default 80°, accepted at 85°.
        let a = 81f64.to_radians();
        let dir = Vector3::new(a.sin(), 0.0, -a.cos());
        let ground = (Vector3::new(0.0, 0.0, 1.0), Vector3::zeros());
        let o = Vector3::new(0.0, 0.0, 1.0);
        assert!(matches!(
            intersect_ray_plane(&o, &dir, &ground.0, &ground.1, &opts),
            Err(RayPlaneMiss::NearlyParallel { incidence_deg }) if (incidence_deg - 81.0).abs() < 1e-9
        ));
        let wide = RayPlaneOptions {
            max_incidence_deg: 85.0,
            ..opts.clone()
        };
        let hit = intersect_ray_plane(&o, &dir, &ground.0, &ground.1, &wide).unwrap();
        assert!((hit.range_m - 1.0 / a.cos()).abs() < 1e-9);
        // Exactly parallel, degenerate and invalid inputs: errors, no panic.
        assert!(matches!(
            intersect_ray_plane(&o, &Vector3::x(), &ground.0, &ground.1, &wide),
            Err(RayPlaneMiss::NearlyParallel { .. })
        ));
        for bad_dir in [Vector3::zeros(), Vector3::new(f64::NAN, 0.0, -1.0)] {
            assert_eq!(
                intersect_ray_plane(&o, &bad_dir, &ground.0, &ground.1, &opts),
                Err(RayPlaneMiss::Degenerate)
            );
        }
        let bad = RayPlaneOptions {
            max_incidence_deg: 95.0,
            ..opts.clone()
        };
        assert!(matches!(
            intersect_ray_plane(&o, &-Vector3::z(), &ground.0, &ground.1, &bad),
            Err(RayPlaneMiss::InvalidOptions(_))
        ));
        let near = RayPlaneOptions {
            max_range_m: 0.5,
            ..opts
        };
        assert!(matches!(
            intersect_ray_plane(&o, &-Vector3::z(), &ground.0, &ground.1, &near),
            Err(RayPlaneMiss::TooFar { .. })
        ));
    }

    #[test]
    fn random_camera_poses() {
        // For any pose: a world point X on a random plane, seen by the camera;
        // the pixel ray's intersection must give X back, at range |X - centre|.
        let camera = Camera {
            id: crate::scene::CameraId(1),
            model: crate::scene::CameraModel::OpenCv,
            width: 1920,
            height: 1080,
            params: vec![1400.0, 1390.0, 962.0, 538.0, -0.25, 0.08, 0.001, -0.0015],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(77);
        let mut checked = 0;
        for _ in 0..500 {
            let cam_from_world = Rigid3::new(
                UnitQuaternion::from_euler_angles(
                    rng.gen_range(-3.1..3.1),
                    rng.gen_range(-1.5..1.5),
                    rng.gen_range(-3.1..3.1),
                ),
                Vector3::new(
                    rng.gen_range(-1e3..1e3),
                    rng.gen_range(-1e3..1e3),
                    rng.gen_range(-50.0..50.0),
                ),
            );
            let pixel = Vector2::new(rng.gen_range(0.0..1920.0), rng.gen_range(0.0..1080.0));
            let depth_m = rng.gen_range(0.5..40.0);
            let point_in_cam = camera.unproject(&pixel).unwrap() * depth_m;
            let point = cam_from_world.inverse().transform_point(&point_in_cam);
            let normal = Vector3::new(
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            );
            // Another point of the same plane.
            let in_plane = normal.cross(&Vector3::new(0.3, -0.2, 0.9)) * rng.gen_range(-5.0..5.0);
            match intersect_pixel_ray_plane(
                &camera,
                &cam_from_world,
                &pixel,
                &normal,
                &(point + in_plane),
                &RayPlaneOptions::default(),
            ) {
                Ok(hit) => {
                    assert!(
                        (hit.point - point).norm() < 1e-7 * (1.0 + hit.incidence_deg),
                        "{hit:?}"
                    );
                    assert!((hit.range_m - point_in_cam.norm()).abs() < 1e-7);
                    checked += 1;
                }
                Err(RayPlaneMiss::NearlyParallel { incidence_deg }) => {
                    assert!(incidence_deg > 80.0)
                }
                Err(e) => panic!("{e}"),
            }
        }
        assert!(checked > 400, "{checked}");
    }
}
