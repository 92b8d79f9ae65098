//! Rigid transforms with their frames in their names.
//!
//! Convention (COLMAP): an image stores `cam_from_world`, so that
//! `X_cam = R * X_world + t`. Camera frame: x right, y down, z forward.
//! Quaternions are written QW QX QY QZ in COLMAP's files.
use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};

/// A rigid transform `b_from_a`: maps coordinates in frame `a` to frame `b`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rigid3 {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Default for Rigid3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Rigid3 {
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
        }
    }

    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// From COLMAP's text order: qw qx qy qz tx ty tz. The quaternion is normalised.
    pub fn from_colmap(q_wxyz: [f64; 4], t: [f64; 3]) -> Self {
        let q = nalgebra::Quaternion::new(q_wxyz[0], q_wxyz[1], q_wxyz[2], q_wxyz[3]);
        Self {
            rotation: UnitQuaternion::from_quaternion(q),
            translation: Vector3::from(t),
        }
    }

    /// COLMAP's order: qw qx qy qz.
    pub fn quaternion_wxyz(&self) -> [f64; 4] {
        let q = self.rotation.quaternion();
        [q.w, q.i, q.j, q.k]
    }

    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        self.rotation.to_rotation_matrix().into_inner()
    }

    /// Applies the transform to a point.
    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    pub fn transform_point3(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.transform_point(&p.coords))
    }

    /// `a_from_b` for a `b_from_a`.
    pub fn inverse(&self) -> Self {
        let inv = self.rotation.inverse();
        Self {
            rotation: inv,
            translation: -(inv * self.translation),
        }
    }

    /// Composition: `c_from_a = c_from_b.compose(b_from_a)`.
    pub fn compose(&self, b_from_a: &Rigid3) -> Self {
        Self {
            rotation: self.rotation * b_from_a.rotation,
            translation: self.rotation * b_from_a.translation + self.translation,
        }
    }

    /// For a `cam_from_world`: the camera centre in world coordinates.
    pub fn camera_center(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }

    /// The `cam_from_world` with this rotation whose camera centre is
    /// `centre` (world coordinates): the inverse of [`Self::camera_center`].
    pub fn from_rotation_and_center(rotation: UnitQuaternion<f64>, centre: &Vector3<f64>) -> Self {
        Self::new(rotation, -(rotation * centre))
    }

    pub fn from_rotation_matrix(r: &Matrix3<f64>, t: Vector3<f64>) -> Self {
        let rot = Rotation3::from_matrix_unchecked(*r);
        Self {
            rotation: UnitQuaternion::from_rotation_matrix(&rot),
            translation: t,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_and_centre() {
        let r = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        let cam_from_world = Rigid3::new(r, Vector3::new(1.0, 2.0, 3.0));
        let centre = cam_from_world.camera_center();
        // The centre maps to the camera origin.
        assert!(cam_from_world.transform_point(&centre).norm() < 1e-12);
        let world_from_cam = cam_from_world.inverse();
        assert!((world_from_cam.translation - centre).norm() < 1e-12);
        let id = cam_from_world.compose(&world_from_cam);
        assert!(id.translation.norm() < 1e-12 && id.rotation.angle() < 1e-12);
    }
}
