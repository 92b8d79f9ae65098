//! Photometric refinement of the tracked keypoints on the map's planes.
//!
//! SIFT places a feature a little differently in each view of it, and the
//! errors a track's views share (and neighbouring tracks alike) move the few
//! surfaces that hold a direction of the model, which the map's planes then
//! pass on to the whole model (`docs/results.md`, session 77). Here each
//! track on a plane keeps its most head-on view's keypoint as the reference;
//! a square patch of that image around it is carried through the plane to
//! every other view of the track (each patch pixel's ray cut with the plane,
//! projected into the other view with its pose and camera), and the other
//! view's keypoint becomes where that patch fits best: the translation that
//! minimises the difference of the two zero-mean, unit-norm patches
//! (Gauss-Newton from the SIFT keypoint). So a track's keypoints agree on
//! the image content, not on where SIFT put each. A position is kept only
//! where the patches correlate by [`KeypointOptions::min_ncc`] and it moved
//! at most [`KeypointOptions::max_shift_px`].
use std::collections::BTreeMap;
use std::path::Path;

use image::GrayImage;
use nalgebra::{Matrix2, Vector2, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use crate::io::database::DatabaseSnapshot;
use crate::io::images::{read_gray, ExpectedImage};
use crate::scene::{Camera, ImageId, Point3DId, Rigid3};
use crate::sfm::options::KeypointOptions;
use crate::sfm::state::{MapState, PointPlane};

/// The images' grey values, 8 bits, by image id.
#[derive(Default)]
pub struct GrayImages {
    images: BTreeMap<ImageId, GrayImage>,
}

impl GrayImages {
    /// The images `ids` of `db` from the folder `dir` as grey values, read
    /// in parallel; an image that cannot be read is left out with a warning
    /// (its keypoints keep SIFT's positions).
    pub fn read(dir: &Path, db: &DatabaseSnapshot, ids: &[ImageId]) -> Self {
        let read: Vec<_> = ids
            .par_iter()
            .filter_map(|id| {
                let img = db.images.get(id)?;
                let expected = ExpectedImage::new(&img.name, db.cameras.get(&img.camera_id)?);
                Some((*id, read_gray(dir, &expected)))
            })
            .collect();
        let mut images = BTreeMap::new();
        for (id, result) in read {
            match result {
                Ok(gray) => {
                    images.insert(id, gray);
                }
                Err(e) => log::warn!("{e}: its keypoints are not refined"),
            }
        }
        Self { images }
    }

    pub fn get(&self, id: ImageId) -> Option<&GrayImage> {
        self.images.get(&id)
    }

    pub fn len(&self) -> usize {
        self.images.len()
    }

    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }
}

/// Megabytes (2^20 bytes) the grey values of the images `ids` of `db`
/// take: a byte a pixel.
pub fn gray_megabytes(db: &DatabaseSnapshot, ids: &[ImageId]) -> f64 {
    ids.iter()
        .filter_map(|id| db.cameras.get(&db.images.get(id)?.camera_id))
        .map(|c| f64::from(c.width) * f64::from(c.height))
        .sum::<f64>()
        / f64::from(1u32 << 20)
}

/// What the refinement did (`report.json` → `keypoint_refinement`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RefinementRecord {
    /// The registered images read as grey values, the megabytes they take
    /// and the seconds reading them took (the images are read for the
    /// refinement and dropped after it).
    pub images_read: usize,
    pub image_memory_mb: f64,
    pub read_seconds: f64,
    /// Not refined: the registered images would take more than
    /// `keypoints.max_image_memory_mb` as grey values.
    pub over_memory_budget: bool,
    /// Tracks on a plane with at least two views in loaded images.
    pub tracks: usize,
    /// Their observations other than the reference views.
    pub observations: usize,
    /// Observations given a refined position.
    pub refined: usize,
    /// Left at SIFT's position: the patches correlated less than `min_ncc`
    /// (or the patch left the image, or the alignment did not converge).
    pub low_correlation: usize,
    /// Left at SIFT's position: the fit lay farther than `max_shift_px`.
    pub too_far: usize,
    /// Median distance of a refined position from SIFT's, pixels.
    pub median_shift_px: f64,
    /// The final rounds' camera-centre median move after the refinement,
    /// metres (filled in by the mapper).
    pub median_camera_move_m: Option<f64>,
    pub seconds: f64,
}

