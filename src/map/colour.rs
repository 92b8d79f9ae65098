//! The map coloured by the photos: each map point takes the colour the
//! registered images show at its projection, where they see it (the paper's
//! colour point cloud). A coloured LiDAR map is a product of its own
//! (surveys, digital twins) and a dense, metric start for Gaussian splatting.
//!
//! Per image, in image order: the map points in its frustum are projected
//! with the camera's own model and splatted into a z-buffer of ranges (the
//! splats of [`super::projection`], which close the gaps between points, so
//! a surface in front hides the one behind it). A point is seen when its
//! projection lies inside the image, the view is within
//! `max_view_angle_deg` of its normal (either side; any view for a point
//! without a normal) and the z-buffer's range at its pixel is at most
//! `(occlusion_margin_m + h sin a) / cos a` shorter than its own, `a` the
//! view's angle from the normal and `h` the splat's half-width in metres:
//! an offset along the normal (the map's noise) is `1 / cos a` longer
//! along the ray, and the splats of the point's neighbours on its own
//! surface come up to `h tan a` nearer. A seen point takes the
//! image's colour there (bilinear between pixel centres) with the weight
//! `cos(angle) / range²`, which is proportional to the number of pixels per
//! square metre of surface: near, head-on views count most. Its colour is
//! the weighted mean over the images that see it.
//!
//! Images are visited one at a time (one decoded image in memory), the
//! projection and the sampling run in parallel with results summed in a
//! fixed order: the colours do not depend on the number of threads.
use image::RgbImage;
use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;
use super::depth_image::depth_image_from_splats;
use super::grid::FrustumGrid;
use super::projection::{
    project_visible_points, splat_depth_m, ProjectionError, ProjectionOptions,
};
use crate::io::images::sample_bilinear;
use crate::scene::camera::Camera;
use crate::scene::pose::Rigid3;

/// Why map points could not be coloured.
#[derive(Debug, thiserror::Error)]
pub enum MapColourError {
    #[error(transparent)]
    Projection(#[from] ProjectionError),
    #[error("invalid colouring option: {0}")]
    InvalidOption(String),
    #[error(
        "the image is {width}x{height} pixels, but its camera is {camera_width}x{camera_height}"
    )]
    ImageSize {
        width: u32,
        height: u32,
        camera_width: u32,
        camera_height: u32,
    },
}

/// How map points are coloured.
#[derive(Clone, Debug, PartialEq)]
pub struct MapColourOptions {
    /// Depth range, splats (see [`ProjectionOptions`]).
    pub projection: ProjectionOptions,
    /// A point is hidden when the surface seen at its pixel lies more than
    /// this in front of it along its normal, metres (plus the splats'
    /// reach; see the module's doc). About three times the map's noise.
    pub occlusion_margin_m: f64,
    /// On a map of spacing s, a map point's splat is at least this times s
    /// wide either side (`widen_splats_for_spacing`): wide enough that a
    /// surface in front has no gaps a surface behind could show through.
    pub splat_per_spacing: f64,
    /// Views farther than this from the point's normal give no colour,
    /// degrees (grazing views smear the texture). Ignored for points without
    /// a normal.
    pub max_view_angle_deg: f64,
}

impl Default for MapColourOptions {
    fn default() -> Self {
        MapColourOptions {
            projection: ProjectionOptions::default(),
            occlusion_margin_m: 0.05,
            splat_per_spacing: 0.8,
            max_view_angle_deg: 75.0,
        }
    }
}

impl MapColourOptions {
    pub fn validate(&self) -> Result<(), MapColourError> {
        self.projection.validate()?;
        let bad = |m: &str| Err(MapColourError::InvalidOption(m.to_string()));
        if !(self.occlusion_margin_m >= 0.0 && self.occlusion_margin_m.is_finite()) {
            return bad("the occlusion margin must be finite and >= 0 m");
        }
        if !(self.splat_per_spacing >= 0.0 && self.splat_per_spacing.is_finite()) {
            return bad("the splat width per map spacing must be finite and >= 0");
        }
        if !(self.max_view_angle_deg > 0.0 && self.max_view_angle_deg <= 90.0) {
            return bad("the largest view angle must be in (0, 90] degrees");
        }
        Ok(())
    }

