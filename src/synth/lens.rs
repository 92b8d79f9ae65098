//! The rendering camera: pixel <-> ray through a COLMAP camera model.
//!
//! This is the one place the synthetic renderer touches camera models: it
//! delegates to [`Camera::project`] / [`Camera::unproject`]. The generator
//! offers the models listed in [`SUPPORTED_MODELS`].
use nalgebra::{Vector2, Vector3};

use crate::scene::{Camera, CameraModel};

/// Camera models the generator can render with.
pub const SUPPORTED_MODELS: [CameraModel; 7] = [
    CameraModel::SimplePinhole,
    CameraModel::Pinhole,
    CameraModel::SimpleRadial,
    CameraModel::Radial,
    CameraModel::OpenCv,
    CameraModel::SimpleRadialFisheye,
    CameraModel::OpenCvFisheye,
];

/// Pixel coordinates of a point in the camera frame; `None` behind the camera.
pub fn project(camera: &Camera, point_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
    camera.project(point_in_cam)
}

/// Ray direction (z = 1) of a pixel. For the supported models with the mild
/// distortion the generator uses, undistortion always converges (a fisheye's
/// field of view is checked to stay below 180 degrees when the options are
/// validated); the undistorted-pinhole ray is a fallback that keeps rendering total.
pub fn unproject(camera: &Camera, pixel: &Vector2<f64>) -> Vector3<f64> {
    camera.unproject(pixel).unwrap_or_else(|| {
        let f = camera.mean_focal_length();
        let c = camera.principal_point();
        Vector3::new((pixel.x - c.x) / f, (pixel.y - c.y) / f, 1.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::CameraId;

    #[test]
    fn round_trip_all_supported_models() {
        let params = |m: CameraModel| -> Vec<f64> {
            match m {
                CameraModel::SimplePinhole => vec![500.0, 320.0, 240.0],
                CameraModel::Pinhole => vec![500.0, 510.0, 321.0, 239.0],
                CameraModel::SimpleRadial => vec![500.0, 320.0, 240.0, -0.05],
                CameraModel::Radial => vec![500.0, 320.0, 240.0, -0.05, 0.01],
                CameraModel::SimpleRadialFisheye => vec![280.0, 320.0, 240.0, 0.02],
                CameraModel::OpenCvFisheye => {
                    vec![280.0, 281.0, 321.0, 239.0, 0.03, -0.01, 0.002, -0.001]
                }
                _ => vec![500.0, 505.0, 320.0, 240.0, -0.05, 0.01, 0.001, -0.0005],
            }
        };
        for model in SUPPORTED_MODELS {
            let cam = Camera {
                id: CameraId(1),
                model,
                width: 640,
                height: 480,
                params: params(model),
            };
            for (u, v) in [(0.0, 0.0), (640.0, 480.0), (100.5, 400.25), (320.0, 240.0)] {
                let ray = unproject(&cam, &Vector2::new(u, v));
                let back = project(&cam, &(ray * 3.7)).unwrap();
                assert!(
                    (back - Vector2::new(u, v)).norm() < 1e-8,
                    "{model:?} {u} {v} {back}"
                );
            }
        }
        // Hand-computed SIMPLE_RADIAL: x = 0.2, y = 0 -> r2 = 0.04, u = f*(0.2*(1 - 0.05*0.04)) + cx.
        let cam = Camera {
            id: CameraId(1),
            model: CameraModel::SimpleRadial,
            width: 640,
            height: 480,
            params: params(CameraModel::SimpleRadial),
        };
        let px = project(&cam, &Vector3::new(0.2, 0.0, 1.0)).unwrap();
        assert!((px.x - (500.0 * 0.2 * (1.0 - 0.05 * 0.04) + 320.0)).abs() < 1e-12);
    }
}
