//! COLMAP camera models: ids, parameter orders, projection and unprojection.
//!
//! Pixel convention (COLMAP): the upper-left corner of the upper-left pixel is
//! (0, 0), so that pixel's centre is (0.5, 0.5). `project` maps a point in the
//! camera frame (x right, y down, z forward) to pixel coordinates; `unproject`
//! maps a pixel to a point on the normalised image plane (z = 1).
//!
//! All 11 COLMAP models are implemented with COLMAP's ids, parameter orders and
//! distortion formulas (see [`Camera::project_normalized`]); the removable
//! singularities (r -> 0 in the fisheye models, omega -> 0 in FOV) are evaluated
//! by Taylor series instead of COLMAP's epsilon branches, so the values are
//! exact to rounding everywhere.
//!
//! * [`Camera::project`] / [`Camera::project_normalized`]: the forward model,
//!   a few ns per point (fisheye and FOV: one `atan`/`tan`, ~50-100 ns).
//! * [`Camera::unproject`]: the inverse by damped Newton (analytic Jacobian).
//! * [`Camera::max_normalized_radius`], [`Camera::max_half_fov_rad`]: the
//!   model's valid domain and the image's field of view, for frustum culling
//!   (distortion polynomials fold back beyond their monotonic range).
//!
//! The same projection exists in C++ for the solver (`cpp/camera_models.h`,
//! templated for Ceres autodiff) with the same operations in the same order;
//! `tests/camera_models.rs` checks the two agree (to 1e-9 px; in practice bit
//! for bit).
use std::f64::consts::FRAC_PI_2;

use nalgebra::{Matrix2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::ids::CameraId;

/// Every COLMAP camera model, with COLMAP's numeric ids.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum CameraModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    OpenCv,
    OpenCvFisheye,
    FullOpenCv,
    Fov,
    SimpleRadialFisheye,
    RadialFisheye,
    ThinPrismFisheye,
}

impl CameraModel {
    pub const ALL: [CameraModel; 11] = [
        CameraModel::SimplePinhole,
        CameraModel::Pinhole,
        CameraModel::SimpleRadial,
        CameraModel::Radial,
        CameraModel::OpenCv,
        CameraModel::OpenCvFisheye,
        CameraModel::FullOpenCv,
        CameraModel::Fov,
        CameraModel::SimpleRadialFisheye,
        CameraModel::RadialFisheye,
        CameraModel::ThinPrismFisheye,
    ];

    /// COLMAP's `model_id`.
    pub fn id(self) -> i32 {
        match self {
            CameraModel::SimplePinhole => 0,
            CameraModel::Pinhole => 1,
            CameraModel::SimpleRadial => 2,
            CameraModel::Radial => 3,
            CameraModel::OpenCv => 4,
            CameraModel::OpenCvFisheye => 5,
            CameraModel::FullOpenCv => 6,
            CameraModel::Fov => 7,
            CameraModel::SimpleRadialFisheye => 8,
            CameraModel::RadialFisheye => 9,
            CameraModel::ThinPrismFisheye => 10,
        }
    }

    /// The fisheye models: image radius about proportional to the ray's angle
    /// from the axis (equidistant), not to its tangent.
    pub fn is_fisheye(self) -> bool {
        matches!(
            self,
            CameraModel::SimpleRadialFisheye
                | CameraModel::RadialFisheye
                | CameraModel::OpenCvFisheye
                | CameraModel::ThinPrismFisheye
        )
    }

    pub fn from_id(id: i64) -> Option<Self> {
        Self::ALL.into_iter().find(|m| i64::from(m.id()) == id)
    }

    /// COLMAP's model name, as written in `cameras.txt`.
    pub fn name(self) -> &'static str {
        match self {
            CameraModel::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
            CameraModel::Radial => "RADIAL",
            CameraModel::OpenCv => "OPENCV",
            CameraModel::OpenCvFisheye => "OPENCV_FISHEYE",
            CameraModel::FullOpenCv => "FULL_OPENCV",
            CameraModel::Fov => "FOV",
            CameraModel::SimpleRadialFisheye => "SIMPLE_RADIAL_FISHEYE",
            CameraModel::RadialFisheye => "RADIAL_FISHEYE",
            CameraModel::ThinPrismFisheye => "THIN_PRISM_FISHEYE",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }

