//! The photos themselves: checked against the database's cameras before a
//! run, and read after it to give every 3D point the colour it shows.
//!
//! A point's colour is the mean over its observations of the image's colour
//! at the keypoint, interpolated bilinearly between the four nearest pixel
//! centres (COLMAP's keypoint convention: the upper-left pixel's centre is at
//! (0.5, 0.5)), rounded to 8 bits, as COLMAP's `color_extractor` colours a
//! model (its mapper keeps each point's first colour instead). Gaussian-
//! splatting and NeRF tools start from these colours; without the images
//! the points stay grey.
//!
//! Image names come from the database and may hold subfolders
//! (`cam0/0001.jpg`); they are looked up under the image folder. Formats:
//! JPEG, PNG, TIFF and BMP, told by their first bytes. Images are not turned
//! by their EXIF orientation, as COLMAP's feature extractor does not turn
//! them either.
use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use rayon::prelude::*;

use crate::scene::{Camera, Point3DId, Reconstruction};

/// Why the images could not be used. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageFolderError {
    #[error("the image folder {0} does not exist or is not a folder")]
    NoFolder(PathBuf),
    #[error("{path}: image `{name}` is not in the image folder")]
    Missing { path: PathBuf, name: String },
    #[error("image `{name}` has camera {camera_id}, which the model does not hold")]
    UnknownCamera { name: String, camera_id: u32 },
    #[error("{path}: cannot read the image: {source}")]
    Unreadable {
        path: PathBuf,
        source: image::ImageError,
    },
    #[error(
        "{path}: the image is {width}x{height} pixels, but its camera {camera_id} in the database \
         is {camera_width}x{camera_height} (a different folder, or resized images?)"
    )]
    SizeMismatch {
        path: PathBuf,
        width: u32,
        height: u32,
        camera_id: u32,
        camera_width: u32,
        camera_height: u32,
    },
}

/// An image as the database knows it: its name and its camera's size.
#[derive(Clone, Debug)]
pub struct ExpectedImage<'a> {
    pub name: &'a str,
    pub camera_id: u32,
    pub width: u32,
    pub height: u32,
}

impl<'a> ExpectedImage<'a> {
    /// The image `name` taken with `camera`.
    pub fn new(name: &'a str, camera: &Camera) -> Self {
        ExpectedImage {
            name,
            camera_id: camera.id.0,
            width: camera.width,
            height: camera.height,
        }
    }
}

fn resolve(dir: &Path, name: &str) -> Result<PathBuf, ImageFolderError> {
    let path = dir.join(name);
    if path.is_file() {
        Ok(path)
    } else {
        Err(ImageFolderError::Missing {
            path,
            name: name.to_string(),
        })
    }
}

fn check_size(
    path: &Path,
    (width, height): (u32, u32),
    expected: &ExpectedImage,
) -> Result<(), ImageFolderError> {
    if (width, height) == (expected.width, expected.height) {
        return Ok(());
    }
    Err(ImageFolderError::SizeMismatch {
        path: path.to_path_buf(),
        width,
        height,
        camera_id: expected.camera_id,
        camera_width: expected.width,
        camera_height: expected.height,
    })
}

type Reader = image::ImageReader<std::io::BufReader<std::fs::File>>;

/// Opens `path` with a reader that tells the format from the file's first
/// bytes (the extension only where they do not say), without the crate's
/// default 512 MiB limit on a decoded image (a 100-megapixel 16-bit photo is
/// more), and reads it with `read`; errors name the file.
fn read_image<T>(
    path: &Path,
    read: impl FnOnce(Reader) -> image::ImageResult<T>,
) -> Result<T, ImageFolderError> {
    let open = || -> image::ImageResult<T> {
        let mut reader = image::ImageReader::open(path)?.with_guessed_format()?;
        reader.no_limits();
        read(reader)
    };
    open().map_err(|source| ImageFolderError::Unreadable {
        path: path.to_path_buf(),
        source,
    })
}

/// Checks, before a run, that every image is in `dir`, readable (its header)
/// and of its camera's size; the first problem found is the error.
pub fn check_image_folder<'a>(
    dir: &Path,
    images: impl IntoIterator<Item = ExpectedImage<'a>>,
) -> Result<usize, ImageFolderError> {
    if !dir.is_dir() {
        return Err(ImageFolderError::NoFolder(dir.to_path_buf()));
    }
    let mut count = 0;
    for expected in images {
        let path = resolve(dir, expected.name)?;
        let size = read_image(&path, |r| r.into_dimensions())?;
        check_size(&path, size, &expected)?;
        count += 1;
    }
    Ok(count)
}