/// Grey value at `(x, y)` (COLMAP pixel convention: centres at +0.5),
/// bilinear; `None` unless the four pixels around it are in the image.
fn sample(image: &GrayImage, x: f64, y: f64) -> Option<f64> {
    let (u, v) = (x - 0.5, y - 0.5);
    let (w, h) = image.dimensions();
    if !(u >= 0.0 && v >= 0.0 && u < f64::from(w) - 1.0 && v < f64::from(h) - 1.0) {
        return None;
    }
    let (x0, y0) = (u.floor() as u32, v.floor() as u32);
    let (fx, fy) = (u - f64::from(x0), v - f64::from(y0));
    let px = |x: u32, y: u32| f64::from(image.get_pixel(x, y).0[0]);
    let top = px(x0, y0) * (1.0 - fx) + px(x0 + 1, y0) * fx;
    let bottom = px(x0, y0 + 1) * (1.0 - fx) + px(x0 + 1, y0 + 1) * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

/// The grey value at `(x, y)` ([`sample`]) and its gradient there: the
/// Sobel filter (a central difference over two pixels, smoothed across it
/// by 1 2 1, over 8) of the bilinear image, which is the bilinear
/// interpolation of the Sobel-filtered image, so both come from the 4 x 4
/// pixels around the point. Gauss-Newton on it converged closer than on the
/// difference of bilinear samples half a pixel either side: the seed-0
/// 24-image corridor mapped at 0.91 against 1.70 mm, the room at 0.67
/// against 0.74 mm, and four other scenes the same or better (session 78).
/// `None` unless those pixels are in the image.
fn sample_with_gradient(image: &GrayImage, x: f64, y: f64) -> Option<(f64, Vector2<f64>)> {
    let (u, v) = (x - 0.5, y - 0.5);
    let (w, h) = image.dimensions();
    if !(u >= 1.0 && v >= 1.0 && u < f64::from(w) - 2.0 && v < f64::from(h) - 2.0) {
        return None;
    }
    let (x0, y0) = (u.floor() as u32, v.floor() as u32);
    let (fx, fy) = (u - f64::from(x0), v - f64::from(y0));
    // p[j][i]: the pixel (x0 - 1 + i, y0 - 1 + j).
    let (raw, w) = (image.as_raw(), w as usize);
    let corner = (y0 as usize - 1) * w + x0 as usize - 1;
    let p: [[f64; 4]; 4] =
        std::array::from_fn(|j| std::array::from_fn(|i| f64::from(raw[corner + j * w + i])));
    // Sobel at the block's pixel (i, j), 1 <= i, j <= 2.
    let sobel = |i: usize, j: usize| {
        Vector2::new(
            (p[j - 1][i + 1] + 2.0 * p[j][i + 1] + p[j + 1][i + 1]
                - p[j - 1][i - 1]
                - 2.0 * p[j][i - 1]
                - p[j + 1][i - 1])
                / 8.0,
            (p[j + 1][i - 1] + 2.0 * p[j + 1][i] + p[j + 1][i + 1]
                - p[j - 1][i - 1]
                - 2.0 * p[j - 1][i]
                - p[j - 1][i + 1])
                / 8.0,
        )
    };
    let (a, b, c, d) = (
        (1.0 - fx) * (1.0 - fy),
        fx * (1.0 - fy),
        (1.0 - fx) * fy,
        fx * fy,
    );
    let value = a * p[1][1] + b * p[1][2] + c * p[2][1] + d * p[2][2];
    let gradient = sobel(1, 1) * a + sobel(2, 1) * b + sobel(1, 2) * c + sobel(2, 2) * d;
    Some((value, gradient))
}

/// `values` minus their mean, scaled to unit norm; `None` for a flat patch.
fn normalised(values: &[f64]) -> Option<(Vec<f64>, f64)> {
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    let centred: Vec<f64> = values.iter().map(|v| v - mean).collect();
    let norm = centred.iter().map(|v| v * v).sum::<f64>().sqrt();
    // Less than about a grey level of contrast over the patch: no texture.
    (norm > 1.0).then(|| (centred.iter().map(|v| v / norm).collect(), norm))
}

/// A view of a track: its image, camera, pose and keypoint.
#[derive(Clone, Copy)]
pub struct View<'a> {
    pub image: &'a GrayImage,
    pub camera: &'a Camera,
    pub cam_from_world: &'a Rigid3,
    pub keypoint: Vector2<f64>,
}