    /// Splats at least `splat_per_spacing` times `spacing_m` wide either
    /// side, near and far (unchanged for a spacing that is not a positive
    /// number).
    pub fn widen_splats_for_spacing(&mut self, spacing_m: f64) {
        if spacing_m.is_finite() && spacing_m > 0.0 {
            let splat = &mut self.projection.splat;
            let half = self.splat_per_spacing * spacing_m;
            splat.patch_half_width_m = splat.patch_half_width_m.max(half);
            splat.near_half_width_m = splat.near_half_width_m.max(half);
        }
    }
}

/// Weighted colour sums per map point, filled image by image.
#[derive(Clone, Debug)]
pub struct MapColours {
    sum: Vec<[f32; 3]>,
    weight: Vec<f32>,
    views: Vec<u16>,
}

impl MapColours {
    /// Empty sums for a map of `num_points` points.
    pub fn new(num_points: usize) -> Self {
        MapColours {
            sum: vec![[0.0; 3]; num_points],
            weight: vec![0.0; num_points],
            views: vec![0; num_points],
        }
    }

    /// Adds one image's colours of the points it sees (from [`seen_points`]).
    pub fn add(&mut self, seen: &[SeenPoint]) {
        for s in seen {
            let i = s.point_idx as usize;
            for (sum, c) in self.sum[i].iter_mut().zip(s.colour) {
                *sum += (s.weight * c) as f32;
            }
            self.weight[i] += s.weight as f32;
            self.views[i] = self.views[i].saturating_add(1);
        }
    }

    /// The number of images that saw map point `i` (at most 65535).
    pub fn views(&self, i: usize) -> u16 {
        self.views[i]
    }

    /// Number of map points seen by at least one image.
    pub fn num_seen(&self) -> usize {
        self.views.iter().filter(|&&v| v > 0).count()
    }

    /// The colour of map point `i`: the weighted mean of its views, rounded
    /// to 8 bits; `None` when no image saw it.
    pub fn colour(&self, i: usize) -> Option<[u8; 3]> {
        let w = self.weight[i];
        (self.views[i] > 0 && w > 0.0)
            .then(|| self.sum[i].map(|s| (s / w).round().clamp(0.0, 255.0) as u8))
    }
}

/// A map point an image sees, and what it shows there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeenPoint {
    pub point_idx: u32,
    /// Where it projects (pixels, COLMAP's convention).
    pub pixel: Vector2<f64>,
    /// Distance from the camera centre, metres.
    pub range_m: f64,
    /// The image's colour there (bilinear, 0-255).
    pub colour: [f64; 3],
    /// `cos(view angle) / range²` (1 for a point without a normal).
    pub weight: f64,
}

/// The map points `image` (taken by `camera` at `cam_from_world`) sees, in
/// the projection's order (by grid cell, then point index), and the number
/// of map points in its frustum. See the module's doc for the tests.
pub fn seen_points(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    cam_from_world: &Rigid3,
    image: &RgbImage,
    options: &MapColourOptions,
) -> Result<(Vec<SeenPoint>, usize), MapColourError> {
    if image.dimensions() != (camera.width, camera.height) {
        return Err(MapColourError::ImageSize {
            width: image.width(),
            height: image.height(),
            camera_width: camera.width,
            camera_height: camera.height,
        });
    }
    let splats = project_visible_points(cloud, grid, camera, cam_from_world, &options.projection)?;
    let depth = depth_image_from_splats(&splats, camera.width, camera.height);
    let centre = cam_from_world.camera_center();
    let cos_max = options.max_view_angle_deg.to_radians().cos();
    let focal = camera.mean_focal_length();
    let fisheye = camera.model.is_fisheye();
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let seen = splats
        .par_iter()
        .filter_map(|s| {
            let (x, y) = (s.pixel.x, s.pixel.y);
            if !(x >= 0.0 && x < w && y >= 0.0 && y < h) {
                return None;
            }
            let i = s.point_idx as usize;
            let to_camera = (centre - cloud.point_in_map(i)) / s.range_m;
            let cos = match normal_of(cloud, i) {
                Some(n) => n.dot(&to_camera).abs(),
                None => 1.0,
            };
            if cos < cos_max {
                return None;
            }
            // On a surface seen at angle a from its normal, the splats of
            // the point's neighbours (half-width `half_m` across the ray)
            // come up to `half_m * tan(a)` nearer, and an offset along the
            // normal (the map's noise) is `1 / cos(a)` times longer along
            // the ray.
            let half_m = s.half_size_px * splat_depth_m(fisheye, s.depth_m, s.range_m) / focal;
            let sin = (1.0 - cos * cos).sqrt();
            let margin = (options.occlusion_margin_m + half_m * sin) / cos;
            let nearest = f64::from(depth.range_at(x as u32, y as u32));
            if s.range_m > nearest + margin {
                return None;
            }
            Some(SeenPoint {
                point_idx: s.point_idx,
                pixel: s.pixel,
                range_m: s.range_m,
                colour: sample_bilinear(image, x, y),
                weight: cos / (s.range_m * s.range_m),
            })
        })
        .collect();
    Ok((seen, splats.len()))
}