    /// Parameter names in COLMAP's order.
    pub fn param_names(self) -> &'static [&'static str] {
        match self {
            CameraModel::SimplePinhole => &["f", "cx", "cy"],
            CameraModel::Pinhole => &["fx", "fy", "cx", "cy"],
            CameraModel::SimpleRadial => &["f", "cx", "cy", "k"],
            CameraModel::Radial => &["f", "cx", "cy", "k1", "k2"],
            CameraModel::OpenCv => &["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"],
            CameraModel::OpenCvFisheye => &["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"],
            CameraModel::FullOpenCv => &[
                "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
            ],
            CameraModel::Fov => &["fx", "fy", "cx", "cy", "omega"],
            CameraModel::SimpleRadialFisheye => &["f", "cx", "cy", "k"],
            CameraModel::RadialFisheye => &["f", "cx", "cy", "k1", "k2"],
            CameraModel::ThinPrismFisheye => &[
                "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1",
            ],
        }
    }

    pub fn num_params(self) -> usize {
        self.param_names().len()
    }

    /// Indices of the focal length parameter(s) (one or two).
    pub fn focal_idxs(self) -> &'static [usize] {
        if self.param_names()[0] == "f" {
            &[0]
        } else {
            &[0, 1]
        }
    }

    /// Indices of the principal point (cx, cy).
    pub fn principal_point_idxs(self) -> [usize; 2] {
        if self.param_names()[0] == "f" {
            [1, 2]
        } else {
            [2, 3]
        }
    }

    /// Indices of the remaining (distortion) parameters.
    pub fn extra_idxs(self) -> std::ops::Range<usize> {
        let first = self.principal_point_idxs()[1] + 1;
        first..self.num_params()
    }
}

/// A camera (intrinsics) as stored in COLMAP.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub id: CameraId,
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    /// Parameters in COLMAP's order for `model` (see [`CameraModel::param_names`]).
    pub params: Vec<f64>,
}

/// Largest image side, pixels, a camera may have: beyond any real camera
/// (a 150-megapixel back is 14204 px wide), so that a size read from a file
/// cannot make a depth image or a mask too large to allocate.
pub const MAX_IMAGE_SIDE: u32 = 100_000;
/// Largest image, pixels (a gigapixel).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 30;

/// Why `width` x `height` is not an image size a camera can have: zero, a
/// side over [`MAX_IMAGE_SIDE`] or over [`MAX_IMAGE_PIXELS`] in all.
pub fn bad_image_size(width: u64, height: u64) -> Option<String> {
    if width == 0 || height == 0 {
        Some(format!("image size {width}x{height} is empty"))
    } else if width > u64::from(MAX_IMAGE_SIDE) || height > u64::from(MAX_IMAGE_SIDE) {
        Some(format!(
            "image size {width}x{height} has a side over {MAX_IMAGE_SIDE} pixels"
        ))
    } else if width * height > MAX_IMAGE_PIXELS {
        Some(format!(
            "image size {width}x{height} is over {MAX_IMAGE_PIXELS} pixels"
        ))
    } else {
        None
    }
}

impl Camera {
    /// Mean focal length in pixels.
    pub fn mean_focal_length(&self) -> f64 {
        let idxs = self.model.focal_idxs();
        idxs.iter().map(|&i| self.params[i]).sum::<f64>() / idxs.len() as f64
    }

    pub fn principal_point(&self) -> Vector2<f64> {
        let [ix, iy] = self.model.principal_point_idxs();
        Vector2::new(self.params[ix], self.params[iy])
    }

    /// Projects a point in the camera frame to pixel coordinates.
    ///
    /// `None` when the point is at or behind the camera plane (z <= 0, or NaN),
    /// when the pixel is not finite, or when `params` does not have the model's
    /// length. The model is evaluated everywhere in front of the camera, as COLMAP
    /// does, also beyond the radius where a distortion polynomial folds back
    /// (where a point far off to the side can land inside the image): callers
    /// projecting points from all directions (the map projection) should first
    /// keep only points within [`Camera::max_half_fov_rad`] of the optical axis.
    #[inline]
    pub fn project(&self, point_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        let z = point_in_cam.z;
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        // Divisions (not a multiplication by 1/z) to match cpp/camera_models.h.
        self.project_normalized(&Vector2::new(point_in_cam.x / z, point_in_cam.y / z))
    }

