//! Seeing the map from a camera (method.md, section 4.3): for query pixels
//! (feature positions), the LiDAR point the camera sees there.
//!
//! 1. Cull: the map cells that may intersect the camera's frustum
//!    ([`FrustumGrid::cells_in_frustum`]), never the whole map.
//! 2. Project every point of those cells with the real camera model; keep
//!    those with depth in `[min_depth_m, max_depth_m]` that land near the image.
//! 3. Splat: the point covers the square of half-size
//!    [`SplatOptions::half_size_px`] around its projection (larger when near,
//!    proportional to the focal length).
//! 4. At each query pixel inside the square, keep the point with the smallest
//!    range (distance from the camera centre): a z-buffer evaluated at the
//!    query pixels only. Ties are broken by the smaller point index.
//!
//! The query pixels are bucketed in 8 px tiles. [`project_map_at_pixels`]
//! visits the frustum's cells front to back (by their distance from the
//! camera centre) and skips, exactly, what cannot change any answer: a cell
//! whose nearest possible range exceeds the largest best range of every
//! query tile its splats can reach (pinhole cameras: the box of its corners'
//! projections, widened by the largest splat), and a point's test against a
//! tile's queries when its range exceeds that tile's largest best range. Once
//! the near surfaces have filled the queries, occluded cells cost one test
//! each. Parallel over horizontal strips of tiles (each strip owns its
//! queries); ties are broken by the point index, so the result does not
//! depend on the number of threads, the schedule or the visiting order, and
//! equals [`project_map_at_pixels_reference`] (every point of every frustum
//! cell splatted) bit for bit.
//!
//! Pixel convention (COLMAP): the upper-left corner of the image is (0, 0), the
//! centre of pixel (i, j) is (i + 0.5, j + 0.5).
use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;
use super::grid::{Frustum, FrustumGrid};
use crate::scene::camera::{Camera, CameraModel};
use crate::scene::pose::Rigid3;

/// Errors of the projection.
#[derive(Debug, thiserror::Error)]
pub enum ProjectionError {
    #[error("invalid projection option: {0}")]
    InvalidOption(String),
    #[error("camera {model} has {got} parameters, expected {expected}")]
    BadCamera {
        model: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("the grid holds {grid} points but the map has {map}: built from another map?")]
    GridMismatch { grid: usize, map: usize },
}

/// How large a projected map point is drawn.
///
/// A point stands for a small patch of surface of half-width
/// `patch_half_width_m` plus an angular margin `angular_margin_rad`; at depth
/// `d` (m) and focal length `f` (px) its square has half-size
///
/// ```text
/// h(d) = clamp(max(f * (patch_half_width_m / max(d, saturation_depth_m) + angular_margin_rad),
///                  f * near_half_width_m / d),
///              min_half_size_px, max_half_size_px)
/// ```
///
/// The defaults reproduce the reference implementation's splat (10 px at
/// <= 2 m down to 2 px at 40 m at 0.2x image scale of a 4000 px wide image,
/// i.e. a focal length of about 640 px at that scale; about 50 px to 10 px at
/// full resolution): `f * (a / 2 + b) = 10` and `f * (a / 40 + b) = 2` at
/// `f = 640` give `a = 0.02632 m`, `b = 0.002467 rad`.
#[derive(Clone, Debug, PartialEq)]
pub struct SplatOptions {
    /// Half-width of the surface patch a point stands for (m). Default 0.02632.
    pub patch_half_width_m: f64,
    /// Angular margin added to every splat (rad). Default 0.002467.
    pub angular_margin_rad: f64,
    /// Below this depth the splat stops growing (m). Default 2.
    pub saturation_depth_m: f64,
    /// Smallest half-size (px). Default 0.5 (the pixel the point falls in).
    pub min_half_size_px: f64,
    /// Largest half-size (px). Default 64.
    pub max_half_size_px: f64,
    /// Half-width of the surface patch a point stands for at every depth,
    /// nearer than `saturation_depth_m` too (m): the saturated splat of a
    /// map point near the camera is narrower than the gaps between the
    /// map's points there. Still capped at `max_half_size_px` (64 px: at a
    /// focal length of 3200 px a 5 cm map closes from about 1.25 m on).
    /// Default 0 (the reference's splat); the mapper and `depth` set it from
    /// the map's spacing ([`widen_splats_for_spacing`]).
    pub near_half_width_m: f64,
}

impl Default for SplatOptions {
    fn default() -> Self {
        Self {
            patch_half_width_m: 0.026_32,
            angular_margin_rad: 0.002_467,
            saturation_depth_m: 2.0,
            min_half_size_px: 0.5,
            max_half_size_px: 64.0,
            near_half_width_m: 0.0,
        }
    }
}

/// Splat half-width per map spacing: a map point stands for at least this
/// share of the map's spacing on its surface
/// ([`super::index::MapIndex::surface_spacing_m`]), so that a camera does not
/// see through a sparse map between its splats.
pub const SPLAT_PER_SPACING: f64 = 0.6;

/// `half_width_m` raised to [`SPLAT_PER_SPACING`] times `spacing_m` (for
/// both half-widths of [`widen_splats_for_spacing`]); unchanged for a
/// spacing that is not a positive number.
fn splat_half_width_for_spacing(half_width_m: f64, spacing_m: f64) -> f64 {
    if spacing_m.is_finite() && spacing_m > 0.0 {
        half_width_m.max(SPLAT_PER_SPACING * spacing_m)
    } else {
        half_width_m
    }
}

