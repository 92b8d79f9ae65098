//! The rendering camera: pixel <-> ray through a COLMAP camera model.
//!
//! This is the one place the synthetic renderer touches camera models. It
//! implements the distortion of the models the generator offers
//! (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV) directly, so the
//! renderer does not wait for `Camera::project/unproject`; once those exist
//! the bodies of [`project`] and [`unproject`] can delegate to them.
use nalgebra::{Vector2, Vector3};

use crate::scene::{Camera, CameraModel};

/// Camera models the generator can render with.
pub const SUPPORTED_MODELS: [CameraModel; 5] = [
    CameraModel::SimplePinhole,
    CameraModel::Pinhole,
    CameraModel::SimpleRadial,
    CameraModel::Radial,
    CameraModel::OpenCv,
];

struct Split {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    /// k1, k2, p1, p2 (zeros where the model has none).
    k: [f64; 4],
}

fn split(camera: &Camera) -> Split {
    let p = &camera.params;
    match camera.model {
        CameraModel::SimplePinhole => Split {
            fx: p[0],
            fy: p[0],
            cx: p[1],
            cy: p[2],
            k: [0.0; 4],
        },
        CameraModel::Pinhole => Split {
            fx: p[0],
            fy: p[1],
            cx: p[2],
            cy: p[3],
            k: [0.0; 4],
        },
        CameraModel::SimpleRadial => Split {
            fx: p[0],
            fy: p[0],
            cx: p[1],
            cy: p[2],
            k: [p[3], 0.0, 0.0, 0.0],
        },
        CameraModel::Radial => Split {
            fx: p[0],
            fy: p[0],
            cx: p[1],
            cy: p[2],
            k: [p[3], p[4], 0.0, 0.0],
        },
        CameraModel::OpenCv => Split {
            fx: p[0],
            fy: p[1],
            cx: p[2],
            cy: p[3],
            k: [p[4], p[5], p[6], p[7]],
        },
        other => panic!(
            "synthetic renderer: unsupported camera model {} (checked by SynthOptions::validate)",
            other.name()
        ),
    }
}

/// Distortion offset added to normalised coordinates (COLMAP's formulas).
fn distortion(k: &[f64; 4], x: f64, y: f64) -> (f64, f64) {
    let (x2, y2, xy) = (x * x, y * y, x * y);
    let r2 = x2 + y2;
    let radial = k[0] * r2 + k[1] * r2 * r2;
    let dx = x * radial + 2.0 * k[2] * xy + k[3] * (r2 + 2.0 * x2);
    let dy = y * radial + 2.0 * k[3] * xy + k[2] * (r2 + 2.0 * y2);
    (dx, dy)
}

/// Pixel coordinates of a point in the camera frame; `None` behind the camera.
pub fn project(camera: &Camera, point_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
    if point_in_cam.z <= 1e-12 {
        return None;
    }
    let s = split(camera);
    let (x, y) = (
        point_in_cam.x / point_in_cam.z,
        point_in_cam.y / point_in_cam.z,
    );
    let (dx, dy) = distortion(&s.k, x, y);
    Some(Vector2::new(s.fx * (x + dx) + s.cx, s.fy * (y + dy) + s.cy))
}

/// Ray direction (z = 1) of a pixel, undoing the distortion by Newton's method.
pub fn unproject(camera: &Camera, pixel: &Vector2<f64>) -> Vector3<f64> {
    let s = split(camera);
    let (xd, yd) = ((pixel.x - s.cx) / s.fx, (pixel.y - s.cy) / s.fy);
    let (mut x, mut y) = (xd, yd);
    for _ in 0..50 {
        let (dx, dy) = distortion(&s.k, x, y);
        let (fx, fy) = (x + dx - xd, y + dy - yd);
        if fx.abs() < 1e-14 && fy.abs() < 1e-14 {
            break;
        }
        // Numerical Jacobian of x + d(x).
        let h = 1e-7;
        let (dxx, dyx) = distortion(&s.k, x + h, y);
        let (dxy, dyy) = distortion(&s.k, x, y + h);
        let j00 = 1.0 + (dxx - dx) / h;
        let j10 = (dyx - dy) / h;
        let j01 = (dxy - dx) / h;
        let j11 = 1.0 + (dyy - dy) / h;
        let det = j00 * j11 - j01 * j10;
        if det.abs() < 1e-12 {
            break;
        }
        x -= (j11 * fx - j01 * fy) / det;
        y -= (-j10 * fx + j00 * fy) / det;
    }
    Vector3::new(x, y, 1.0)
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