    /// Maps a point (x/z, y/z) of the normalised image plane to pixel
    /// coordinates: distortion, then `pixel = f * distorted + c`.
    ///
    /// `None` when the pixel is not finite or `params` has the wrong length.
    /// Formulas (r² = u² + v²):
    /// * SIMPLE_RADIAL, RADIAL: `(u, v) * (1 + k1 r² + k2 r⁴)`;
    /// * OPENCV: the same plus the tangential terms
    ///   `(2 p1 u v + p2 (r² + 2u²), 2 p2 u v + p1 (r² + 2v²))`;
    /// * FULL_OPENCV: radial factor `(1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)`;
    /// * fisheye models: equidistant coordinates `(a, b) = (u, v) θ / r`, `θ = atan r`,
    ///   scaled by `1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸` (THIN_PRISM_FISHEYE adds the
    ///   tangential terms on `(a, b)` and `(sx1 θ², sy1 θ²)`);
    /// * FOV: `(u, v) * atan(2 r tan(ω/2)) / (r ω)`.
    ///
    /// The limits r → 0 and ω → 0 are evaluated by Taylor series.
    #[inline]
    pub fn project_normalized(&self, normalized: &Vector2<f64>) -> Option<Vector2<f64>> {
        use CameraModel as M;
        let (u, v) = (normalized.x, normalized.y);
        let ([fx, fy, cx, cy], [x, y]) = match (self.model, self.params.as_slice()) {
            (M::SimplePinhole, &[f, cx, cy]) => ([f, f, cx, cy], [u, v]),
            (M::Pinhole, &[fx, fy, cx, cy]) => ([fx, fy, cx, cy], [u, v]),
            (M::SimpleRadial, &[f, cx, cy, k]) => {
                let radial = 1.0 + k * (u * u + v * v);
                ([f, f, cx, cy], [u * radial, v * radial])
            }
            (M::Radial, &[f, cx, cy, k1, k2]) => {
                let r_sq = u * u + v * v;
                let radial = 1.0 + r_sq * (k1 + r_sq * k2);
                ([f, f, cx, cy], [u * radial, v * radial])
            }
            (M::OpenCv, &[fx, fy, cx, cy, k1, k2, p1, p2]) => {
                let r_sq = u * u + v * v;
                let radial = 1.0 + r_sq * (k1 + r_sq * k2);
                let [tx, ty] = tangential(p1, p2, u, v, r_sq);
                ([fx, fy, cx, cy], [u * radial + tx, v * radial + ty])
            }
            (M::FullOpenCv, &[fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6]) => {
                let r_sq = u * u + v * v;
                let numerator = 1.0 + r_sq * (k1 + r_sq * (k2 + r_sq * k3));
                let denominator = 1.0 + r_sq * (k4 + r_sq * (k5 + r_sq * k6));
                let radial = numerator / denominator;
                let [tx, ty] = tangential(p1, p2, u, v, r_sq);
                ([fx, fy, cx, cy], [u * radial + tx, v * radial + ty])
            }
            (M::Fov, &[fx, fy, cx, cy, omega]) => {
                let factor = fov_distortion_factor(omega, u * u + v * v);
                ([fx, fy, cx, cy], [u * factor, v * factor])
            }
            (M::SimpleRadialFisheye, &[f, cx, cy, k]) => {
                let ([a, b], theta_sq) = equidistant(u, v);
                let radial = 1.0 + k * theta_sq;
                ([f, f, cx, cy], [a * radial, b * radial])
            }
            (M::RadialFisheye, &[f, cx, cy, k1, k2]) => {
                let ([a, b], theta_sq) = equidistant(u, v);
                let radial = 1.0 + theta_sq * (k1 + theta_sq * k2);
                ([f, f, cx, cy], [a * radial, b * radial])
            }
            (M::OpenCvFisheye, &[fx, fy, cx, cy, k1, k2, k3, k4]) => {
                let ([a, b], theta_sq) = equidistant(u, v);
                let radial =
                    1.0 + theta_sq * (k1 + theta_sq * (k2 + theta_sq * (k3 + theta_sq * k4)));
                ([fx, fy, cx, cy], [a * radial, b * radial])
            }
            (M::ThinPrismFisheye, &[fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1]) => {
                let ([a, b], theta_sq) = equidistant(u, v);
                let radial =
                    1.0 + theta_sq * (k1 + theta_sq * (k2 + theta_sq * (k3 + theta_sq * k4)));
                let [tx, ty] = tangential(p1, p2, a, b, theta_sq);
                (
                    [fx, fy, cx, cy],
                    [
                        a * radial + tx + sx1 * theta_sq,
                        b * radial + ty + sy1 * theta_sq,
                    ],
                )
            }
            _ => return None,
        };
        let pixel = Vector2::new(fx * x + cx, fy * y + cy);
        (pixel.x.is_finite() && pixel.y.is_finite()).then_some(pixel)
    }