fn normal_of(cloud: &PointCloud, i: usize) -> Option<Vector3<f64>> {
    let n = cloud.normals.as_ref()?[i];
    Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2])).try_normalize(1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::grid::GridOptions;
    use crate::scene::camera::CameraModel;
    use crate::scene::ids::CameraId;

    /// Points on a regular grid of the plane z = `z`, `x` and `y` within
    /// `half` of 0, normals towards -z.
    fn square(z: f32, half: f32, step: f32, points: &mut Vec<[f32; 3]>) {
        let n = (2.0 * half / step).round() as i32;
        for i in 0..=n {
            for j in 0..=n {
                points.push([-half + i as f32 * step, -half + j as f32 * step, z]);
            }
        }
    }

    fn camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        }
    }

    /// A camera at `(x, 0, 0)` looking along +z (the camera frame's axes
    /// are the world's).
    fn looking_up_z(x: f64) -> Rigid3 {
        Rigid3::new(
            nalgebra::UnitQuaternion::identity(),
            Vector3::new(-x, 0.0, 0.0),
        )
    }

    /// A 2 m wall at z = 5 behind a 0.4 m square at z = 3, seen by a red
    /// image from the origin and a blue image from x = 0.5, both looking
    /// along +z. By similar triangles, the square hides from the first
    /// camera the wall's points with |x|, |y| < 0.333 and from the second
    /// those with x in (-0.667, 0), |y| < 0.333.
    #[test]
    fn each_point_takes_the_colour_of_the_images_that_see_it() {
        let mut points = Vec::new();
        square(5.0, 1.0, 0.02, &mut points);
        let wall = points.len();
        square(3.0, 0.2, 0.02, &mut points);
        let normals = vec![[0.0, 0.0, -1.0]; points.len()];
        let cloud = PointCloud {
            origin: Vector3::zeros(),
            points,
            normals: Some(normals),
            planarity: None,
        };
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let camera = camera();
        let red = RgbImage::from_pixel(640, 480, image::Rgb([255, 0, 0]));
        let blue = RgbImage::from_pixel(640, 480, image::Rgb([0, 0, 255]));
        let options = MapColourOptions::default();
        let mut colours = MapColours::new(cloud.len());
        let (a, a_in_view) =
            seen_points(&cloud, &grid, &camera, &looking_up_z(0.0), &red, &options).unwrap();
        let (b, b_in_view) =
            seen_points(&cloud, &grid, &camera, &looking_up_z(0.5), &blue, &options).unwrap();
        colours.add(&a);
        colours.add(&b);
        // Everything is in both frusta. Each camera loses the square's
        // shadow on the wall: 0.667 m wide (33 x 33 points), widened by the
        // square's splats, 5.6 px at 3 m (5.6 cm on the wall: 39 x 39).
        assert_eq!(a_in_view, cloud.len());
        assert_eq!(b_in_view, cloud.len());
        let hidden = |seen: &[SeenPoint]| cloud.len() - seen.len();
        assert!((33 * 33..=39 * 39).contains(&hidden(&a)), "{}", a.len());
        assert!((33 * 33..=39 * 39).contains(&hidden(&b)), "{}", b.len());

        let (mut both, mut only_red, mut only_blue, mut none) = (0, 0, 0, 0);
        for i in 0..wall {
            let p = cloud.points[i];
            let (x, y) = (f64::from(p[0]), f64::from(p[1]));
            // Clear of a shadow: beyond the splats' reach (5.6 cm) and 2 cm.
            let away = |lo: f64, hi: f64| x < lo - 0.076 || x > hi + 0.076 || y.abs() > 0.41;
            let inside = |lo: f64, hi: f64| x > lo + 0.02 && x < hi - 0.02 && y.abs() < 0.313;
            let c = colours.colour(i);
            if inside(-1.0 / 3.0, 0.0) {
                // Behind the square from both cameras.
                assert_eq!(c, None, "{p:?}");
                assert_eq!(colours.views(i), 0);
                none += 1;
            } else if inside(-2.0 / 3.0, -1.0 / 3.0) && away(-1.0 / 3.0, 1.0 / 3.0) {
                assert_eq!(c, Some([255, 0, 0]), "{p:?}");
                assert_eq!(colours.views(i), 1);
                only_red += 1;
            } else if inside(0.0, 1.0 / 3.0) && away(-2.0 / 3.0, 0.0) {
                assert_eq!(c, Some([0, 0, 255]), "{p:?}");
                only_blue += 1;
            } else if away(-2.0 / 3.0, 1.0 / 3.0) {
                let c = c.unwrap();
                assert_eq!(colours.views(i), 2);
                // The nearer camera (the first) weighs a little more.
                assert!(c[0] > 0 && c[2] > 0 && c[1] == 0, "{p:?}: {c:?}");
                let red_share = f64::from(c[0]) / f64::from(u16::from(c[0]) + u16::from(c[2]));
                assert!((0.4..0.6).contains(&red_share), "{p:?}: {c:?}");
                both += 1;
            }
        }
        assert!(none > 100 && only_red > 100 && only_blue > 100 && both > 5000);
        // The square itself is seen by both.
        for i in wall..cloud.len() {
            assert_eq!(colours.views(i), 2);
        }

        // Views more than 5 degrees off the normal give nothing: from the
        // origin the wall's points beyond 5 m x tan 5° = 0.437 m off axis.
        let narrow = MapColourOptions {
            max_view_angle_deg: 5.0,
            ..Default::default()
        };
        let mut colours = MapColours::new(cloud.len());
        let (seen, _) =
            seen_points(&cloud, &grid, &camera, &looking_up_z(0.0), &red, &narrow).unwrap();
        colours.add(&seen);
        for i in 0..wall {
            let p = cloud.points[i];
            let off_axis = f64::from(p[0]).hypot(f64::from(p[1]));
            // (Not behind the square: its shadow reaches 0.389 m.)
            let clear = p[0].abs().max(p[1].abs()) > 0.415;
            if off_axis > 0.45 {
                assert_eq!(colours.views(i), 0, "{p:?}");
            } else if clear && off_axis < 0.434 {
                assert_eq!(colours.colour(i), Some([255, 0, 0]), "{p:?}");
            }
        }
    }

    #[test]
    fn an_image_of_the_wrong_size_is_an_error() {
        let cloud = PointCloud {
            origin: Vector3::zeros(),
            points: vec![[0.0, 0.0, 5.0]],
            normals: None,
            planarity: None,
        };
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let small = RgbImage::new(320, 240);
        let options = MapColourOptions::default();
        let err = seen_points(
            &cloud,
            &grid,
            &camera(),
            &looking_up_z(0.0),
            &small,
            &options,
        )
        .unwrap_err();
        assert!(err.to_string().contains("320x240"), "{err}");
    }

    #[test]
    fn options_are_checked() {
        assert!(MapColourOptions::default().validate().is_ok());
        for bad in [
            MapColourOptions {
                occlusion_margin_m: f64::NAN,
                ..Default::default()
            },
            MapColourOptions {
                occlusion_margin_m: -0.1,
                ..Default::default()
            },
            MapColourOptions {
                max_view_angle_deg: 0.0,
                ..Default::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
