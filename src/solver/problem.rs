//! The bundle-adjustment problem as plain, index-addressed data, and its
//! validation (run before anything reaches Ceres: a failed check inside Ceres
//! aborts the process, so every index, size and value is checked here first).
//!
//! Conventions: poses are `cam_from_world` (`X_cam = R X_world + t`), stored as
//! `[qw, qx, qy, qz, tx, ty, tz]`; points are in the world frame, metres;
//! pixels follow COLMAP (centre of the upper-left pixel at (0.5, 0.5)).
use nalgebra::Vector3;

use super::SolverError;
use crate::scene::{CameraModel, Rigid3};

/// Largest accepted deviation of a quaternion or normal from unit length. Inputs
/// within it are normalised exactly before the solve.
pub const UNIT_TOLERANCE: f64 = 1e-6;

/// Largest `n` of [`PlaneFamily::Other`].
pub const MAX_OTHER_PLANE_FAMILY: u8 = 63;

/// One image's pose.
#[derive(Clone, Debug, PartialEq)]
pub struct BaPose {
    /// `cam_from_world` as `[qw, qx, qy, qz, tx, ty, tz]`; unit quaternion.
    pub cam_from_world: [f64; 7],
    /// The whole pose stays fixed.
    pub constant: bool,
}

impl BaPose {
    pub fn new(cam_from_world: &Rigid3, constant: bool) -> Self {
        let q = cam_from_world.quaternion_wxyz();
        let t = cam_from_world.translation;
        Self {
            cam_from_world: [q[0], q[1], q[2], q[3], t.x, t.y, t.z],
            constant,
        }
    }

    /// Camera centre in the world frame, metres.
    pub fn center(&self) -> Vector3<f64> {
        self.rigid().camera_center()
    }

    /// The pose as a [`Rigid3`] (quaternion re-normalised).
    pub fn rigid(&self) -> Rigid3 {
        let p = &self.cam_from_world;
        Rigid3::from_colmap([p[0], p[1], p[2], p[3]], [p[4], p[5], p[6]])
    }
}

/// Which intrinsic parameters stay fixed.
#[derive(Clone, Debug, PartialEq, Default)]
pub enum ConstantParams {
    /// All parameters are refined.
    #[default]
    None,
    /// All parameters are fixed.
    All,
    /// One flag per parameter in the model's order; `true` = fixed.
    Mask(Vec<bool>),
}

/// One camera's intrinsics.
#[derive(Clone, Debug, PartialEq)]
pub struct BaCamera {
    /// COLMAP model id (see [`CameraModel::id`]).
    pub model_id: i32,
    /// Parameters in COLMAP's order for the model.
    pub params: Vec<f64>,
    pub constant: ConstantParams,
}

impl BaCamera {
    pub fn new(camera: &crate::scene::Camera, constant: ConstantParams) -> Self {
        Self {
            model_id: camera.model.id(),
            params: camera.params.clone(),
            constant,
        }
    }

    /// Whether parameter `k` is fixed.
    pub fn is_param_constant(&self, k: usize) -> bool {
        match &self.constant {
            ConstantParams::None => false,
            ConstantParams::All => true,
            ConstantParams::Mask(mask) => mask.get(k).copied().unwrap_or(false),
        }
    }
}

/// One 3D point.
#[derive(Clone, Debug, PartialEq)]
pub struct BaPoint {
    /// Position in the world frame, metres.
    pub position_in_world: [f64; 3],
    pub constant: bool,
}

impl BaPoint {
    pub fn new(position_in_world: &Vector3<f64>, constant: bool) -> Self {
        Self {
            position_in_world: [
                position_in_world.x,
                position_in_world.y,
                position_in_world.z,
            ],
            constant,
        }
    }

    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.position_in_world)
    }
}

/// One reprojection residual: `weight * (project(camera, pose * point) - pixel_px)`.
#[derive(Clone, Debug, PartialEq)]
pub struct BaObservation {
    pub pose_idx: u32,
    pub camera_idx: u32,
    pub point_idx: u32,
    /// Observed pixel, COLMAP convention.
    pub pixel_px: [f64; 2],
    /// Multiplies the residual (so the cost scales with its square); 1 for a
    /// plain observation. Finite and >= 0.
    pub weight: f64,
}