    /// Maps a pixel to the normalised image plane: the returned point (x, y, 1)
    /// is the direction of the pixel's viewing ray.
    ///
    /// Distortion is undone by damped Newton iteration with the analytic
    /// Jacobian (FOV: closed form) to a residual below 1e-13 of the normalised
    /// radius (~1e-10 px). `None` when `params` has the wrong length, when the
    /// pixel has no preimage within the model's domain (beyond the radius where
    /// the distortion folds back, i.e. where the Jacobian of the distortion is
    /// not positive; at or beyond 90° from the axis for fisheye and FOV models),
    /// or when the iteration does not converge.
    pub fn unproject(&self, pixel: &Vector2<f64>) -> Option<Vector3<f64>> {
        let intrinsics = self.intrinsics()?;
        let distorted = Vector2::new(
            (pixel.x - intrinsics.principal_point[0]) / intrinsics.focal[0],
            (pixel.y - intrinsics.principal_point[1]) / intrinsics.focal[1],
        );
        if !(distorted.x.is_finite() && distorted.y.is_finite()) {
            return None;
        }
        let normalized = match intrinsics.distortion {
            Distortion::Polynomial(Plane::Perspective, poly) => poly.invert(&distorted)?,
            Distortion::Polynomial(Plane::Equidistant, poly) => {
                let equidistant = poly.invert(&distorted)?;
                let theta_sq = equidistant.norm_squared();
                if theta_sq.is_nan() || theta_sq >= FRAC_PI_2 * FRAC_PI_2 {
                    return None;
                }
                equidistant * tan_over_x(theta_sq)
            }
            Distortion::Fov { omega } => {
                // Distorted radius ρ = atan(r a) / ω with a = 2 tan(ω/2), so
                // r / ρ = tan(ρ ω) / (ρ ω) * ω / a.
                let y_sq = distorted.norm_squared() * omega * omega;
                if y_sq.is_nan() || y_sq >= FRAC_PI_2 * FRAC_PI_2 {
                    return None;
                }
                distorted * (tan_over_x(y_sq) / tan_over_x(0.25 * omega * omega))
            }
        };
        Some(Vector3::new(normalized.x, normalized.y, 1.0))
    }

    /// Radius sqrt(x² + y²) / z on the normalised image plane up to which the
    /// radial part of the distortion is monotonic (`f64::INFINITY` when it is
    /// monotonic everywhere in front of the camera). Beyond it the image folds
    /// back: e.g. SIMPLE_RADIAL with k < 0 reaches its largest distorted radius
    /// at r = 1/sqrt(-3k) and maps larger radii back towards the centre.
    ///
    /// Found by scanning 4096 angles in [0°, 90°) for the first sign change of
    /// the radial derivative, then bisection; tangential and thin-prism terms
    /// are ignored. Costs ~0.1 ms: compute once per camera. `None` when
    /// `params` has the wrong length.
    pub fn max_normalized_radius(&self) -> Option<f64> {
        let intrinsics = self.intrinsics()?;
        Some(match intrinsics.distortion {
            Distortion::Polynomial(plane, poly) => poly.fold_radius(plane),
            Distortion::Fov { .. } => f64::INFINITY,
        })
    }

    /// Largest angle (radians) between the optical axis and the viewing ray of
    /// any pixel of the image `[0, width] x [0, height]`: the half-angle of the
    /// smallest cone around the axis that contains the whole field of view, for
    /// frustum culling. Pixels without a preimage (beyond the fold, see
    /// [`Camera::max_normalized_radius`]) count as the fold angle.
    ///
    /// Evaluated on 64 samples per image side, corners included (for radially
    /// monotonic distortion the maximum lies at a corner); < π/2. Compute once
    /// per camera. `None` when `params` has the wrong length.
    pub fn max_half_fov_rad(&self) -> Option<f64> {
        let fold_rad = self.max_normalized_radius()?.atan();
        let (width, height) = (f64::from(self.width), f64::from(self.height));
        const SAMPLES_PER_SIDE: u32 = 64;
        let mut max_rad: f64 = 0.0;
        for i in 0..=SAMPLES_PER_SIDE {
            let t = f64::from(i) / f64::from(SAMPLES_PER_SIDE);
            for pixel in [
                Vector2::new(t * width, 0.0),
                Vector2::new(t * width, height),
                Vector2::new(0.0, t * height),
                Vector2::new(width, t * height),
            ] {
                let angle_rad = match self.unproject(&pixel) {
                    Some(ray) => ray.xy().norm().atan().min(fold_rad),
                    None => fold_rad,
                };
                max_rad = max_rad.max(angle_rad);
            }
        }
        Some(max_rad)
    }