/// The reference patch: each pixel's point on the plane and the patch's
/// normalised grey values.
pub struct Patch {
    world: Vec<Vector3<f64>>,
    values: Vec<f64>,
}

/// The `(2 half + 1)^2` pixel patch of `view` around its keypoint, on the
/// plane; `None` where a ray misses the plane (or meets it behind the
/// camera), the patch leaves the image or has no texture.
pub fn reference_patch(view: &View, plane: &PointPlane, half: u32) -> Option<Patch> {
    let world_from_cam = view.cam_from_world.inverse();
    let centre = world_from_cam.translation;
    let h = half as i32;
    let mut world = Vec::with_capacity(((2 * h + 1) * (2 * h + 1)) as usize);
    let mut values = Vec::with_capacity(world.capacity());
    for dy in -h..=h {
        for dx in -h..=h {
            let pixel = view.keypoint + Vector2::new(f64::from(dx), f64::from(dy));
            values.push(sample(view.image, pixel.x, pixel.y)?);
            let ray = world_from_cam.rotation * view.camera.unproject(&pixel)?;
            let denom = plane.normal.dot(&ray);
            let s = (plane.offset_m - plane.normal.dot(&centre)) / denom;
            if !(s.is_finite() && s > 0.0) {
                return None;
            }
            world.push(centre + ray * s);
        }
    }
    let (values, _) = normalised(&values)?;
    Some(Patch { world, values })
}

/// Gauss-Newton steps at most, and the step below which it has converged
/// (pixels).
const MAX_STEPS: usize = 12;
const CONVERGED_PX: f64 = 1e-3;

/// Where `patch` fits best in `view`, from its keypoint: the position of
/// the patch's centre and the patches' normalised cross-correlation there.
/// `None` when a patch point falls outside the image or behind the camera,
/// or the alignment does not converge (or goes more than a pixel beyond
/// `max_shift_px` from the keypoint, where it could not be kept).
pub fn align(patch: &Patch, view: &View, max_shift_px: f64) -> Option<(Vector2<f64>, f64)> {
    let projected: Vec<Vector2<f64>> = patch
        .world
        .iter()
        .map(|w| view.camera.project(&view.cam_from_world.transform_point(w)))
        .collect::<Option<_>>()?;
    let middle = projected[projected.len() / 2];
    let mut shift = view.keypoint - middle;
    let n = projected.len();
    let mut values = vec![0.0; n];
    let mut grads = vec![Vector2::zeros(); n];
    for step in 0..=MAX_STEPS {
        for (k, q) in projected.iter().enumerate() {
            let p = q + shift;
            (values[k], grads[k]) = sample_with_gradient(view.image, p.x, p.y)?;
        }
        let (z, norm) = normalised(&values)?;
        if step == MAX_STEPS {
            return None;
        }
        // d z / d shift: the gradients without their mean, without their
        // part along z, over the norm.
        let mean = grads.iter().sum::<Vector2<f64>>() / n as f64;
        let along = z
            .iter()
            .zip(&grads)
            .fold(Vector2::zeros(), |acc: Vector2<f64>, (zk, g)| {
                acc + (g - mean) * *zk
            });
        let mut jtj = Matrix2::zeros();
        let mut jtr = Vector2::zeros();
        for k in 0..n {
            let j = ((grads[k] - mean) - along * z[k]) / norm;
            jtj += j * j.transpose();
            jtr += j * (patch.values[k] - z[k]);
        }
        let delta = jtj.try_inverse()? * jtr;
        shift += delta;
        // Gone farther than a pixel past what could be kept: diverging.
        if (middle + shift - view.keypoint).norm() > max_shift_px + 1.0 {
            return None;
        }
        if delta.norm() < CONVERGED_PX {
            let p = middle + shift;
            // The correlation at the converged position.
            let at: Vec<f64> = projected
                .iter()
                .map(|q| sample(view.image, q.x + shift.x, q.y + shift.y))
                .collect::<Option<_>>()?;
            let (z, _) = normalised(&at)?;
            let ncc_end: f64 = z.iter().zip(&patch.values).map(|(a, b)| a * b).sum();
            return Some((p, ncc_end));
        }
    }
    None
}

