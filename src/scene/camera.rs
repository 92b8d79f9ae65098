//! COLMAP camera models: ids, parameter orders, projection and unprojection.
//!
//! Pixel convention (COLMAP): the upper-left corner of the upper-left pixel is
//! (0, 0), so that pixel's centre is (0.5, 0.5). `project` maps a point in the
//! camera frame (x right, y down, z forward) to pixel coordinates; `unproject`
//! maps a pixel to a point on the normalised image plane (z = 1).
//!
//! The same projection exists in C++ for the solver (`cpp/camera_models.h`);
//! the two are tested against each other.
use nalgebra::{Vector2, Vector3};
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

    /// Projects a point in the camera frame to pixel coordinates. `None` when the
    /// point is at or behind the camera plane (z <= 0) for perspective models.
    pub fn project(&self, point_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        let _ = point_in_cam;
        todo!("camera models")
    }

    /// Maps a pixel to the normalised image plane (a ray direction with z = 1),
    /// undoing distortion iteratively. `None` if undistortion does not converge.
    pub fn unproject(&self, pixel: &Vector2<f64>) -> Option<Vector3<f64>> {
        let _ = pixel;
        todo!("camera models")
    }
}