    /// Focal lengths, principal point and distortion in the general form used
    /// for inversion. `None` when `params` has the wrong length.
    fn intrinsics(&self) -> Option<Intrinsics> {
        use CameraModel as M;
        let p = self.params.as_slice();
        if p.len() != self.model.num_params() {
            return None;
        }
        let [ix, iy] = self.model.principal_point_idxs();
        let focal_idxs = self.model.focal_idxs();
        let focal = [p[focal_idxs[0]], p[*focal_idxs.last()?]];
        let extra = &p[self.model.extra_idxs()];
        let mut poly = PolyDistortion::default();
        let plane = match self.model {
            M::SimplePinhole | M::Pinhole => Plane::Perspective,
            M::SimpleRadial | M::Radial => {
                poly.numerator[..extra.len()].copy_from_slice(extra);
                Plane::Perspective
            }
            M::OpenCv => {
                poly.numerator[..2].copy_from_slice(&extra[..2]);
                poly.tangential.copy_from_slice(&extra[2..4]);
                Plane::Perspective
            }
            M::FullOpenCv => {
                poly.numerator[..2].copy_from_slice(&extra[..2]);
                poly.tangential.copy_from_slice(&extra[2..4]);
                poly.numerator[2] = extra[4];
                poly.denominator.copy_from_slice(&extra[5..8]);
                Plane::Perspective
            }
            M::Fov => {
                return Some(Intrinsics {
                    focal,
                    principal_point: [p[ix], p[iy]],
                    distortion: Distortion::Fov { omega: extra[0] },
                })
            }
            M::SimpleRadialFisheye | M::RadialFisheye | M::OpenCvFisheye => {
                poly.numerator[..extra.len()].copy_from_slice(extra);
                Plane::Equidistant
            }
            M::ThinPrismFisheye => {
                poly.numerator[..2].copy_from_slice(&extra[..2]);
                poly.tangential.copy_from_slice(&extra[2..4]);
                poly.numerator[2..4].copy_from_slice(&extra[4..6]);
                poly.prism.copy_from_slice(&extra[6..8]);
                Plane::Equidistant
            }
        };
        Some(Intrinsics {
            focal,
            principal_point: [p[ix], p[iy]],
            distortion: Distortion::Polynomial(plane, poly),
        })
    }
}

/// Below this squared argument, atan(x)/x and tan(x)/x are evaluated by their
/// Taylor series (truncation error < 1e-20). Same constant in cpp/camera_models.h.
const SERIES_MAX_ARG_SQ: f64 = 1e-4;

/// atan(x) / x as a function of x² (>= 0); 1 at x = 0.
#[inline]
fn atan_over_x(x_sq: f64) -> f64 {
    if x_sq < SERIES_MAX_ARG_SQ {
        // 1 - x²/3 + x⁴/5 - x⁶/7 + x⁸/9
        return 1.0
            + x_sq * (-1.0 / 3.0 + x_sq * (1.0 / 5.0 + x_sq * (-1.0 / 7.0 + x_sq * (1.0 / 9.0))));
    }
    let x = x_sq.sqrt();
    x.atan() / x
}

/// tan(x) / x as a function of x² (>= 0, x < π/2); 1 at x = 0.
#[inline]
fn tan_over_x(x_sq: f64) -> f64 {
    if x_sq < SERIES_MAX_ARG_SQ {
        // 1 + x²/3 + 2x⁴/15 + 17x⁶/315 + 62x⁸/2835
        return 1.0
            + x_sq
                * (1.0 / 3.0
                    + x_sq * (2.0 / 15.0 + x_sq * (17.0 / 315.0 + x_sq * (62.0 / 2835.0))));
    }
    let x = x_sq.sqrt();
    x.tan() / x
}