/// Splats for a map of surface spacing `spacing_m` (the mapper's and
/// `depth`'s rule): a map point stands for at least [`SPLAT_PER_SPACING`]
/// times the spacing at every depth, so that a camera does not see through
/// the map between its points, far (a sparse map: the saturating half-width
/// is raised) or near (any map: the floor below the saturation depth), up
/// to the largest splat (`max_half_size_px`).
/// Unchanged for a spacing that is not a positive number.
pub fn widen_splats_for_spacing(splat: &mut SplatOptions, spacing_m: f64) {
    splat.patch_half_width_m = splat_half_width_for_spacing(splat.patch_half_width_m, spacing_m);
    splat.near_half_width_m = splat_half_width_for_spacing(splat.near_half_width_m, spacing_m);
}

impl SplatOptions {
    /// Half-size (px) of the square splat of a point at `depth_m` seen with
    /// focal length `focal_px` (see the type's doc).
    pub fn half_size_px(&self, depth_m: f64, focal_px: f64) -> f64 {
        let d = depth_m.max(self.saturation_depth_m);
        let h = focal_px * (self.patch_half_width_m / d + self.angular_margin_rad);
        let near = focal_px * self.near_half_width_m / depth_m;
        // `max` ignores a NaN `near` (depth 0 with no floor).
        h.max(near)
            .clamp(self.min_half_size_px, self.max_half_size_px)
    }

    pub fn validate(&self) -> Result<(), ProjectionError> {
        let bad = |what: &str| Err(ProjectionError::InvalidOption(what.to_string()));
        if !(self.patch_half_width_m >= 0.0 && self.patch_half_width_m.is_finite()) {
            return bad("patch_half_width_m must be finite and >= 0");
        }
        if !(self.angular_margin_rad >= 0.0 && self.angular_margin_rad.is_finite()) {
            return bad("angular_margin_rad must be finite and >= 0");
        }
        if !(self.saturation_depth_m >= 0.0 && self.saturation_depth_m.is_finite()) {
            return bad("saturation_depth_m must be finite and >= 0");
        }
        if !(self.near_half_width_m >= 0.0 && self.near_half_width_m.is_finite()) {
            return bad("near_half_width_m must be finite and >= 0");
        }
        if !(self.min_half_size_px >= 0.0
            && self.max_half_size_px >= self.min_half_size_px
            && self.max_half_size_px.is_finite())
        {
            return bad("need 0 <= min_half_size_px <= max_half_size_px < infinity");
        }
        Ok(())
    }
}

/// Options of the projection of the map into a camera.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectionOptions {
    /// Points closer than this along the optical axis are ignored (m; a
    /// fisheye's: closer than this to the camera). Default 0.5.
    pub min_depth_m: f64,
    /// Points deeper than this (or farther from the centre) are ignored (m). Default 40.
    pub max_depth_m: f64,
    /// Splat size. Defaults: see [`SplatOptions`].
    pub splat: SplatOptions,
}

impl Default for ProjectionOptions {
    fn default() -> Self {
        Self {
            min_depth_m: 0.5,
            max_depth_m: 40.0,
            splat: SplatOptions::default(),
        }
    }
}

impl ProjectionOptions {
    pub fn validate(&self) -> Result<(), ProjectionError> {
        if !(self.min_depth_m > 0.0
            && self.max_depth_m > self.min_depth_m
            && self.max_depth_m.is_finite())
        {
            return Err(ProjectionError::InvalidOption(format!(
                "need 0 < min_depth_m < max_depth_m < infinity, got {} and {}",
                self.min_depth_m, self.max_depth_m
            )));
        }
        self.splat.validate()
    }
}

/// The LiDAR point seen at a query pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct LidarHit {
    /// Index of the point in the map.
    pub point_idx: u32,
    /// The point in the map frame (m).
    pub point_in_map: Vector3<f64>,
    /// Its unit normal in the map frame, when the map has normals.
    pub normal_in_map: Option<Vector3<f64>>,
    /// Distance from the camera centre (m).
    pub range_m: f64,
    /// Depth along the optical axis (m).
    pub depth_m: f64,
}

/// A map point seen by the camera, after projection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectedPoint {
    pub point_idx: u32,
    /// Pixel coordinates of the projection (COLMAP convention).
    pub pixel: Vector2<f64>,
    pub depth_m: f64,
    pub range_m: f64,
    /// Half-size of its square splat (px).
    pub half_size_px: f64,
}

/// Camera projection with closed forms for the distortion-free models.
enum Projector<'a> {
    Pinhole {
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
    },
    /// The camera model; points beyond `max_normalized_radius_sq` (where the
    /// distortion folds back and a point far off to the side would land inside
    /// the image) are not projected.
    Model {
        camera: &'a Camera,
        max_normalized_radius_sq: f64,
    },
}

