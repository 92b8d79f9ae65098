//! Body poses in the map convention of method.md section 2, and their conversion
//! to and from COLMAP's `cam_from_world`.
//!
//! Body frame: x forward (the optical axis), y left, z up.
//! `R_world_from_body = Rz(yaw) * Ry(pitch) * Rx(roll)`; the position is the camera
//! centre in world coordinates. The camera frame (x right, y down, z forward) is
//! fixed in the body: `z_cam = x_body`, `x_cam = -y_body`, `y_cam = -z_body`.
//! All zeros is a level camera at the origin looking along +x. With this
//! convention a positive pitch tilts the optical axis down (towards -z).
//! Used by `map --init-pose` and by the synthetic scenes (`init_pose.txt`).
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::scene::Rigid3;

/// A pose in the body convention. Angles in radians.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyPose {
    /// Camera centre in world coordinates, metres.
    pub position_m: Vector3<f64>,
    pub roll_rad: f64,
    pub pitch_rad: f64,
    pub yaw_rad: f64,
}

/// `R_body_from_cam`: its columns are the camera axes written in the body frame.
pub fn body_from_cam_rotation() -> Matrix3<f64> {
    Matrix3::new(
        0.0, 0.0, 1.0, //
        -1.0, 0.0, 0.0, //
        0.0, -1.0, 0.0,
    )
}

impl BodyPose {
    /// From degrees, as given on the command line.
    pub fn from_degrees(
        position_m: Vector3<f64>,
        roll_deg: f64,
        pitch_deg: f64,
        yaw_deg: f64,
    ) -> Self {
        Self {
            position_m,
            roll_rad: roll_deg.to_radians(),
            pitch_rad: pitch_deg.to_radians(),
            yaw_rad: yaw_deg.to_radians(),
        }
    }

    /// Parses `x,y,z,roll,pitch,yaw` (metres, degrees), as on the command line.
    pub fn parse_degrees(text: &str) -> Result<Self, String> {
        let values: Vec<f64> = text
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("`{text}`: expected six numbers x,y,z,roll,pitch,yaw"))?;
        if values.len() != 6 {
            return Err(format!(
                "`{text}`: expected six numbers x,y,z,roll,pitch,yaw, got {}",
                values.len()
            ));
        }
        if values.iter().any(|v| !v.is_finite()) {
            return Err(format!("`{text}`: every value must be finite"));
        }
        Ok(Self::from_degrees(
            Vector3::new(values[0], values[1], values[2]),
            values[3],
            values[4],
            values[5],
        ))
    }

    /// `[x, y, z, roll_deg, pitch_deg, yaw_deg]`.
    pub fn to_degrees_array(&self) -> [f64; 6] {
        [
            self.position_m.x,
            self.position_m.y,
            self.position_m.z,
            self.roll_rad.to_degrees(),
            self.pitch_rad.to_degrees(),
            self.yaw_rad.to_degrees(),
        ]
    }

    /// `R_world_from_body = Rz(yaw) Ry(pitch) Rx(roll)`.
    pub fn world_from_body_rotation(&self) -> Matrix3<f64> {
        Rotation3::from_euler_angles(self.roll_rad, self.pitch_rad, self.yaw_rad).into_inner()
    }

    /// COLMAP's `cam_from_world` for this body pose.
    pub fn to_cam_from_world(&self) -> Rigid3 {
        let world_from_cam = self.world_from_body_rotation() * body_from_cam_rotation();
        let cam_from_world = world_from_cam.transpose();
        let translation = -(cam_from_world * self.position_m);
        Rigid3::from_rotation_matrix(&cam_from_world, translation)
    }

    /// The body pose of a `cam_from_world`. At pitch = +-90 deg roll and yaw are
    /// not separable; nalgebra then puts the whole heading into yaw... the
    /// returned pose still maps to the same `cam_from_world`.
    pub fn from_cam_from_world(cam_from_world: &Rigid3) -> Self {
        let world_from_cam = cam_from_world.rotation_matrix().transpose();
        let world_from_body = world_from_cam * body_from_cam_rotation().transpose();
        let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(world_from_body).euler_angles();
        Self {
            position_m: cam_from_world.camera_center(),
            roll_rad: roll,
            pitch_rad: pitch,
            yaw_rad: yaw,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_pose_looks_along_plus_x() {
        let pose = BodyPose::from_degrees(Vector3::new(1.0, 2.0, 3.0), 0.0, 0.0, 0.0);
        let cam_from_world = pose.to_cam_from_world();
        // A point 5 m ahead along +x is on the optical axis at depth 5.
        let p = cam_from_world.transform_point(&Vector3::new(6.0, 2.0, 3.0));
        assert!((p - Vector3::new(0.0, 0.0, 5.0)).norm() < 1e-12);
        // A point to the left (+y) appears at negative x_cam; a point above at negative y_cam.
        let left = cam_from_world.transform_point(&Vector3::new(6.0, 3.0, 3.0));
        assert!((left - Vector3::new(-1.0, 0.0, 5.0)).norm() < 1e-12);
        let up = cam_from_world.transform_point(&Vector3::new(6.0, 2.0, 4.0));
        assert!((up - Vector3::new(0.0, -1.0, 5.0)).norm() < 1e-12);
    }

    #[test]
    fn yaw_90_looks_along_plus_y_and_positive_pitch_looks_down() {
        let pose = BodyPose::from_degrees(Vector3::zeros(), 0.0, 0.0, 90.0);
        let p = pose
            .to_cam_from_world()
            .transform_point(&Vector3::new(0.0, 4.0, 0.0));
        assert!((p - Vector3::new(0.0, 0.0, 4.0)).norm() < 1e-12);
        let pose = BodyPose::from_degrees(Vector3::zeros(), 0.0, 45.0, 0.0);
        let p = pose
            .to_cam_from_world()
            .transform_point(&Vector3::new(1.0, 0.0, -1.0));
        assert!(p.x.abs() < 1e-12 && p.y.abs() < 1e-12 && p.z > 0.0);
    }

    #[test]
    fn parse_degrees_reads_six_finite_numbers() {
        let pose = BodyPose::parse_degrees("1, 2,3,0,-90,180").unwrap();
        assert_eq!(pose.to_degrees_array(), [1.0, 2.0, 3.0, 0.0, -90.0, 180.0]);
        assert!(BodyPose::parse_degrees("1,2,3").is_err());
        assert!(BodyPose::parse_degrees("1,2,3,a,5,6").is_err());
        assert!(BodyPose::parse_degrees("1,2,3,4,5,nan").is_err());
        assert!(BodyPose::parse_degrees("1,2,3,4,5,6,").is_err());
    }

    #[test]
    fn round_trip() {
        let pose =
            BodyPose::from_degrees(Vector3::new(500000.0, 4400000.0, 200.0), 3.0, -7.0, 123.0);
        let back = BodyPose::from_cam_from_world(&pose.to_cam_from_world());
        let a = pose.to_degrees_array();
        let b = back.to_degrees_array();
        for i in 0..3 {
            assert!((a[i] - b[i]).abs() < 1e-6, "{a:?} {b:?}");
        }
        for i in 3..6 {
            assert!((a[i] - b[i]).abs() < 1e-9, "{a:?} {b:?}");
        }
    }
}