/// OpenCV's tangential distortion of the point (a, b), r_sq = a² + b².
#[inline]
fn tangential(p1: f64, p2: f64, a: f64, b: f64, r_sq: f64) -> [f64; 2] {
    let ab = a * b;
    [
        2.0 * p1 * ab + p2 * (r_sq + 2.0 * a * a),
        2.0 * p2 * ab + p1 * (r_sq + 2.0 * b * b),
    ]
}

/// Equidistant fisheye coordinates (a, b) = (u, v) θ / r with θ = atan(r), and θ².
#[inline]
fn equidistant(u: f64, v: f64) -> ([f64; 2], f64) {
    let theta_over_r = atan_over_x(u * u + v * v);
    let (a, b) = (u * theta_over_r, v * theta_over_r);
    ([a, b], a * a + b * b)
}

/// FOV model: atan(2 r tan(ω/2)) / (r ω) = atan(r a)/(r a) * a/ω with
/// a = 2 tan(ω/2) = ω tan(ω/2)/(ω/2).
#[inline]
fn fov_distortion_factor(omega: f64, r_sq: f64) -> f64 {
    let a_over_omega = tan_over_x(0.25 * omega * omega);
    let a = omega * a_over_omega;
    a_over_omega * atan_over_x(r_sq * a * a)
}

/// Intrinsics in the general form used to invert the models.
struct Intrinsics {
    focal: [f64; 2],
    principal_point: [f64; 2],
    distortion: Distortion,
}

/// The plane on which a polynomial distortion acts.
#[derive(Clone, Copy, Debug)]
enum Plane {
    /// (x/z, y/z).
    Perspective,
    /// (x/z, y/z) θ / r with θ = atan(r): the radius is the angle to the axis.
    Equidistant,
}

#[derive(Clone, Copy, Debug)]
enum Distortion {
    Polynomial(Plane, PolyDistortion),
    Fov { omega: f64 },
}

/// Every polynomial model in one form: for q on its plane and ρ² = |q|²,
/// `d(q) = q N(ρ²)/D(ρ²) + tangential(q) + (sx1, sy1) ρ²` with
/// `N = 1 + n1 ρ² + n2 ρ⁴ + n3 ρ⁶ + n4 ρ⁸` and `D = 1 + d1 ρ² + d2 ρ⁴ + d3 ρ⁶`.
#[derive(Clone, Copy, Debug, Default)]
struct PolyDistortion {
    numerator: [f64; 4],
    denominator: [f64; 3],
    tangential: [f64; 2],
    prism: [f64; 2],
}

/// Newton iterations allowed when undistorting.
const UNDISTORT_MAX_ITERATIONS: usize = 100;

impl PolyDistortion {
    /// Radial factor R = N/D and its derivative dR/d(ρ²).
    #[inline]
    fn radial(&self, rho_sq: f64) -> (f64, f64) {
        let [n1, n2, n3, n4] = self.numerator;
        let [d1, d2, d3] = self.denominator;
        let num = 1.0 + rho_sq * (n1 + rho_sq * (n2 + rho_sq * (n3 + rho_sq * n4)));
        let num_deriv = n1 + rho_sq * (2.0 * n2 + rho_sq * (3.0 * n3 + rho_sq * 4.0 * n4));
        let den = 1.0 + rho_sq * (d1 + rho_sq * (d2 + rho_sq * d3));
        let den_deriv = d1 + rho_sq * (2.0 * d2 + rho_sq * 3.0 * d3);
        (num / den, (num_deriv * den - num * den_deriv) / (den * den))
    }

    /// d(q) and its Jacobian with respect to q.
    #[inline]
    fn apply_with_jacobian(&self, q: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (a, b) = (q.x, q.y);
        let rho_sq = a * a + b * b;
        let (radial, radial_deriv) = self.radial(rho_sq);
        let [p1, p2] = self.tangential;
        let [sx, sy] = self.prism;
        let [tx, ty] = tangential(p1, p2, a, b, rho_sq);
        let value = Vector2::new(a * radial + tx + sx * rho_sq, b * radial + ty + sy * rho_sq);
        let cross = 2.0 * a * b * radial_deriv;
        let jacobian = Matrix2::new(
            radial + 2.0 * a * a * radial_deriv + 2.0 * p1 * b + 6.0 * p2 * a + 2.0 * sx * a,
            cross + 2.0 * p1 * a + 2.0 * p2 * b + 2.0 * sx * b,
            cross + 2.0 * p2 * b + 2.0 * p1 * a + 2.0 * sy * a,
            radial + 2.0 * b * b * radial_deriv + 2.0 * p2 * a + 6.0 * p1 * b + 2.0 * sy * b,
        );
        (value, jacobian)
    }