impl<'a> Projector<'a> {
    fn new(camera: &'a Camera) -> Result<Self, ProjectionError> {
        let p = &camera.params;
        if p.len() != camera.model.num_params() {
            return Err(ProjectionError::BadCamera {
                model: camera.model.name(),
                got: p.len(),
                expected: camera.model.num_params(),
            });
        }
        Ok(match camera.model {
            CameraModel::SimplePinhole => Projector::Pinhole {
                fx: p[0],
                fy: p[0],
                cx: p[1],
                cy: p[2],
            },
            CameraModel::Pinhole => Projector::Pinhole {
                fx: p[0],
                fy: p[1],
                cx: p[2],
                cy: p[3],
            },
            _ => {
                let r = camera
                    .max_normalized_radius()
                    .ok_or(ProjectionError::BadCamera {
                        model: camera.model.name(),
                        got: p.len(),
                        expected: camera.model.num_params(),
                    })?;
                Projector::Model {
                    camera,
                    max_normalized_radius_sq: r * r,
                }
            }
        })
    }

    #[inline]
    fn project(&self, point_in_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        match *self {
            Projector::Pinhole { fx, fy, cx, cy } => {
                let iz = 1.0 / point_in_cam.z;
                Some(Vector2::new(
                    fx * point_in_cam.x * iz + cx,
                    fy * point_in_cam.y * iz + cy,
                ))
            }
            Projector::Model {
                camera,
                max_normalized_radius_sq,
            } => {
                let z = point_in_cam.z;
                let r_sq =
                    (point_in_cam.x * point_in_cam.x + point_in_cam.y * point_in_cam.y) / (z * z);
                if !(r_sq <= max_normalized_radius_sq) {
                    return None;
                }
                camera.project(point_in_cam)
            }
        }
    }
}

/// The depth at which the splat of a point at `depth_m` (along the optical
/// axis) and `range_m` (from the camera) is sized: the depth for a
/// perspective camera; for a fisheye (`fisheye`) the depth at which a
/// perspective camera of the same focal length shows a patch as large as the
/// fisheye does, `r / θ` (`r` the point's distance from the axis, `θ` its
/// angle from it; the depth on the axis). The equidistant image of a patch
/// at range `ρ` is `f / ρ` per metre radially and `f θ / (ρ sin θ)` across:
/// `f θ / r` is the larger. Sized by the depth, a fisheye's splats were `tan
/// θ / θ` times too large: 2.3 times at 70 degrees off the axis.
#[inline]
pub fn splat_depth_m(fisheye: bool, depth_m: f64, range_m: f64) -> f64 {
    if !fisheye {
        return depth_m;
    }
    let r = (range_m * range_m - depth_m * depth_m).max(0.0).sqrt();
    if r <= 1e-6 * depth_m.abs() {
        return depth_m;
    }
    r / r.atan2(depth_m)
}

/// Everything the per-point loop needs, computed once per projection.
struct Setup<'a> {
    projector: Projector<'a>,
    /// `cam_from_world` rotation.
    rotation: Matrix3<f64>,
    /// Translation for local offsets: `X_cam = R * X_local + t_local`.
    t_local: Vector3<f64>,
    focal_px: f64,
    /// A fisheye model: splats sized by [`splat_depth_m`], the near limit
    /// on the range.
    fisheye: bool,
    width: f64,
    height: f64,
    cells: Vec<u32>,
    /// Camera centre relative to the cloud's origin (m).
    centre_rel: Vector3<f64>,
}

/// Groups of consecutive cells of about this many points form one parallel task.
const POINTS_PER_TASK: usize = 32_768;

impl<'a> Setup<'a> {
    fn new(
        cloud: &PointCloud,
        grid: &FrustumGrid,
        camera: &'a Camera,
        cam_from_world: &Rigid3,
        options: &ProjectionOptions,
    ) -> Result<Self, ProjectionError> {
        options.validate()?;
        if grid.num_points() != cloud.len() {
            return Err(ProjectionError::GridMismatch {
                grid: grid.num_points(),
                map: cloud.len(),
            });
        }
        let projector = Projector::new(camera)?;
        let rotation = cam_from_world.rotation_matrix();
        let t_local = rotation * cloud.origin + cam_from_world.translation;
        let focal_px = camera.mean_focal_length();
        let margin_px = options.splat.max_half_size_px.max(0.0) + 1.0;
        let fisheye = camera.model.is_fisheye();
        // A fisheye's near limit is on the range (`project_point`): along
        // the axis, 0.5 m would be 2.4 m at 78 degrees off it, and the image
        // corners would show nothing nearer. Its frustum reaches down to the
        // depth such a point has at the edge of the view.
        let near_m = if fisheye {
            let edge_cos = camera.max_half_fov_rad().map_or(0.0, f64::cos);
            options.min_depth_m * edge_cos.max(1e-3)
        } else {
            options.min_depth_m
        };
        let frustum = Frustum::from_camera(
            camera,
            cam_from_world,
            near_m,
            options.max_depth_m,
            margin_px,
        );
        let cells = grid.cells_in_frustum(&frustum);
        Ok(Self {
            projector,
            rotation,
            t_local,
            focal_px,
            fisheye,
            width: f64::from(camera.width),
            height: f64::from(camera.height),
            cells,
            centre_rel: cam_from_world.camera_center() - cloud.origin,
        })
    }

    /// Chunks of consecutive cells of roughly equal point counts (depends only
    /// on the data, never on the number of threads).
    fn tasks(&self, grid: &FrustumGrid) -> Vec<std::ops::Range<usize>> {
        let mut tasks = Vec::new();
        let mut start = 0;
        let mut count = 0;
        for (k, &c) in self.cells.iter().enumerate() {
            count += grid.cell_points(c).len();
            if count >= POINTS_PER_TASK {
                tasks.push(start..k + 1);
                start = k + 1;
                count = 0;
            }
        }
        if start < self.cells.len() {
            tasks.push(start..self.cells.len());
        }
        tasks
    }