/// One refined keypoint: image, keypoint index, new position.
pub type RefinedKeypoint = (ImageId, u32, Vector2<f64>);

/// One track's refinement: its observations besides the reference, the
/// refined ones with their shifts, and how many correlated too little or
/// moved too far.
type TrackRefinement = (usize, Vec<(RefinedKeypoint, f64)>, usize, usize);

/// The refined positions of the tracked keypoints of `state`'s points tied
/// to a plane (the plane of their latest solve), and what was done.
pub fn refine_keypoints(
    state: &MapState,
    images: &GrayImages,
    options: &KeypointOptions,
) -> (Vec<RefinedKeypoint>, RefinementRecord) {
    let start = std::time::Instant::now();
    let points: Vec<Point3DId> = state
        .points
        .iter()
        .filter(|(_, p)| p.plane.is_some() && p.track.len() >= 2)
        .map(|(id, _)| *id)
        .collect();
    let per_point: Vec<TrackRefinement> = points
        .par_iter()
        .filter_map(|id| {
            let p = &state.points[id];
            let plane = p.plane.as_ref()?;
            let views: Vec<(ImageId, u32, View)> = p
                .track
                .iter()
                .filter_map(|e| {
                    let img = state.images.get(&e.image_id)?;
                    let pose = img.cam_from_world.as_ref()?;
                    let camera = &state.cameras[&state.intrinsics_of(img.camera_id)];
                    Some((
                        e.image_id,
                        e.point2d_idx,
                        View {
                            image: images.get(e.image_id)?,
                            camera,
                            cam_from_world: pose,
                            keypoint: state.keypoint(*e),
                        },
                    ))
                })
                .collect();
            if views.len() < 2 {
                return None;
            }
            // The most head-on view is the reference.
            let incidence = |v: &View| {
                let centre = v.cam_from_world.inverse().translation;
                let ray = centre - p.xyz;
                plane.normal.dot(&ray).abs() / ray.norm().max(1e-12)
            };
            let reference = (0..views.len())
                .max_by(|&a, &b| incidence(&views[a].2).total_cmp(&incidence(&views[b].2)))?;
            let patch = reference_patch(&views[reference].2, plane, options.patch_half_px);
            let mut refined = Vec::new();
            let (mut low, mut far) = (0, 0);
            for (k, (image, idx, view)) in views.iter().enumerate() {
                if k == reference {
                    continue;
                }
                let fit = patch
                    .as_ref()
                    .and_then(|patch| align(patch, view, options.max_shift_px));
                match fit {
                    Some((q, ncc)) if ncc >= options.min_ncc => {
                        let shift = (q - view.keypoint).norm();
                        if shift <= options.max_shift_px {
                            refined.push(((*image, *idx, q), shift));
                        } else {
                            far += 1;
                        }
                    }
                    _ => low += 1,
                }
            }
            Some((views.len() - 1, refined, low, far))
        })
        .collect();
    let mut record = RefinementRecord::default();
    let mut out = Vec::new();
    let mut shifts = Vec::new();
    for (observations, refined, low, far) in per_point {
        record.tracks += 1;
        record.observations += observations;
        record.low_correlation += low;
        record.too_far += far;
        for (r, shift) in refined {
            out.push(r);
            shifts.push(shift);
        }
    }
    record.refined = out.len();
    if !shifts.is_empty() {
        record.median_shift_px = crate::sfm::associate::median_in_place(&mut shifts);
    }
    record.seconds = start.elapsed().as_secs_f64();
    (out, record)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraId, CameraModel};
    use nalgebra::{Rotation3, UnitQuaternion};

    fn camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::from_name("SIMPLE_RADIAL").expect("known model"),
            width: 240,
            height: 200,
            params: vec![300.0, 120.0, 100.0, -0.03],
        }
    }

    /// A texture on the floor z = 0 (grey values 28-228; periods of 6-11
    /// cm, 10-20 pixels in the views below).
    fn texture(x: f64, y: f64) -> f64 {
        128.0 + 60.0 * (70.0 * x).sin() * (55.0 * y).cos() + 40.0 * (90.0 * x + 40.0 * y).sin()
    }

    /// The floor seen from `centre`, looking down and tilted `tilt_deg`
    /// about the x axis (pixel centres sampled, no blur).
    fn view(
        centre: Vector3<f64>,
        tilt_deg: f64,
        texture: impl Fn(f64, f64) -> f64,
    ) -> (Rigid3, GrayImage) {
        // Camera z down (toward the floor), tilted about x.
        let down = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let tilt = Rotation3::from_axis_angle(&Vector3::x_axis(), tilt_deg.to_radians());
        let world_from_cam = UnitQuaternion::from_rotation_matrix(&(tilt * down));
        let cam_from_world = Rigid3::new(
            world_from_cam.inverse(),
            -(world_from_cam.inverse() * centre),
        );
        let cam = camera();
        let image = GrayImage::from_fn(cam.width, cam.height, |u, v| {
            let pixel = Vector2::new(f64::from(u) + 0.5, f64::from(v) + 0.5);
            let ray = world_from_cam * cam.unproject(&pixel).unwrap();
            let s = -centre.z / ray.z;
            let p = centre + ray * s;
            image::Luma([texture(p.x, p.y).round().clamp(0.0, 255.0) as u8])
        });
        (cam_from_world, image)
    }

    /// The value and Sobel gradient from the 4 x 4 block are the bilinear
    /// samples' (the value) and the Sobel weights over bilinear samples one
    /// pixel apart (the gradient); none within a pixel and a half of the
    /// border.
    #[test]
    fn the_gradient_is_the_sobel_filter_of_the_bilinear_image() {
        let cam = camera();
        let image = GrayImage::from_fn(cam.width, cam.height, |u, v| {
            let t = texture(f64::from(u) / 97.0, f64::from(v) / 83.0);
            image::Luma([t.round().clamp(0.0, 255.0) as u8])
        });
        let at = |x: f64, y: f64| sample(&image, x, y).unwrap();
        for (x, y) in [(1.5, 1.5), (20.25, 30.75), (100.9, 7.1), (237.49, 197.49)] {
            let (value, g) = sample_with_gradient(&image, x, y).unwrap();
            let gx = (at(x + 1.0, y - 1.0) + 2.0 * at(x + 1.0, y) + at(x + 1.0, y + 1.0)
                - at(x - 1.0, y - 1.0)
                - 2.0 * at(x - 1.0, y)
                - at(x - 1.0, y + 1.0))
                / 8.0;
            let gy = (at(x - 1.0, y + 1.0) + 2.0 * at(x, y + 1.0) + at(x + 1.0, y + 1.0)
                - at(x - 1.0, y - 1.0)
                - 2.0 * at(x, y - 1.0)
                - at(x + 1.0, y - 1.0))
                / 8.0;
            assert!((value - at(x, y)).abs() < 1e-9, "{x} {y}");
            assert!((g - Vector2::new(gx, gy)).norm() < 1e-9, "{x} {y}: {g:?}");
        }
        for (x, y) in [(1.49, 50.0), (50.0, 1.4), (238.5, 50.0), (50.0, 198.5)] {
            assert!(sample_with_gradient(&image, x, y).is_none(), "{x} {y}");
        }
    }

    #[test]
    fn the_registered_images_are_read_as_grey_values_and_their_size_counted() {
        use crate::io::database::DbImage;
        let dir = tempfile::tempdir().expect("temp dir");
        let cam = camera();
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(cam.id, cam.clone());
        for (id, name) in [(1, "a.png"), (2, "b.png"), (3, "c.png"), (4, "d.png")] {
            db.images.insert(
                ImageId(id),
                DbImage {
                    id: ImageId(id),
                    name: name.to_owned(),
                    camera_id: cam.id,
                },
            );
        }
        // a: right size, b: the wrong size, c: missing, d: right size.
        let rgb = |w, h| image::RgbImage::from_pixel(w, h, image::Rgb([30, 60, 90]));
        rgb(cam.width, cam.height)
            .save(dir.path().join("a.png"))
            .expect("a");
        rgb(cam.width + 1, cam.height)
            .save(dir.path().join("b.png"))
            .expect("b");
        rgb(cam.width, cam.height)
            .save(dir.path().join("d.png"))
            .expect("d");
        let ids = [ImageId(1), ImageId(2), ImageId(3)];
        let gray = GrayImages::read(dir.path(), &db, &ids);
        // Only a: b is refused for its size, c is missing, d was not asked for.
        assert_eq!(gray.len(), 1);
        let a = gray.get(ImageId(1)).expect("a read");
        assert_eq!(a.dimensions(), (240, 200));
        // Luma of (30, 60, 90): (2126 * 30 + 7152 * 60 + 722 * 90) / 10000.
        assert_eq!(a.get_pixel(10, 10).0[0], 56);
        assert!(gray.get(ImageId(4)).is_none());
        // Three 240 x 200 images, a byte a pixel; an unknown id counts nothing.
        let mb = gray_megabytes(&db, &[ImageId(1), ImageId(2), ImageId(3), ImageId(9)]);
        assert!((mb - 3.0 * 48_000.0 / 1_048_576.0).abs() < 1e-12, "{mb}");
    }

    #[test]
    fn a_keypoint_off_by_most_of_a_pixel_comes_back_to_the_image_content() {
        let cam = camera();
        let floor = PointPlane {
            family: crate::solver::PlaneFamily::Ground,
            normal: Vector3::z(),
            offset_m: 0.0,
        };
        let (pose_a, image_a) = view(Vector3::new(0.0, 0.0, 2.0), 0.0, texture);
        let (pose_b, image_b) = view(Vector3::new(0.4, -0.9, 1.6), 25.0, texture);
        let point = Vector3::new(0.1, -0.05, 0.0);
        let seen = |pose: &Rigid3| cam.project(&pose.transform_point(&point)).unwrap();
        let (at_a, at_b) = (seen(&pose_a), seen(&pose_b));
        let reference = View {
            image: &image_a,
            camera: &cam,
            cam_from_world: &pose_a,
            keypoint: at_a,
        };
        let patch = reference_patch(&reference, &floor, 7).expect("textured, on the floor");
        for start in [
            Vector2::new(0.6, -0.4),
            Vector2::new(-0.8, 0.3),
            Vector2::zeros(),
        ] {
            let other = View {
                image: &image_b,
                camera: &cam,
                cam_from_world: &pose_b,
                keypoint: at_b + start,
            };
            let (fit, ncc) = align(&patch, &other, 1.5).expect("converges");
            assert!(
                (fit - at_b).norm() < 0.02,
                "from {start:?}: {fit:?} for {at_b:?}"
            );
            assert!(ncc > 0.97, "{ncc}");
        }
        // Another texture there: the patches do not correlate.
        let (_, elsewhere) = view(Vector3::new(0.4, -0.9, 1.6), 25.0, |x, y| {
            texture(y + 3.0, x)
        });
        let other = View {
            image: &elsewhere,
            camera: &cam,
            cam_from_world: &pose_b,
            keypoint: at_b,
        };
        let ncc = align(&patch, &other, 1.5).map_or(-1.0, |(_, ncc)| ncc);
        assert!(ncc < 0.8, "{ncc}");
        // A flat image gives no reference patch, and one at the border none.
        let flat = GrayImage::from_pixel(cam.width, cam.height, image::Luma([90]));
        let flat_view = View {
            image: &flat,
            ..reference
        };
        assert!(reference_patch(&flat_view, &floor, 7).is_none());
        let border = View {
            keypoint: Vector2::new(4.0, 50.0),
            ..reference
        };
        assert!(reference_patch(&border, &floor, 7).is_none());
    }
}