    /// Solves d(q) = target by damped Newton from q = target. `None` without
    /// convergence or when the Jacobian at the solution is not positive
    /// (a root beyond the fold).
    fn invert(&self, target: &Vector2<f64>) -> Option<Vector2<f64>> {
        let scale = 1.0 + target.norm();
        let converged_sq = (1e-13 * scale).powi(2);
        let mut q = *target;
        let (value, mut jacobian) = self.apply_with_jacobian(&q);
        let mut residual = value - target;
        let mut residual_sq = residual.norm_squared();
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            if residual_sq <= converged_sq {
                break;
            }
            let inverse = jacobian.try_inverse()?;
            let step = inverse * residual;
            let mut step_scale = 1.0;
            let mut improved = false;
            for _ in 0..40 {
                let candidate = q - step * step_scale;
                let (value, candidate_jacobian) = self.apply_with_jacobian(&candidate);
                let candidate_residual = value - target;
                let candidate_sq = candidate_residual.norm_squared();
                if candidate_sq < residual_sq {
                    q = candidate;
                    residual = candidate_residual;
                    jacobian = candidate_jacobian;
                    residual_sq = candidate_sq;
                    improved = true;
                    break;
                }
                step_scale *= 0.5;
            }
            if !improved {
                break;
            }
        }
        let converged = residual_sq <= converged_sq;
        (converged && jacobian.determinant() > 0.0 && q.x.is_finite() && q.y.is_finite())
            .then_some(q)
    }

    /// Radius on `plane` mapped to the normalised plane (x/z, y/z).
    fn fold_radius(&self, plane: Plane) -> f64 {
        const NUM_SCAN_ANGLES: u32 = 4096;
        // Radius on the distortion's own plane for an angle θ to the axis.
        let rho_of = |theta: f64| match plane {
            Plane::Perspective => theta.tan(),
            Plane::Equidistant => theta,
        };
        // d(ρ R(ρ²))/dρ.
        let slope = |rho: f64| {
            let (radial, radial_deriv) = self.radial(rho * rho);
            radial + 2.0 * rho * rho * radial_deriv
        };
        let step = FRAC_PI_2 / f64::from(NUM_SCAN_ANGLES);
        let mut previous_theta = 0.0;
        for i in 1..NUM_SCAN_ANGLES {
            let theta = f64::from(i) * step;
            let theta_slope = slope(rho_of(theta));
            if theta_slope.is_nan() || theta_slope <= 0.0 {
                let (mut good, mut bad) = (previous_theta, theta);
                for _ in 0..60 {
                    let mid = 0.5 * (good + bad);
                    if slope(rho_of(mid)) > 0.0 {
                        good = mid;
                    } else {
                        bad = mid;
                    }
                }
                return good.tan();
            }
            previous_theta = theta;
        }
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(model: CameraModel, params: &[f64]) -> Camera {
        Camera {
            id: CameraId(1),
            model,
            width: 640,
            height: 480,
            params: params.to_vec(),
        }
    }

    #[test]
    fn ids_and_names_round_trip() {
        for (expected_id, model) in CameraModel::ALL.into_iter().enumerate() {
            assert_eq!(model.id() as usize, expected_id);
            assert_eq!(CameraModel::from_id(i64::from(model.id())), Some(model));
            assert_eq!(CameraModel::from_name(model.name()), Some(model));
        }
        assert_eq!(CameraModel::from_id(11), None);
        assert_eq!(CameraModel::from_id(-1), None);
        assert_eq!(CameraModel::from_name("OPENCV5"), None);
        assert_eq!(CameraModel::from_name("opencv"), None);
        let counts: Vec<usize> = CameraModel::ALL.iter().map(|m| m.num_params()).collect();
        assert_eq!(counts, [3, 4, 4, 5, 8, 8, 12, 5, 4, 5, 12]);
    }

    #[test]
    fn series_match_closed_forms_around_the_threshold() {
        for x_sq in [0.5e-4, 0.999_999e-4, 1e-4, 1.000_001e-4, 2e-4, 0.3, 2.0] {
            let x: f64 = f64::sqrt(x_sq);
            assert!(
                (atan_over_x(x_sq) - x.atan() / x).abs() < 1e-15,
                "atan {x_sq}"
            );
            assert!((tan_over_x(x_sq) - x.tan() / x).abs() < 1e-15, "tan {x_sq}");
        }
        assert_eq!(atan_over_x(0.0), 1.0);
        assert_eq!(tan_over_x(0.0), 1.0);
    }

    #[test]
    fn polynomial_jacobian_matches_finite_differences() {
        let poly = PolyDistortion {
            numerator: [-0.2, 0.05, 0.01, -0.002],
            denominator: [0.03, -0.01, 0.002],
            tangential: [0.002, -0.003],
            prism: [0.001, -0.0015],
        };
        let q = Vector2::new(0.4, -0.3);
        let (_, jacobian) = poly.apply_with_jacobian(&q);
        let h = 1e-6;
        for col in 0..2 {
            let mut dq = Vector2::zeros();
            dq[col] = h;
            let numeric = (poly.apply_with_jacobian(&(q + dq)).0
                - poly.apply_with_jacobian(&(q - dq)).0)
                / (2.0 * h);
            for row in 0..2 {
                assert!((jacobian[(row, col)] - numeric[row]).abs() < 1e-8);
            }
        }
    }

    #[test]
    fn fold_radius_of_simple_radial_is_one_over_sqrt_minus_three_k() {
        let cam = camera(CameraModel::SimpleRadial, &[500.0, 320.0, 240.0, -0.3]);
        let expected = 1.0 / f64::sqrt(0.9);
        assert!((cam.max_normalized_radius().unwrap() - expected).abs() < 1e-12);
        let cam = camera(CameraModel::SimpleRadial, &[500.0, 320.0, 240.0, 0.3]);
        assert_eq!(cam.max_normalized_radius(), Some(f64::INFINITY));
        // Fisheye: θ(1 + kθ²) peaks at θ = 1/sqrt(-3k).
        let cam = camera(
            CameraModel::SimpleRadialFisheye,
            &[500.0, 320.0, 240.0, -0.5],
        );
        let expected = f64::tan(1.0 / f64::sqrt(1.5));
        assert!((cam.max_normalized_radius().unwrap() - expected).abs() < 1e-12);
    }

    #[test]
    fn half_fov_of_pinhole_is_the_corner_angle() {
        let cam = camera(CameraModel::Pinhole, &[500.0, 400.0, 300.0, 200.0]);
        // Farthest corner from (300, 200) in normalised units: (340/500, 280/400).
        let expected = f64::hypot(340.0 / 500.0, 280.0 / 400.0).atan();
        assert!((cam.max_half_fov_rad().unwrap() - expected).abs() < 1e-12);
        // Past the fold the cone is capped at the fold angle.
        let cam = camera(CameraModel::SimpleRadial, &[100.0, 320.0, 240.0, -0.3]);
        let fold_rad = (1.0 / f64::sqrt(0.9)).atan();
        assert!((cam.max_half_fov_rad().unwrap() - fold_rad).abs() < 1e-12);
    }

    #[test]
    fn wrong_param_count_is_none_not_a_panic() {
        for model in CameraModel::ALL {
            let cam = camera(model, &[500.0, 320.0]);
            assert_eq!(cam.project(&Vector3::new(0.1, 0.2, 1.0)), None);
            assert_eq!(cam.unproject(&Vector2::new(10.0, 20.0)), None);
            assert_eq!(cam.max_half_fov_rad(), None);
        }
    }

    #[test]
    fn points_behind_or_on_the_camera_plane_do_not_project() {
        let cam = camera(CameraModel::SimplePinhole, &[500.0, 320.0, 240.0]);
        assert_eq!(cam.project(&Vector3::new(0.1, 0.2, 0.0)), None);
        assert_eq!(cam.project(&Vector3::new(0.1, 0.2, -1.0)), None);
        assert_eq!(cam.project(&Vector3::new(0.1, 0.2, f64::NAN)), None);
        assert_eq!(cam.project(&Vector3::new(f64::INFINITY, 0.2, 1.0)), None);
        let pixel = cam.project(&Vector3::new(0.1, 0.2, 2.0)).unwrap();
        assert_eq!(pixel, Vector2::new(345.0, 290.0));
    }
}