    /// Calls `f` for every point of the task's cells that the camera sees
    /// (depth range, splat reaching the image), in cell then index order.
    /// Points are read from the grid's cell-local coordinates (sequential
    /// memory); their camera coordinates are `corner_cam + step_cam * q`.
    #[inline]
    fn for_each_projected(
        &self,
        grid: &FrustumGrid,
        task: std::ops::Range<usize>,
        options: &ProjectionOptions,
        mut f: impl FnMut(ProjectedPoint),
    ) {
        let step_cam = self.rotation * grid.cell_step_m();
        for &cell in &self.cells[task] {
            self.for_each_projected_in_cell(grid, cell, &step_cam, options, &mut f);
        }
    }

    /// [`for_each_projected`](Self::for_each_projected) for one cell;
    /// `step_cam` is `rotation * grid.cell_step_m()`.
    #[inline]
    fn for_each_projected_in_cell(
        &self,
        grid: &FrustumGrid,
        cell: u32,
        step_cam: &Matrix3<f64>,
        options: &ProjectionOptions,
        f: &mut impl FnMut(ProjectedPoint),
    ) {
        let corner_cam = self.rotation * grid.cell_corner_rel(cell) + self.t_local;
        let (idxs, locals) = grid.cell_points_local(cell);
        for (&idx, q) in idxs.iter().zip(locals) {
            let q = Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2]));
            let point_in_cam = corner_cam + step_cam * q;
            if let Some(pp) = self.project_point(idx, &point_in_cam, options) {
                f(pp);
            }
        }
    }

    /// Projects one point given in the camera frame; `None` when outside the
    /// depth range, not projectable, or when its splat cannot reach the image.
    #[inline]
    fn project_point(
        &self,
        idx: u32,
        point_in_cam: &Vector3<f64>,
        options: &ProjectionOptions,
    ) -> Option<ProjectedPoint> {
        let depth_m = point_in_cam.z;
        let range_sq = point_in_cam.norm_squared();
        let near = if self.fisheye {
            !(depth_m > 0.0) || range_sq < options.min_depth_m * options.min_depth_m
        } else {
            depth_m < options.min_depth_m
        };
        if near
            || depth_m > options.max_depth_m
            || range_sq > options.max_depth_m * options.max_depth_m
        {
            return None;
        }
        let pixel = self.projector.project(point_in_cam)?;
        // The range's square root only where the splat needs it (a fisheye)
        // or the point is kept.
        let splat_depth = if self.fisheye {
            splat_depth_m(true, depth_m, range_sq.sqrt())
        } else {
            depth_m
        };
        let h = options.splat.half_size_px(splat_depth, self.focal_px);
        if !(pixel.x + h >= 0.0
            && pixel.x - h <= self.width
            && pixel.y + h >= 0.0
            && pixel.y - h <= self.height)
        {
            return None;
        }
        Some(ProjectedPoint {
            point_idx: idx,
            pixel,
            depth_m,
            range_m: range_sq.sqrt(),
            half_size_px: h,
        })
    }
}

/// Query pixels bucketed by square tiles (CSR layout) for splat lookups.
struct QueryTiles {
    tile_px: f64,
    tiles_x: i64,
    tiles_y: i64,
    starts: Vec<u32>,
    /// Query indices grouped by tile.
    queries: Vec<u32>,
    /// Query pixel coordinates in the order of `queries`.
    pixels: Vec<[f64; 2]>,
}

impl QueryTiles {
    fn new(query_pixels: &[Vector2<f64>], width: f64, height: f64, tile_px: f64) -> Self {
        let tiles_x = ((width / tile_px).ceil() as i64).max(1);
        let tiles_y = ((height / tile_px).ceil() as i64).max(1);
        let ntiles = (tiles_x * tiles_y) as usize;
        let tile_of = |q: &Vector2<f64>| -> Option<usize> {
            if !(q.x >= 0.0 && q.y >= 0.0 && q.x < width && q.y < height) {
                return None;
            }
            let tx = ((q.x / tile_px) as i64).min(tiles_x - 1);
            let ty = ((q.y / tile_px) as i64).min(tiles_y - 1);
            Some((ty * tiles_x + tx) as usize)
        };
        let mut counts = vec![0u32; ntiles + 1];
        for q in query_pixels {
            if let Some(t) = tile_of(q) {
                counts[t + 1] += 1;
            }
        }
        for t in 0..ntiles {
            counts[t + 1] += counts[t];
        }
        let starts = counts.clone();
        let mut fill = counts;
        let total = starts[ntiles] as usize;
        let mut queries = vec![0u32; total];
        let mut pixels = vec![[0.0; 2]; total];
        for (i, q) in query_pixels.iter().enumerate() {
            if let Some(t) = tile_of(q) {
                let slot = fill[t] as usize;
                queries[slot] = i as u32;
                pixels[slot] = [q.x, q.y];
                fill[t] += 1;
            }
        }
        Self {
            tile_px,
            tiles_x,
            tiles_y,
            starts,
            queries,
            pixels,
        }
    }