impl BaObservation {
    /// An observation with weight 1.
    pub fn new(pose_idx: u32, camera_idx: u32, point_idx: u32, pixel_px: [f64; 2]) -> Self {
        Self {
            pose_idx,
            camera_idx,
            point_idx,
            pixel_px,
            weight: 1.0,
        }
    }
}

/// Kinds of point-to-plane constraints: each family has its own robust loss and
/// its own line in the summary.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum PlaneFamily {
    /// LiDAR point found by projecting the map into an image.
    Projection,
    /// Nearest LiDAR point to the 3D point.
    Nearest,
    /// Ground plane (normal near vertical).
    Ground,
    /// Any other family, `n <= MAX_OTHER_PLANE_FAMILY`.
    Other(u8),
}

impl PlaneFamily {
    /// Index among plane families: Projection 0, Nearest 1, Ground 2, Other(n) 3 + n.
    pub fn index(self) -> u32 {
        match self {
            PlaneFamily::Projection => 0,
            PlaneFamily::Nearest => 1,
            PlaneFamily::Ground => 2,
            PlaneFamily::Other(n) => 3 + u32::from(n),
        }
    }

    /// Inverse of [`PlaneFamily::index`].
    pub fn from_index(index: u32) -> Option<Self> {
        match index {
            0 => Some(PlaneFamily::Projection),
            1 => Some(PlaneFamily::Nearest),
            2 => Some(PlaneFamily::Ground),
            n => u8::try_from(n - 3)
                .ok()
                .filter(|&k| k <= MAX_OTHER_PLANE_FAMILY)
                .map(PlaneFamily::Other),
        }
    }
}

/// A point-to-plane constraint: residual `weight * (normal . X - offset_m)`,
/// signed, in "pixel equivalents" (weight 1000: 1 mm counts like 1 px).
/// For a LiDAR point `l` with normal `n`, `offset_m = n . l`.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaneConstraint {
    pub point_idx: u32,
    /// Unit normal, world frame.
    pub normal: [f64; 3],
    /// Plane offset `d` in `n . X = d`, metres.
    pub offset_m: f64,
    /// Finite and >= 0.
    pub weight: f64,
    pub family: PlaneFamily,
}

/// A soft prior on one pose. Residuals (6):
/// `position_weight * (C - position_in_world)` with `C` the camera centre
/// (metres), and `rotation_weight * angle_axis(R * R_prior^T)` (radians) with
/// both rotations `cam_from_world`.
#[derive(Clone, Debug, PartialEq)]
pub struct PosePrior {
    pub pose_idx: u32,
    /// Prior camera centre in the world frame, metres; `None`: no position prior.
    pub position_in_world: Option<[f64; 3]>,
    /// Prior orientation as the `cam_from_world` quaternion `[qw, qx, qy, qz]`
    /// (the same convention as [`BaPose`]); `None`: no rotation prior.
    pub cam_from_world_rotation: Option<[f64; 4]>,
    /// Multiplies the position residual (metres -> pixel equivalents), >= 0.
    pub position_weight: f64,
    /// Multiplies the rotation residual (radians -> pixel equivalents), >= 0.
    pub rotation_weight: f64,
}

/// A whole bundle-adjustment problem. Indices address the vectors; a pose,
/// camera or point that no residual mentions is left untouched.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BundleAdjustmentProblem {
    pub poses: Vec<BaPose>,
    pub cameras: Vec<BaCamera>,
    pub points: Vec<BaPoint>,
    pub observations: Vec<BaObservation>,
    pub planes: Vec<PlaneConstraint>,
    pub pose_priors: Vec<PosePrior>,
}

fn invalid(what: String) -> SolverError {
    SolverError::InvalidProblem(what)
}

fn check_finite(values: &[f64], what: impl Fn() -> String) -> Result<(), SolverError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(invalid(format!("{} is not finite: {values:?}", what())))
    }
}

fn check_unit(values: &[f64], what: impl Fn() -> String) -> Result<(), SolverError> {
    let norm = values.iter().map(|v| v * v).sum::<f64>().sqrt();
    if (norm - 1.0).abs() > UNIT_TOLERANCE {
        return Err(invalid(format!(
            "{} is not unit length (norm {norm})",
            what()
        )));
    }
    Ok(())
}

