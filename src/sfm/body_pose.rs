//! The user's pose convention (method.md section 2) and its conversion to
//! COLMAP's `cam_from_world`.
//!
//! Body frame: x forward (= optical axis), y left, z up;
//! `R_world_from_body = Rz(yaw) * Ry(pitch) * Rx(roll)`; the position is the
//! camera centre in the world (map) frame. The camera frame (x right, y down,
//! z forward) is fixed in the body: `z_cam = x_body`, `x_cam = -y_body`,
//! `y_cam = -z_body`. All zeros: a level camera at the origin looking along +x.
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::scene::Rigid3;

/// A pose in the body convention; angles in degrees (as on the command line).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyPoseDeg {
    /// Camera centre in the map frame, metres.
    pub position_m: Vector3<f64>,
    pub roll_deg: f64,
    pub pitch_deg: f64,
    pub yaw_deg: f64,
}

/// `R_body_from_cam`: columns are the camera axes written in the body frame.
pub fn body_from_cam_rotation() -> Matrix3<f64> {
    Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0)
}

impl BodyPoseDeg {
    /// Parses `x,y,z,roll,pitch,yaw` (metres, degrees).
    pub fn parse(text: &str) -> Result<Self, String> {
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
        Ok(Self {
            position_m: Vector3::new(values[0], values[1], values[2]),
            roll_deg: values[3],
            pitch_deg: values[4],
            yaw_deg: values[5],
        })
    }

    /// COLMAP's `cam_from_world` of this pose.
    pub fn to_cam_from_world(&self) -> Rigid3 {
        let world_from_body = Rotation3::from_euler_angles(
            self.roll_deg.to_radians(),
            self.pitch_deg.to_radians(),
            self.yaw_deg.to_radians(),
        )
        .into_inner();
        let cam_from_world = (world_from_body * body_from_cam_rotation()).transpose();
        let translation = -(cam_from_world * self.position_m);
        Rigid3::from_rotation_matrix(&cam_from_world, translation)
    }

    /// The body pose of a `cam_from_world`.
    pub fn from_cam_from_world(cam_from_world: &Rigid3) -> Self {
        let world_from_cam = cam_from_world.rotation_matrix().transpose();
        let world_from_body = world_from_cam * body_from_cam_rotation().transpose();
        let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(world_from_body).euler_angles();
        Self {
            position_m: cam_from_world.camera_center(),
            roll_deg: roll.to_degrees(),
            pitch_deg: pitch.to_degrees(),
            yaw_deg: yaw.to_degrees(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_pose_looks_along_x() {
        let pose = BodyPoseDeg::parse("1,2,3,0,0,0").unwrap();
        let cam_from_world = pose.to_cam_from_world();
        assert!((cam_from_world.camera_center() - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
        // A point 5 m ahead (+x) lies on the optical axis at depth 5.
        let p = cam_from_world.transform_point(&Vector3::new(6.0, 2.0, 3.0));
        assert!((p - Vector3::new(0.0, 0.0, 5.0)).norm() < 1e-12);
        // A point to the left (+y) has negative x_cam; above (+z) negative y_cam.
        let left = cam_from_world.transform_point(&Vector3::new(6.0, 3.0, 3.0));
        assert!(left.x < -0.9);
        let up = cam_from_world.transform_point(&Vector3::new(6.0, 2.0, 4.0));
        assert!(up.y < -0.9);
    }

    #[test]
    fn yaw_90_looks_along_y_and_round_trips() {
        let pose = BodyPoseDeg::parse("0,0,0,0,0,90").unwrap();
        let p = pose
            .to_cam_from_world()
            .transform_point(&Vector3::new(0.0, 4.0, 0.0));
        assert!((p - Vector3::new(0.0, 0.0, 4.0)).norm() < 1e-12);
        let pose = BodyPoseDeg::parse("5,-1,2,3,-10,40").unwrap();
        let back = BodyPoseDeg::from_cam_from_world(&pose.to_cam_from_world());
        assert!((back.position_m - pose.position_m).norm() < 1e-9);
        assert!((back.roll_deg - 3.0).abs() < 1e-9);
        assert!((back.pitch_deg + 10.0).abs() < 1e-9);
        assert!((back.yaw_deg - 40.0).abs() < 1e-9);
    }

    #[test]
    fn parse_errors() {
        assert!(BodyPoseDeg::parse("1,2,3").is_err());
        assert!(BodyPoseDeg::parse("1,2,3,a,5,6").is_err());
        assert!(BodyPoseDeg::parse("1,2,3,4,5,nan").is_err());
    }
}