    /// Calls `f(query index)` for every query pixel inside the splat square.
    #[inline]
    fn for_each_covered(&self, pixel: &Vector2<f64>, h: f64, mut f: impl FnMut(u32)) {
        let (x0, x1) = (pixel.x - h, pixel.x + h);
        let (y0, y1) = (pixel.y - h, pixel.y + h);
        // Truncation, not floor (a libm call on baseline x86-64): it differs
        // only below 0, where the clamp to tile 0 applies anyway; the exact
        // test below decides.
        let tx0 = ((x0 / self.tile_px) as i64).max(0);
        let tx1 = ((x1 / self.tile_px) as i64).min(self.tiles_x - 1);
        let ty0 = ((y0 / self.tile_px) as i64).max(0);
        let ty1 = ((y1 / self.tile_px) as i64).min(self.tiles_y - 1);
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                let t = (ty * self.tiles_x + tx) as usize;
                for slot in self.starts[t] as usize..self.starts[t + 1] as usize {
                    let [qx, qy] = self.pixels[slot];
                    if qx >= x0 && qx <= x1 && qy >= y0 && qy <= y1 {
                        f(self.queries[slot]);
                    }
                }
            }
        }
    }
}

/// Best (range, point index) so far; `u32::MAX` index = none.
#[derive(Clone, Copy)]
struct Best {
    range_m: f64,
    point_idx: u32,
}

impl Best {
    const NONE: Best = Best {
        range_m: f64::INFINITY,
        point_idx: u32::MAX,
    };

    #[inline]
    fn is_better_than(&self, other: &Best) -> bool {
        self.range_m < other.range_m
            || (self.range_m == other.range_m && self.point_idx < other.point_idx)
    }
}

/// For each query pixel, the LiDAR point the camera sees there (see the module
/// doc), or `None`. Query pixels outside the image get `None`.
///
/// Visits the frustum's cells front to back and skips what cannot change the
/// answer (see the module doc); the result equals
/// [`project_map_at_pixels_reference`] exactly.
pub fn project_map_at_pixels(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    cam_from_world: &Rigid3,
    query_pixels: &[Vector2<f64>],
    options: &ProjectionOptions,
) -> Result<Vec<Option<LidarHit>>, ProjectionError> {
    let setup = Setup::new(cloud, grid, camera, cam_from_world, options)?;
    if query_pixels.is_empty() {
        return Ok(Vec::new());
    }
    let tiles = QueryTiles::new(query_pixels, setup.width, setup.height, TILE_PX);
    let best = occlusion_culled_best(&setup, grid, &tiles, options, query_pixels.len());
    Ok(hits_from_best(cloud, &setup, best))
}

/// The straightforward form of [`project_map_at_pixels`], kept as the
/// reference its optimised form is tested against: every point of the
/// frustum's cells is projected and splatted onto the query pixels it covers.
#[doc(hidden)]
pub fn project_map_at_pixels_reference(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    cam_from_world: &Rigid3,
    query_pixels: &[Vector2<f64>],
    options: &ProjectionOptions,
) -> Result<Vec<Option<LidarHit>>, ProjectionError> {
    let setup = Setup::new(cloud, grid, camera, cam_from_world, options)?;
    if query_pixels.is_empty() {
        return Ok(Vec::new());
    }
    let tiles = QueryTiles::new(query_pixels, setup.width, setup.height, TILE_PX);
    let n = query_pixels.len();
    let tasks = setup.tasks(grid);
    let best = tasks
        .par_iter()
        .fold(
            || vec![Best::NONE; n],
            |mut best, task| {
                setup.for_each_projected(grid, task.clone(), options, |pp| {
                    let cand = Best {
                        range_m: pp.range_m,
                        point_idx: pp.point_idx,
                    };
                    tiles.for_each_covered(&pp.pixel, pp.half_size_px, |q| {
                        let b = &mut best[q as usize];
                        if cand.is_better_than(b) {
                            *b = cand;
                        }
                    });
                });
                best
            },
        )
        .reduce(
            || vec![Best::NONE; n],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(&b) {
                    if y.is_better_than(x) {
                        *x = *y;
                    }
                }
                a
            },
        );
    Ok(hits_from_best(cloud, &setup, best))
}

/// Edge of the square tiles bucketing the query pixels (px).
const TILE_PX: f64 = 8.0;
/// Edge of a super-tile, in tiles.
const SUPER: i64 = 8;

/// A frustum cell in visiting order: the smallest range any of its points can
/// have, and (pinhole cameras) the pixel box its points' splats can reach.
struct CellVisit {
    min_range_m: f64,
    cell: u32,
    /// `[x0, x1, y0, y1]` (px), `None` when unknown (then the whole image).
    splat_box_px: Option<[f64; 4]>,
}

