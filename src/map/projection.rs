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
//! Parallel with rayon over chunks of cells; each chunk keeps its own best
//! (range, index) per query and chunks are merged with the same total order,
//! so the result does not depend on the number of threads or the schedule.
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
/// h(d) = clamp(f * (patch_half_width_m / max(d, saturation_depth_m) + angular_margin_rad),
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
}

impl Default for SplatOptions {
    fn default() -> Self {
        Self {
            patch_half_width_m: 0.026_32,
            angular_margin_rad: 0.002_467,
            saturation_depth_m: 2.0,
            min_half_size_px: 0.5,
            max_half_size_px: 64.0,
        }
    }
}

impl SplatOptions {
    /// Half-size (px) of the square splat of a point at `depth_m` seen with
    /// focal length `focal_px` (see the type's doc).
    pub fn half_size_px(&self, depth_m: f64, focal_px: f64) -> f64 {
        let d = depth_m.max(self.saturation_depth_m);
        let h = focal_px * (self.patch_half_width_m / d + self.angular_margin_rad);
        h.clamp(self.min_half_size_px, self.max_half_size_px)
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
    /// Points closer than this along the optical axis are ignored (m). Default 0.5.
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

/// Everything the per-point loop needs, computed once per projection.
struct Setup<'a> {
    projector: Projector<'a>,
    /// `cam_from_world` rotation.
    rotation: Matrix3<f64>,
    /// Translation for local offsets: `X_cam = R * X_local + t_local`.
    t_local: Vector3<f64>,
    focal_px: f64,
    width: f64,
    height: f64,
    cells: Vec<u32>,
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
        let frustum = Frustum::from_camera(
            camera,
            cam_from_world,
            options.min_depth_m,
            options.max_depth_m,
            margin_px,
        );
        let cells = grid.cells_in_frustum(&frustum);
        Ok(Self {
            projector,
            rotation,
            t_local,
            focal_px,
            width: f64::from(camera.width),
            height: f64::from(camera.height),
            cells,
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
        if depth_m < options.min_depth_m || depth_m > options.max_depth_m {
            return None;
        }
        let range_sq = point_in_cam.norm_squared();
        if range_sq > options.max_depth_m * options.max_depth_m {
            return None;
        }
        let pixel = self.projector.project(point_in_cam)?;
        let h = options.splat.half_size_px(depth_m, self.focal_px);
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
    let tiles = QueryTiles::new(query_pixels, setup.width, setup.height, 8.0);
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
    let rotation = setup.rotation;
    Ok(best
        .into_iter()
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
        .collect())
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
    fn options_validate() {
        assert!(ProjectionOptions::default().validate().is_ok());
        let mut o = ProjectionOptions::default();
        o.min_depth_m = 50.0;
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