/// Reads image `expected` from `dir` as 8-bit RGB, checked against its
/// camera's size; errors name the file.
pub fn read_rgb(dir: &Path, expected: &ExpectedImage) -> Result<RgbImage, ImageFolderError> {
    let path = resolve(dir, expected.name)?;
    let rgb = read_image(&path, |r| r.decode())?.into_rgb8();
    check_size(&path, rgb.dimensions(), expected)?;
    Ok(rgb)
}

/// Reads image `expected` from `dir` as 8-bit grey values (the image
/// crate's luma weights), checked against its camera's size; errors name
/// the file.
pub fn read_gray(dir: &Path, expected: &ExpectedImage) -> Result<GrayImage, ImageFolderError> {
    let path = resolve(dir, expected.name)?;
    let gray = read_image(&path, |r| r.decode())?.into_luma8();
    check_size(&path, gray.dimensions(), expected)?;
    Ok(gray)
}

/// The colour at keypoint `(x, y)` (pixel centres at +0.5), bilinear between
/// the four nearest pixel centres; positions beyond the outermost centres
/// take the border's colour. Black for an empty image.
pub fn sample_bilinear(image: &RgbImage, x: f64, y: f64) -> [f64; 3] {
    let (w, h) = image.dimensions();
    if w == 0 || h == 0 {
        return [0.0; 3];
    }
    let axis = |v: f64, n: u32| -> (u32, u32, f64) {
        let v = (v - 0.5).clamp(0.0, f64::from(n - 1));
        let lo = (v.floor() as u32).min(n.saturating_sub(2));
        let hi = (lo + 1).min(n - 1);
        (lo, hi, v - f64::from(lo))
    };
    let (x0, x1, fx) = axis(x, w);
    let (y0, y1, fy) = axis(y, h);
    let px = |x: u32, y: u32| image.get_pixel(x, y).0;
    let (a, b, c, d) = (px(x0, y0), px(x1, y0), px(x0, y1), px(x1, y1));
    std::array::from_fn(|k| {
        let top = f64::from(a[k]) * (1.0 - fx) + f64::from(b[k]) * fx;
        let bottom = f64::from(c[k]) * (1.0 - fx) + f64::from(d[k]) * fx;
        top * (1.0 - fy) + bottom * fy
    })
}

/// An image left out of the colouring, and why.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct UnreadImage {
    pub name: String,
    pub error: String,
}

/// What colouring did (`report.json` → `point_colours`).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ColourSummary {
    pub images_read: usize,
    pub points_coloured: usize,
    pub observations_sampled: usize,
    /// Images that could not be read after the run (each with the error):
    /// their keypoints gave no colour. The folder was checked before the
    /// run, so these are files cut short or changed since.
    pub unread: Vec<UnreadImage>,
}

/// True when all four pixel centres around keypoint `(x, y)` are in the
/// image (`x - 0.5` in `[0, width - 1)`, the same for y): COLMAP leaves out
/// the keypoints within half a pixel of the border.
fn between_centres(width: u32, height: u32, x: f64, y: f64) -> bool {
    let inside = |v: f64, n: u32| (0.0..f64::from(n) - 1.0).contains(&(v - 0.5));
    inside(x, width) && inside(y, height)
}

type Sample = (Point3DId, [f64; 3], bool);

/// Reads one image and samples it at its keypoints that have a 3D point.
fn sample_image(
    dir: &Path,
    img: &crate::scene::Image,
    expected: &ExpectedImage,
) -> Result<Vec<Sample>, ImageFolderError> {
    let rgb = read_rgb(dir, expected)?;
    let (w, h) = rgb.dimensions();
    Ok(img
        .points2d
        .iter()
        .filter_map(|p| {
            let (x, y) = (p.xy.x, p.xy.y);
            if !(x.is_finite() && y.is_finite()) {
                return None;
            }
            let inside = between_centres(w, h, x, y);
            Some((p.point3d_id?, sample_bilinear(&rgb, x, y), inside))
        })
        .collect())
}

/// Sum of colours and their count.
#[derive(Clone, Copy, Default)]
struct ColourSum {
    sum: [f64; 3],
    count: usize,
}

impl ColourSum {
    fn add(&mut self, colour: &[f64; 3]) {
        for (s, c) in self.sum.iter_mut().zip(colour) {
            *s += c;
        }
        self.count += 1;
    }