/// Visiting order and bounds of the frustum's cells (front to back).
fn cells_front_to_back(
    setup: &Setup,
    grid: &FrustumGrid,
    options: &ProjectionOptions,
) -> Vec<CellVisit> {
    let s = grid.cell_size_m();
    let pinhole = match setup.projector {
        Projector::Pinhole { fx, fy, cx, cy } => Some((fx, fy, cx, cy)),
        Projector::Model { .. } => None,
    };
    let mut visits: Vec<CellVisit> = setup
        .cells
        .par_iter()
        .map(|&cell| {
            let lo = grid.cell_corner_rel(cell);
            let mut d_sq = 0.0;
            for a in 0..3 {
                let c = setup.centre_rel[a];
                let v = if c < lo[a] {
                    lo[a] - c
                } else if c > lo[a] + s {
                    c - lo[a] - s
                } else {
                    0.0
                };
                d_sq += v * v;
            }
            // Margin for the rounding of the points' camera coordinates.
            let min_range_m = (d_sq.sqrt() - 1e-6 * (1.0 + s)).max(0.0);
            let splat_box_px = pinhole.and_then(|(fx, fy, cx, cy)| {
                let mut b = [
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                ];
                let mut min_z = f64::INFINITY;
                for k in 0..8 {
                    let corner = lo
                        + Vector3::new(
                            if k & 1 == 0 { 0.0 } else { s },
                            if k & 2 == 0 { 0.0 } else { s },
                            if k & 4 == 0 { 0.0 } else { s },
                        );
                    let p = setup.rotation * corner + setup.t_local;
                    if !(p.z > 1e-3) {
                        // Straddles the camera plane: no finite box.
                        return None;
                    }
                    min_z = min_z.min(p.z);
                    let (u, v) = (fx * p.x / p.z + cx, fy * p.y / p.z + cy);
                    b = [b[0].min(u), b[1].max(u), b[2].min(v), b[3].max(v)];
                }
                // Projection keeps convexity in front of the camera: the
                // cell's points project inside the corners' box; their splats
                // are at most the splat at the smallest depth kept.
                let h = options
                    .splat
                    .half_size_px(min_z.max(options.min_depth_m), setup.focal_px)
                    + 1.0;
                Some([b[0] - h, b[1] + h, b[2] - h, b[3] + h])
            });
            CellVisit {
                min_range_m,
                cell,
                splat_box_px,
            }
        })
        .collect();
    visits.sort_by(|a, b| {
        a.min_range_m
            .total_cmp(&b.min_range_m)
            .then(a.cell.cmp(&b.cell))
    });
    visits
}

/// The z-buffer at the query pixels with culling, equal to the reference's:
///
/// * cells are visited front to back; each tile of query pixels keeps the
///   largest best range of its queries (`+inf` while one has no point yet;
///   `-1` for tiles without queries), each super-tile of 8 x 8 tiles an upper
///   bound of its tiles' values;
/// * a cell is skipped when its smallest possible range exceeds the bound of
///   every super-tile its splat box reaches (nothing in it can win anywhere);
///   a point is tested against the queries of a tile only when its range does
///   not exceed the tile's value.
///
/// Both tests only skip points that cannot beat (or tie with) a query's best,
/// so the result is the reference's. Parallel over horizontal strips of tiles
/// (each strip owns its queries and sees every cell): the result does not
/// depend on the number of threads.
fn occlusion_culled_best(
    setup: &Setup,
    grid: &FrustumGrid,
    tiles: &QueryTiles,
    options: &ProjectionOptions,
    n: usize,
) -> Vec<Best> {
    let visits = cells_front_to_back(setup, grid, options);
    let strips = (rayon::current_num_threads() as i64)
        .clamp(1, 16)
        .min(tiles.tiles_y);
    let rows_per_strip = (tiles.tiles_y + strips - 1) / strips;
    let step_cam = setup.rotation * grid.cell_step_m();
    let per_strip: Vec<Vec<(u32, Best)>> = (0..strips)
        .into_par_iter()
        .map(|strip| {
            let ty_lo = strip * rows_per_strip;
            let ty_hi = ((strip + 1) * rows_per_strip).min(tiles.tiles_y);
            strip_best(
                setup, grid, tiles, options, &visits, &step_cam, ty_lo, ty_hi,
            )
        })
        .collect();
    let mut best = vec![Best::NONE; n];
    for (q, b) in per_strip.into_iter().flatten() {
        best[q as usize] = b;
    }
    best
}

