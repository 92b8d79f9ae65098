//! A reconstruction: cameras, images with poses and 2D points, 3D points with tracks.
//! Plain data, ordered maps so iteration (and every file written) is deterministic.
use std::collections::BTreeMap;

use nalgebra::{Vector2, Vector3};

use super::camera::Camera;
use super::ids::{CameraId, ImageId, Point2DIdx, Point3DId};
use super::pose::Rigid3;

/// A keypoint of an image, and the 3D point it observes, if any.
#[derive(Clone, Debug, PartialEq)]
pub struct Point2D {
    /// Pixel coordinates (COLMAP convention: pixel centres at +0.5).
    pub xy: Vector2<f64>,
    pub point3d_id: Option<Point3DId>,
}

/// An image: its camera, its pose (when registered) and its 2D points.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub id: ImageId,
    pub name: String,
    pub camera_id: CameraId,
    /// World-to-camera pose: `X_cam = R X_world + t`. `None` until registered.
    pub cam_from_world: Option<Rigid3>,
    pub points2d: Vec<Point2D>,
}

impl Image {
    pub fn is_registered(&self) -> bool {
        self.cam_from_world.is_some()
    }

    pub fn num_points3d(&self) -> usize {
        self.points2d
            .iter()
            .filter(|p| p.point3d_id.is_some())
            .count()
    }
}

/// One observation of a 3D point: image and keypoint index.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct TrackElement {
    pub image_id: ImageId,
    pub point2d_idx: Point2DIdx,
}

/// A triangulated 3D point.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    pub xyz: Vector3<f64>,
    pub color: [u8; 3],
    /// Mean reprojection error in pixels (as in COLMAP's `points3D` files).
    pub error: f64,
    pub track: Vec<TrackElement>,
}

/// A COLMAP model. Only registered images are written to files.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Reconstruction {
    pub cameras: BTreeMap<CameraId, Camera>,
    pub images: BTreeMap<ImageId, Image>,
    pub points3d: BTreeMap<Point3DId, Point3D>,
}

impl Reconstruction {
    pub fn num_registered_images(&self) -> usize {
        self.images.values().filter(|i| i.is_registered()).count()
    }

    pub fn registered_images(&self) -> impl Iterator<Item = &Image> {
        self.images.values().filter(|i| i.is_registered())
    }

    pub fn image_by_name(&self, name: &str) -> Option<&Image> {
        self.images.values().find(|i| i.name == name)
    }

    /// An image's pose, `None` when it is unknown or not registered.
    pub fn pose(&self, image: ImageId) -> Option<Rigid3> {
        self.images.get(&image).and_then(|i| i.cam_from_world)
    }
}