    fn mean_u8(&self) -> [u8; 3] {
        self.sum
            .map(|s| (s / self.count as f64).round().clamp(0.0, 255.0) as u8)
    }
}

/// Sets every 3D point's colour to the mean of its registered images'
/// colours at its keypoints. Keypoints within half a pixel of the border
/// count only for points seen nowhere else (they take the border pixels'
/// colour). Images are read in parallel and summed in image order, so the
/// result does not depend on the thread count. Points without an
/// observation in a readable registered image keep their colour.
///
/// An image that cannot be read (it was checked before the run, so it was
/// cut short or changed since) is left out with a warning and listed in the
/// summary, rather than throwing the run away; an image whose camera is not
/// in the model is an error.
pub fn colour_points(
    reconstruction: &mut Reconstruction,
    dir: &Path,
) -> Result<ColourSummary, ImageFolderError> {
    let jobs = reconstruction
        .registered_images()
        .map(|img| {
            let camera = reconstruction.cameras.get(&img.camera_id).ok_or_else(|| {
                ImageFolderError::UnknownCamera {
                    name: img.name.clone(),
                    camera_id: img.camera_id.0,
                }
            })?;
            Ok((img, ExpectedImage::new(&img.name, camera)))
        })
        .collect::<Result<Vec<_>, ImageFolderError>>()?;
    let results: Vec<Result<Vec<Sample>, ImageFolderError>> = jobs
        .par_iter()
        .map(|(img, expected)| sample_image(dir, img, expected))
        .collect();
    let mut samples = Vec::with_capacity(results.len());
    let mut unread = Vec::new();
    for ((img, _), result) in jobs.iter().zip(results) {
        match result {
            Ok(s) => samples.push(s),
            Err(e) => {
                log::warn!("no colours from image `{}`: {e}", img.name);
                unread.push(UnreadImage {
                    name: img.name.clone(),
                    error: e.to_string(),
                });
            }
        }
    }
    let images_read = samples.len();
    // Per point: the keypoints between pixel centres, and all of them.
    let mut sums: std::collections::BTreeMap<Point3DId, (ColourSum, ColourSum)> =
        Default::default();
    let mut observations_sampled = 0;
    for (id, colour, inside) in samples.into_iter().flatten() {
        let (interior, all) = sums.entry(id).or_default();
        if inside {
            interior.add(&colour);
        }
        all.add(&colour);
        observations_sampled += 1;
    }
    let mut points_coloured = 0;
    for (id, (interior, all)) in sums {
        if let Some(point) = reconstruction.points3d.get_mut(&id) {
            point.color = if interior.count > 0 {
                interior.mean_u8()
            } else {
                all.mean_u8()
            };
            points_coloured += 1;
        }
    }
    Ok(ColourSummary {
        images_read,
        points_coloured,
        observations_sampled,
        unread,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{
        CameraId, CameraModel, Image, ImageId, Point2D, Point3D, Rigid3, TrackElement,
    };
    use nalgebra::{Vector2, Vector3};

    /// A 4x3 image whose red channel is 10 x + 100 y, green 200 - 20 x and
    /// blue 7 at pixel (x, y).
    fn ramp() -> RgbImage {
        RgbImage::from_fn(4, 3, |x, y| {
            image::Rgb([(10 * x + 100 * y) as u8, (200 - 20 * x) as u8, 7])
        })
    }

    #[test]
    fn bilinear_uses_colmaps_pixel_centres() {
        let img = ramp();
        // Keypoint (0.5, 0.5) is pixel (0, 0)'s centre.
        assert_eq!(sample_bilinear(&img, 0.5, 0.5), [0.0, 200.0, 7.0]);
        // (2.0, 1.5): halfway between pixels (1, 1) and (2, 1).
        assert_eq!(sample_bilinear(&img, 2.0, 1.5), [115.0, 170.0, 7.0]);
        // (1.75, 2.25): x 1.25 and y 1.75 between centres.
        let c = sample_bilinear(&img, 1.75, 2.25);
        let expected = [10.0 * 1.25 + 100.0 * 1.75, 200.0 - 20.0 * 1.25, 7.0];
        for k in 0..3 {
            assert!((c[k] - expected[k]).abs() < 1e-12, "{c:?}");
        }
        // Beyond the last centres: the border pixel (3, 2).
        assert_eq!(sample_bilinear(&img, 3.9, 2.9), [230.0, 140.0, 7.0]);
        assert_eq!(sample_bilinear(&img, 0.0, 0.1), [0.0, 200.0, 7.0]);
    }

    #[test]
    fn bilinear_on_a_one_pixel_image() {
        let img = RgbImage::from_pixel(1, 1, image::Rgb([1, 2, 3]));
        assert_eq!(sample_bilinear(&img, 0.7, 0.2), [1.0, 2.0, 3.0]);
    }

    fn camera(id: u32, width: u32, height: u32) -> Camera {
        Camera {
            id: CameraId(id),
            model: CameraModel::SimplePinhole,
            width,
            height,
            params: vec![4.0, 2.0, 1.5],
        }
    }

    fn image(id: u32, name: &str, registered: bool, points: &[(f64, f64, Option<u64>)]) -> Image {
        Image {
            id: ImageId(id),
            name: name.to_string(),
            camera_id: CameraId(1),
            cam_from_world: registered.then(Rigid3::identity),
            points2d: points
                .iter()
                .map(|&(x, y, p)| Point2D {
                    xy: Vector2::new(x, y),
                    point3d_id: p.map(Point3DId),
                })
                .collect(),
        }
    }

    fn point(track: &[(u32, u32)]) -> Point3D {
        Point3D {
            xyz: Vector3::zeros(),
            color: [128; 3],
            error: 0.0,
            track: track
                .iter()
                .map(|&(i, k)| TrackElement {
                    image_id: ImageId(i),
                    point2d_idx: k,
                })
                .collect(),
        }
    }

    #[test]
    fn points_take_the_mean_colour_of_their_registered_views() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        ramp().save(dir.path().join("a.png")).unwrap();
        // The second image: the ramp plus 1 everywhere.
        let mut plus = ramp();
        plus.pixels_mut().for_each(|p| p.0 = p.0.map(|v| v + 1));
        // TIFF, to show the format is read.
        plus.save(dir.path().join("sub/b.tif")).unwrap();
        let mut rec = Reconstruction::default();
        rec.cameras.insert(CameraId(1), camera(1, 4, 3));
        rec.images.insert(
            ImageId(1),
            image(
                1,
                "a.png",
                true,
                &[
                    (0.5, 0.5, Some(10)),
                    (2.0, 1.5, Some(11)),
                    (3.0, 3.0, None),
                    (3.9, 1.5, Some(10)),
                    (0.2, 2.9, Some(14)),
                ],
            ),
        );
        rec.images.insert(
            ImageId(2),
            image(
                2,
                "sub/b.tif",
                true,
                &[(2.0, 1.5, Some(10)), (1.5, 0.5, Some(12))],
            ),
        );
        // Not registered: its file is not even looked for.
        rec.images.insert(
            ImageId(3),
            image(3, "gone.png", false, &[(0.5, 0.5, Some(12))]),
        );
        rec.points3d.insert(Point3DId(10), point(&[(1, 0), (2, 0)]));
        rec.points3d.insert(Point3DId(11), point(&[(1, 1)]));
        rec.points3d.insert(Point3DId(12), point(&[(2, 1), (3, 0)]));
        rec.points3d.insert(Point3DId(13), point(&[]));
        // Seen only within half a pixel of the border: pixel (0, 2).
        rec.points3d.insert(Point3DId(14), point(&[(1, 4)]));
        let summary = colour_points(&mut rec, dir.path()).unwrap();
        assert_eq!(
            summary,
            ColourSummary {
                images_read: 2,
                points_coloured: 4,
                observations_sampled: 6,
                unread: vec![],
            }
        );
        // Point 10: (0, 200, 7) in a, (116, 171, 8) in b; mean (58, 185.5, 7.5), rounded half away
        // from zero. Its third keypoint, (3.9, 1.5) in a, is beyond the last pixel centre: left out.
        assert_eq!(rec.points3d[&Point3DId(10)].color, [58, 186, 8]);
        assert_eq!(rec.points3d[&Point3DId(11)].color, [115, 170, 7]);
        // Point 12: pixel (1, 0) of b only.
        assert_eq!(rec.points3d[&Point3DId(12)].color, [11, 181, 8]);
        assert_eq!(rec.points3d[&Point3DId(13)].color, [128; 3]);
        assert_eq!(rec.points3d[&Point3DId(14)].color, [200, 200, 7]);
    }

    #[test]
    fn the_folder_is_checked_against_the_database() {
        let dir = tempfile::tempdir().unwrap();
        ramp().save(dir.path().join("a.png")).unwrap();
        std::fs::write(dir.path().join("broken.jpg"), b"not a jpeg").unwrap();
        let ok = ExpectedImage {
            name: "a.png",
            camera_id: 1,
            width: 4,
            height: 3,
        };
        assert_eq!(check_image_folder(dir.path(), [ok.clone()]).unwrap(), 1);

        let err = check_image_folder(&dir.path().join("nope"), [ok.clone()]).unwrap_err();
        assert!(
            err.to_string().contains("nope") && err.to_string().contains("not a folder"),
            "{err}"
        );

        let missing = ExpectedImage {
            name: "b.png",
            ..ok.clone()
        };
        let err = check_image_folder(dir.path(), [ok.clone(), missing]).unwrap_err();
        assert!(matches!(err, ImageFolderError::Missing { .. }), "{err}");
        assert!(err.to_string().contains("b.png"), "{err}");

        let wrong_size = ExpectedImage {
            width: 640,
            height: 480,
            ..ok.clone()
        };
        let err = check_image_folder(dir.path(), [wrong_size]).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("a.png") && text.contains("4x3") && text.contains("640x480"),
            "{text}"
        );

        let broken = ExpectedImage {
            name: "broken.jpg",
            ..ok
        };
        let err = check_image_folder(dir.path(), [broken]).unwrap_err();
        assert!(matches!(err, ImageFolderError::Unreadable { .. }), "{err}");
        assert!(err.to_string().contains("broken.jpg"), "{err}");
    }

    #[test]
    fn unreadable_images_are_left_out_and_listed() {
        let dir = tempfile::tempdir().unwrap();
        ramp().save(dir.path().join("b.png")).unwrap();
        // A PNG cut short after the run's check: its header reads, its pixels do not.
        let mut png = Vec::new();
        ramp()
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        std::fs::write(dir.path().join("c.png"), &png[..png.len() - 20]).unwrap();
        assert!(image::image_dimensions(dir.path().join("c.png")).is_ok());
        let mut rec = Reconstruction::default();
        rec.cameras.insert(CameraId(1), camera(1, 4, 3));
        rec.images
            .insert(ImageId(1), image(1, "a.png", true, &[(0.5, 0.5, Some(10))]));
        rec.images
            .insert(ImageId(2), image(2, "b.png", true, &[(1.5, 0.5, Some(10))]));
        rec.images
            .insert(ImageId(3), image(3, "c.png", true, &[(0.5, 0.5, Some(11))]));
        rec.points3d.insert(Point3DId(10), point(&[(1, 0), (2, 0)]));
        rec.points3d.insert(Point3DId(11), point(&[(3, 0)]));
        let summary = colour_points(&mut rec, dir.path()).unwrap();
        assert_eq!(summary.images_read, 1);
        let names: Vec<&str> = summary.unread.iter().map(|u| u.name.as_str()).collect();
        assert_eq!(names, ["a.png", "c.png"]);
        assert!(summary.unread[0].error.contains("not in the image folder"));
        // Point 10 from b alone (pixel (1, 0)); point 11 only in c: grey.
        assert_eq!(rec.points3d[&Point3DId(10)].color, [10, 180, 7]);
        assert_eq!(rec.points3d[&Point3DId(11)].color, [128; 3]);

        // An image whose camera the model lacks is an error naming it.
        rec.images.get_mut(&ImageId(2)).unwrap().camera_id = CameraId(7);
        let err = colour_points(&mut rec, dir.path()).unwrap_err();
        assert!(
            matches!(err, ImageFolderError::UnknownCamera { .. }),
            "{err}"
        );
        assert!(err.to_string().contains("b.png"), "{err}");
    }

    #[test]
    fn keypoints_on_the_last_pixel_centres_are_left_out() {
        // COLMAP samples x - 0.5 in [0, width - 1): keypoint x = 3.5 of a
        // 4-pixel row lies on the last centre and is left out.
        assert!(between_centres(4, 3, 3.49, 2.49));
        assert!(!between_centres(4, 3, 3.5, 1.0));
        assert!(!between_centres(4, 3, 1.0, 2.5));
        assert!(between_centres(4, 3, 0.5, 0.5));
        assert!(!between_centres(4, 3, 0.49, 1.0));
        assert!(!between_centres(4, 3, f64::NAN, 1.0));
        assert_eq!(sample_bilinear(&RgbImage::new(0, 0), 1.0, 1.0), [0.0; 3]);
    }
}