/// The best point of every query in tile rows `ty_lo..ty_hi`, as
/// `(query index, best)`.
#[allow(clippy::too_many_arguments)]
fn strip_best(
    setup: &Setup,
    grid: &FrustumGrid,
    tiles: &QueryTiles,
    options: &ProjectionOptions,
    visits: &[CellVisit],
    step_cam: &Matrix3<f64>,
    ty_lo: i64,
    ty_hi: i64,
) -> Vec<(u32, Best)> {
    let tx_n = tiles.tiles_x;
    let ntiles = (tiles.tiles_x * tiles.tiles_y) as usize;
    // Best per slot (queries in tile order).
    let mut best = vec![Best::NONE; tiles.queries.len()];
    let mut tile_max = vec![-1.0f64; ntiles];
    for ty in ty_lo..ty_hi {
        for tx in 0..tx_n {
            let t = (ty * tx_n + tx) as usize;
            if tiles.starts[t] < tiles.starts[t + 1] {
                tile_max[t] = f64::INFINITY;
            }
        }
    }
    let sx_n = (tiles.tiles_x + SUPER - 1) / SUPER;
    let sy_n = (tiles.tiles_y + SUPER - 1) / SUPER;
    let mut super_max = vec![-1.0f64; (sx_n * sy_n) as usize];
    let mut super_dirty = vec![true; super_max.len()];
    let refresh =
        |sx: i64, sy: i64, tile_max: &[f64], super_max: &mut [f64], dirty: &mut [bool]| {
            let k = (sy * sx_n + sx) as usize;
            if dirty[k] {
                let mut m = -1.0f64;
                for ty in (sy * SUPER).max(ty_lo)..((sy + 1) * SUPER).min(ty_hi) {
                    for tx in sx * SUPER..((sx + 1) * SUPER).min(tx_n) {
                        m = m.max(tile_max[(ty * tx_n + tx) as usize]);
                    }
                }
                super_max[k] = m;
                dirty[k] = false;
            }
            super_max[k]
        };
    let strip_y0 = ty_lo as f64 * tiles.tile_px;
    let strip_y1 = ty_hi as f64 * tiles.tile_px;
    for visit in visits {
        // Pixel box the cell's splats can reach, within the strip.
        let [x0, x1, y0, y1] = visit
            .splat_box_px
            .unwrap_or([0.0, setup.width, 0.0, setup.height]);
        let (y0, y1) = (y0.max(strip_y0), y1.min(strip_y1));
        let (x0, x1) = (x0.max(0.0), x1.min(setup.width));
        if !(y0 <= y1 && x0 <= x1) {
            continue;
        }
        let sx0 = ((x0 / tiles.tile_px) as i64 / SUPER).clamp(0, sx_n - 1);
        let sx1 = ((x1 / tiles.tile_px) as i64 / SUPER).clamp(0, sx_n - 1);
        let sy0 = ((y0 / tiles.tile_px) as i64 / SUPER).clamp(0, sy_n - 1);
        let sy1 = ((y1 / tiles.tile_px) as i64 / SUPER).clamp(0, sy_n - 1);
        let mut reach = -1.0f64;
        for sy in sy0..=sy1 {
            for sx in sx0..=sx1 {
                reach = reach.max(refresh(sx, sy, &tile_max, &mut super_max, &mut super_dirty));
            }
        }
        if visit.min_range_m > reach {
            continue;
        }
        setup.for_each_projected_in_cell(grid, visit.cell, step_cam, options, &mut |pp| {
            let h = pp.half_size_px;
            let (x0, x1) = (pp.pixel.x - h, pp.pixel.x + h);
            let (y0, y1) = (pp.pixel.y - h, pp.pixel.y + h);
            // Same tile range as `QueryTiles::for_each_covered`, clipped to
            // the strip.
            let tx0 = ((x0 / tiles.tile_px) as i64).max(0);
            let tx1 = ((x1 / tiles.tile_px) as i64).min(tx_n - 1);
            let ty0 = ((y0 / tiles.tile_px) as i64).max(ty_lo);
            let ty1 = ((y1 / tiles.tile_px) as i64).min(ty_hi - 1);
            let cand = Best {
                range_m: pp.range_m,
                point_idx: pp.point_idx,
            };
            for ty in ty0..=ty1 {
                for tx in tx0..=tx1 {
                    let t = (ty * tx_n + tx) as usize;
                    if !(cand.range_m <= tile_max[t]) {
                        continue;
                    }
                    let slots = tiles.starts[t] as usize..tiles.starts[t + 1] as usize;
                    let mut changed = false;
                    for slot in slots.clone() {
                        let [qx, qy] = tiles.pixels[slot];
                        if qx >= x0 && qx <= x1 && qy >= y0 && qy <= y1 {
                            let b = &mut best[slot];
                            if cand.is_better_than(b) {
                                *b = cand;
                                changed = true;
                            }
                        }
                    }
                    if changed {
                        let mut m = -1.0f64;
                        for slot in slots {
                            m = m.max(best[slot].range_m);
                        }
                        tile_max[t] = m;
                        super_dirty[((ty / SUPER) * sx_n + tx / SUPER) as usize] = true;
                    }
                }
            }
        });
    }
    let first = tiles.starts[(ty_lo * tx_n) as usize] as usize;
    let last = tiles.starts[(ty_hi * tx_n) as usize] as usize;
    (first..last)
        .map(|slot| (tiles.queries[slot], best[slot]))
        .collect()
}

/// The hits of the best (range, point) per query, with exact coordinates.
fn hits_from_best(cloud: &PointCloud, setup: &Setup, best: Vec<Best>) -> Vec<Option<LidarHit>> {
    let rotation = setup.rotation;
    best.into_iter()
        .map(|b| {
            if b.point_idx == u32::MAX {
                return None;
            }
            let i = b.point_idx as usize;
            let point_in_map = cloud.point_in_map(i);
            let p = cloud.points[i];
            let local = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            // Exact values (the z-buffer used the grid's quantised copy).
            let point_in_cam = rotation * local + setup.t_local;
            let normal_in_map = cloud.normals.as_ref().map(|normals| {
                let n = normals[i];
                Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2]))
            });
            Some(LidarHit {
                point_idx: b.point_idx,
                point_in_map,
                normal_in_map,
                range_m: point_in_cam.norm(),
                depth_m: point_in_cam.z,
            })
        })
        .collect()
}

