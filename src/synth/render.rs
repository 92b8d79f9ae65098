//! Ray-cast rendering of a scene into a photo-like image.
//!
//! Per pixel: a ray through the (distorted) camera model, nearest-surface hit
//! with correct occlusion, procedural albedo band-limited by the pixel
//! footprint (so textures do not alias); pixels on a geometric or shadow edge
//! (a 4-neighbour sees another surface or shadow state) are re-rendered with
//! `supersample x supersample` rays and averaged (adaptive anti-aliasing); Lambert shading with a directional
//! light (and cast shadows outdoors) plus ambient; then per-image exposure
//! gain, vignetting, gamma encoding and gaussian sensor noise. Rows are
//! rendered in parallel (rayon); the result is deterministic for a seed.
use nalgebra::{Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use super::geometry::Scene;
use super::lens;
use super::texture::{hash64, Rgb};
use crate::scene::{Camera, Rigid3};

/// Photometric settings of one rendered image.
#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    /// Rays per pixel along each axis (anti-aliasing). Default 2.
    pub supersample: u32,
    /// Exposure gain applied to linear radiance. Default 1.
    pub exposure_gain: f32,
    /// Standard deviation of the additive gaussian noise on 8-bit values. Default 2.0.
    pub noise_sigma_u8: f32,
    /// Seed of the sensor noise.
    pub noise_seed: u64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            supersample: 2,
            exposure_gain: 1.0,
            noise_sigma_u8: 2.0,
            noise_seed: 0,
        }
    }
}

/// Ray directions (camera frame, unit length) of every sub-sample, row-major:
/// `(y * ss + j) * width * ss + x * ss + i`. Depends only on the camera.
pub struct RayTable {
    pub width: u32,
    pub height: u32,
    pub supersample: u32,
    rays: Vec<Vector3<f32>>,
    /// One ray through each pixel centre, row-major.
    centre_rays: Vec<Vector3<f32>>,
    /// Size of one pixel on a fronto-parallel surface at 1 m, in metres.
    pixel_angle_rad: f64,
}

impl RayTable {
    pub fn new(camera: &Camera, supersample: u32) -> Self {
        let ss = supersample.max(1);
        let (w, h) = (
            camera.width as usize * ss as usize,
            camera.height as usize * ss as usize,
        );
        let table = |w: usize, h: usize, scale: f64| -> Vec<Vector3<f32>> {
            (0..h)
                .into_par_iter()
                .flat_map_iter(|row| {
                    (0..w).map(move |col| {
                        let px =
                            Vector2::new((col as f64 + 0.5) / scale, (row as f64 + 0.5) / scale);
                        let d = lens::unproject(camera, &px).normalize();
                        Vector3::new(d.x as f32, d.y as f32, d.z as f32)
                    })
                })
                .collect()
        };
        Self {
            width: camera.width,
            height: camera.height,
            supersample: ss,
            rays: table(w, h, f64::from(ss)),
            centre_rays: table(camera.width as usize, camera.height as usize, 1.0),
            pixel_angle_rad: 1.0 / camera.mean_focal_length(),
        }
    }
}

fn sky_colour(dir: &Vector3<f64>) -> Rgb {
    let up = dir.z.clamp(0.0, 1.0) as f32;
    let horizon = [0.78f32, 0.84, 0.9];
    let zenith = [0.32f32, 0.5, 0.82];
    let t = up.sqrt();
    [
        horizon[0] + (zenith[0] - horizon[0]) * t,
        horizon[1] + (zenith[1] - horizon[1]) * t,
        horizon[2] + (zenith[2] - horizon[2]) * t,
    ]
}