fn check_weight(weight: f64, what: impl Fn() -> String) -> Result<(), SolverError> {
    if weight.is_finite() && weight >= 0.0 {
        Ok(())
    } else {
        Err(invalid(format!(
            "{} must be finite and >= 0, got {weight}",
            what()
        )))
    }
}

fn check_index(index: u32, len: usize, what: impl Fn() -> String) -> Result<(), SolverError> {
    if (index as usize) < len {
        Ok(())
    } else {
        Err(invalid(format!(
            "{} = {index} is out of range ({len} available)",
            what()
        )))
    }
}

impl BundleAdjustmentProblem {
    /// Checks every index, size and value: finite numbers, unit quaternions and
    /// normals (within [`UNIT_TOLERANCE`]), known camera models with the right
    /// parameter count and mask length, non-negative weights.
    pub fn validate(&self) -> Result<(), SolverError> {
        for (i, pose) in self.poses.iter().enumerate() {
            check_finite(&pose.cam_from_world, || format!("pose {i}"))?;
            check_unit(&pose.cam_from_world[..4], || format!("pose {i} quaternion"))?;
        }
        for (i, camera) in self.cameras.iter().enumerate() {
            let model = CameraModel::from_id(i64::from(camera.model_id)).ok_or_else(|| {
                invalid(format!("camera {i}: unknown model id {}", camera.model_id))
            })?;
            if camera.params.len() != model.num_params() {
                return Err(invalid(format!(
                    "camera {i}: model {} takes {} parameters, got {}",
                    model.name(),
                    model.num_params(),
                    camera.params.len()
                )));
            }
            check_finite(&camera.params, || format!("camera {i} parameters"))?;
            if let ConstantParams::Mask(mask) = &camera.constant {
                if mask.len() != camera.params.len() {
                    return Err(invalid(format!(
                        "camera {i}: constant mask has {} entries for {} parameters",
                        mask.len(),
                        camera.params.len()
                    )));
                }
            }
        }
        for (i, point) in self.points.iter().enumerate() {
            check_finite(&point.position_in_world, || format!("point {i}"))?;
        }
        for (i, obs) in self.observations.iter().enumerate() {
            check_index(obs.pose_idx, self.poses.len(), || {
                format!("observation {i}: pose_idx")
            })?;
            check_index(obs.camera_idx, self.cameras.len(), || {
                format!("observation {i}: camera_idx")
            })?;
            check_index(obs.point_idx, self.points.len(), || {
                format!("observation {i}: point_idx")
            })?;
            check_finite(&obs.pixel_px, || format!("observation {i}: pixel"))?;
            check_weight(obs.weight, || format!("observation {i}: weight"))?;
        }
        for (i, plane) in self.planes.iter().enumerate() {
            check_index(plane.point_idx, self.points.len(), || {
                format!("plane constraint {i}: point_idx")
            })?;
            check_finite(&plane.normal, || format!("plane constraint {i}: normal"))?;
            check_unit(&plane.normal, || format!("plane constraint {i}: normal"))?;
            check_finite(&[plane.offset_m], || {
                format!("plane constraint {i}: offset")
            })?;
            check_weight(plane.weight, || format!("plane constraint {i}: weight"))?;
            if let PlaneFamily::Other(n) = plane.family {
                if n > MAX_OTHER_PLANE_FAMILY {
                    return Err(invalid(format!(
                        "plane constraint {i}: family Other({n}) above {MAX_OTHER_PLANE_FAMILY}"
                    )));
                }
            }
        }
        for (i, prior) in self.pose_priors.iter().enumerate() {
            check_index(prior.pose_idx, self.poses.len(), || {
                format!("pose prior {i}: pose_idx")
            })?;
            if let Some(position) = &prior.position_in_world {
                check_finite(position, || format!("pose prior {i}: position"))?;
            }
            if let Some(q) = &prior.cam_from_world_rotation {
                check_finite(q, || format!("pose prior {i}: rotation"))?;
                check_unit(q, || format!("pose prior {i}: rotation"))?;
            }
            check_weight(prior.position_weight, || {
                format!("pose prior {i}: position_weight")
            })?;
            check_weight(prior.rotation_weight, || {
                format!("pose prior {i}: rotation_weight")
            })?;
        }
        Ok(())
    }

    /// Number of residual blocks (observations + planes + priors).
    pub fn num_residual_blocks(&self) -> usize {
        self.observations.len() + self.planes.len() + self.pose_priors.len()
    }
}