/// Every map point the camera sees (depth range, splat reaching the image),
/// in a deterministic order (by grid cell, then point index). No occlusion
/// test: that is the z-buffer's job (see [`super::depth_image`]).
pub fn project_visible_points(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    cam_from_world: &Rigid3,
    options: &ProjectionOptions,
) -> Result<Vec<ProjectedPoint>, ProjectionError> {
    let setup = Setup::new(cloud, grid, camera, cam_from_world, options)?;
    let tasks = setup.tasks(grid);
    let chunks: Vec<Vec<ProjectedPoint>> = tasks
        .par_iter()
        .map(|task| {
            let mut out = Vec::new();
            setup.for_each_projected(grid, task.clone(), options, |pp| out.push(pp));
            out
        })
        .collect();
    Ok(chunks.concat())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fisheye_splats_follow_the_angle_not_the_tangent() {
        // Perspective: the depth, wherever the point is.
        assert_eq!(splat_depth_m(false, 1.0, 2.0), 1.0);
        // On the axis: the depth.
        assert_eq!(splat_depth_m(true, 2.5, 2.5), 2.5);
        // 60 deg off the axis at range 2 m: z = 1, r = 2 sin 60 = sqrt(3),
        // θ = π/3, r / θ = 1.6540 m (by z: a splat 1.65 times too large).
        let d = splat_depth_m(true, 1.0, 2.0);
        assert!(
            (d - 3f64.sqrt() * 3.0 / std::f64::consts::PI).abs() < 1e-12,
            "{d}"
        );
        // Continuous at the axis (r = 2e-4 m, 1e-4 rad off).
        let near_axis = splat_depth_m(true, 2.0, 2.0f64.hypot(2e-4));
        assert!((near_axis - 2.0).abs() < 1e-7, "{near_axis}");
    }

    #[test]
    fn default_splat_reproduces_reference() {
        let s = SplatOptions::default();
        // 0.2x scale of a 4000 px image: f ~ 640 px.
        assert!((s.half_size_px(2.0, 640.0) - 10.0).abs() < 0.01);
        assert!((s.half_size_px(1.0, 640.0) - 10.0).abs() < 0.01);
        assert!((s.half_size_px(40.0, 640.0) - 2.0).abs() < 0.01);
        // Full resolution: five times larger.
        assert!((s.half_size_px(2.0, 3200.0) - 50.0).abs() < 0.05);
        assert!((s.half_size_px(40.0, 3200.0) - 10.0).abs() < 0.05);
        // Monotone in depth.
        let mut last = f64::INFINITY;
        for d in [0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 40.0] {
            let h = s.half_size_px(d, 640.0);
            assert!(h <= last);
            last = h;
        }
    }

    #[test]
    fn splats_for_a_maps_spacing() {
        // A 2 cm map: the reference's splat from 0.77 m on (f 640: 10 px at
        // 1 m), 0.6 x 2 cm = 1.2 cm at every depth nearer.
        let mut s = SplatOptions::default();
        widen_splats_for_spacing(&mut s, 0.02);
        assert_eq!(
            s.patch_half_width_m,
            SplatOptions::default().patch_half_width_m
        );
        assert!((s.near_half_width_m - 0.012).abs() < 1e-12);
        assert!((s.half_size_px(1.0, 640.0) - 10.0).abs() < 0.01);
        assert!((s.half_size_px(40.0, 640.0) - 2.0).abs() < 0.01);
        assert!((s.half_size_px(0.5, 640.0) - 640.0 * 0.012 / 0.5).abs() < 1e-9);
        // A 10 cm map: 6 cm, saturating from 2 m as before and growing nearer.
        let mut s = SplatOptions::default();
        widen_splats_for_spacing(&mut s, 0.1);
        assert!((s.patch_half_width_m - 0.06).abs() < 1e-12);
        let far = 640.0 * (0.06 / 4.0 + s.angular_margin_rad);
        assert!((s.half_size_px(4.0, 640.0) - far).abs() < 1e-9);
        assert!((s.half_size_px(1.0, 640.0) - 38.4).abs() < 1e-9);
        assert_eq!(s.half_size_px(0.2, 640.0), s.max_half_size_px);
        assert_eq!(s.half_size_px(0.0, 640.0), s.max_half_size_px);
        // No spacing: unchanged; no floor at depth 0: the saturated size.
        let mut s = SplatOptions::default();
        widen_splats_for_spacing(&mut s, f64::NAN);
        assert_eq!(s, SplatOptions::default());
        assert!((s.half_size_px(0.0, 640.0) - 10.0).abs() < 0.01);
    }

    #[test]
    fn options_validate() {
        assert!(ProjectionOptions::default().validate().is_ok());
        let o = ProjectionOptions {
            min_depth_m: 50.0,
            ..Default::default()
        };
        assert!(o.validate().is_err());
        let mut o = ProjectionOptions::default();
        o.splat.max_half_size_px = 0.1;
        assert!(o.validate().is_err());
    }

    #[test]
    fn query_tiles_cover_exactly() {
        let q = vec![
            Vector2::new(10.5, 10.5),
            Vector2::new(12.0, 10.5),
            Vector2::new(99.5, 49.5),
            Vector2::new(-1.0, 3.0),
        ];
        let tiles = QueryTiles::new(&q, 100.0, 50.0, 8.0);
        let mut hit = Vec::new();
        tiles.for_each_covered(&Vector2::new(11.0, 10.0), 1.0, |i| hit.push(i));
        hit.sort();
        assert_eq!(hit, vec![0, 1]);
        hit.clear();
        tiles.for_each_covered(&Vector2::new(11.0, 10.0), 0.6, |i| hit.push(i));
        assert_eq!(hit, vec![0]);
        hit.clear();
        tiles.for_each_covered(&Vector2::new(100.0, 50.0), 0.5, |i| hit.push(i));
        assert_eq!(hit, vec![2]);
    }
}