/// Linear radiance seen along a world ray, and a key of what was hit
/// (`-1` sky, else `2 * quad + shadowed`) for edge detection.
fn shade(
    scene: &Scene,
    origin: &Vector3<f64>,
    dir: &Vector3<f64>,
    pixel_angle_rad: f64,
) -> (Rgb, i64) {
    let Some(hit) = scene.cast(origin, dir, 1e-4, 1e4) else {
        return (
            if scene.lighting.sky {
                sky_colour(dir)
            } else {
                [0.0; 3]
            },
            -1,
        );
    };
    let quad = &scene.quads[hit.quad];
    let cos_view = quad.normal.dot(dir).abs().max(0.125);
    let footprint_m = hit.t * pixel_angle_rad / cos_view;
    // Textures take the vertical coordinate second on walls.
    let (s_m, t_m) = if quad.u_axis.z.abs() > 0.9 {
        (hit.b_m, hit.a_m)
    } else {
        (hit.a_m, hit.b_m)
    };
    let albedo = quad.texture.albedo(s_m, t_m, footprint_m);
    // The side facing the viewer.
    let normal = if quad.normal.dot(dir) < 0.0 {
        quad.normal
    } else {
        -quad.normal
    };
    let l = &scene.lighting;
    let mut direct = normal.dot(&l.to_light).max(0.0) as f32;
    let mut shadowed = 0;
    if direct > 0.0 && l.shadows {
        let p = origin + dir * hit.t + normal * 1e-6;
        if scene.occluded(&p, &l.to_light, 1e-4, 1e3) {
            direct = 0.0;
            shadowed = 1;
        }
    }
    let k = l.ambient + l.light * direct;
    (
        [albedo[0] * k, albedo[1] * k, albedo[2] * k],
        2 * hit.quad as i64 + shadowed,
    )
}

/// Renders one 8-bit RGB image (row-major, 3 bytes a pixel) seen by a camera
/// with pose `cam_from_world` (scene-local frame).
pub fn render(
    scene: &Scene,
    table: &RayTable,
    cam_from_world: &Rigid3,
    settings: &RenderSettings,
) -> Vec<u8> {
    let (w, h, ss) = (
        table.width as usize,
        table.height as usize,
        table.supersample as usize,
    );
    let world_from_cam = cam_from_world.inverse();
    let rot = world_from_cam.rotation.to_rotation_matrix();
    let origin = world_from_cam.translation;
    let diag = ((w * w + h * h) as f32).sqrt() / 2.0;
    let to_world =
        |d: &Vector3<f32>| rot * Vector3::new(f64::from(d.x), f64::from(d.y), f64::from(d.z));
    // Pass 1: one ray per pixel centre.
    let centre: Vec<(Rgb, i64)> = (0..w * h)
        .into_par_iter()
        .with_min_len(w)
        .map(|i| {
            shade(
                scene,
                &origin,
                &to_world(&table.centre_rays[i]),
                table.pixel_angle_rad,
            )
        })
        .collect();
    let mut out = vec![0u8; w * h * 3];
    out.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let mut rng = ChaCha8Rng::seed_from_u64(hash64(
            settings.noise_seed ^ (y as u64).wrapping_mul(0x9E37),
        ));
        // Normal::new only fails for a negative or NaN sigma; it is clamped to >= 0.
        let noise = Normal::new(0.0f32, settings.noise_sigma_u8.max(0.0)).unwrap();
        for x in 0..w {
            let (mut colour, key) = centre[y * w + x];
            // Pass 2: supersample pixels on an edge.
            let edge = (x > 0 && centre[y * w + x - 1].1 != key)
                || (x + 1 < w && centre[y * w + x + 1].1 != key)
                || (y > 0 && centre[(y - 1) * w + x].1 != key)
                || (y + 1 < h && centre[(y + 1) * w + x].1 != key);
            if edge && ss > 1 {
                let mut acc = [0.0f32; 3];
                for j in 0..ss {
                    let base = (y * ss + j) * w * ss + x * ss;
                    for i in 0..ss {
                        let (c, _) = shade(
                            scene,
                            &origin,
                            &to_world(&table.rays[base + i]),
                            table.pixel_angle_rad,
                        );
                        for k in 0..3 {
                            acc[k] += c[k];
                        }
                    }
                }
                let n = (ss * ss) as f32;
                colour = [acc[0] / n, acc[1] / n, acc[2] / n];
            }
            let r = (((x as f32 + 0.5 - w as f32 / 2.0).powi(2)
                + (y as f32 + 0.5 - h as f32 / 2.0).powi(2))
            .sqrt())
                / diag;
            let vignette = 1.0 - 0.22 * r * r;
            let gain = settings.exposure_gain * vignette;
            for k in 0..3 {
                let linear = (colour[k] * gain).clamp(0.0, 1.0);
                let encoded = linear.powf(1.0 / 2.2) * 255.0 + noise.sample(&mut rng);
                row[x * 3 + k] = encoded.round().clamp(0.0, 255.0) as u8;
            }
        }
    });
    out
}
