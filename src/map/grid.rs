//! Coarse voxel grid of the LiDAR map for frustum culling.
//!
//! The map is cut into cubic cells (default 2 m). Only occupied cells are
//! stored, in a compressed sparse row layout: `cell_keys` (sorted) gives each
//! occupied cell's integer coordinates, `cell_starts[c]..cell_starts[c + 1]` is
//! its range in one `point_idxs` array (point indices sorted within a cell).
//! Each point also keeps its coordinates relative to its cell's corner,
//! quantised to 16 bits an axis (cell size / 65535: 0.03 mm for 2 m cells), so
//! that projection streams through memory in cell order instead of jumping
//! around the cloud. A 20-million-point map costs 10 bytes a point plus 12
//! bytes an occupied cell.
//!
//! Culling ([`FrustumGrid::cells_in_frustum`]) visits only the cells within the
//! far distance of the camera centre (columns of cells found by binary search),
//! never the map's whole bounding box, and keeps a cell unless its box lies
//! entirely outside one plane of the camera's frustum ([`Frustum`]). The test is
//! conservative: a kept cell may hold no visible point, a dropped cell holds
//! none.
use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;
use crate::scene::camera::{Camera, CameraModel};
use crate::scene::pose::Rigid3;

/// Bits per axis in a packed cell key.
const AXIS_BITS: u32 = 21;
const AXIS_MAX: i64 = (1 << AXIS_BITS) - 1;

/// Errors building a [`FrustumGrid`].
#[derive(Debug, thiserror::Error)]
pub enum GridError {
    #[error("grid cell size must be finite and positive, got {0} m")]
    BadCellSize(f64),
    #[error(
        "the map spans {cells} cells of {cell_size_m} m along one axis; at most {max} are \
         supported (use larger cells)"
    )]
    TooLarge {
        cells: i64,
        cell_size_m: f64,
        max: i64,
    },
    #[error("map point {index} has a non-finite coordinate")]
    NonFinitePoint { index: usize },
    #[error("the map has {0} points; the grid holds at most 2^32 - 1")]
    TooManyPoints(usize),
}

/// Options of [`FrustumGrid::build`].
#[derive(Clone, Debug, PartialEq)]
pub struct GridOptions {
    /// Edge length of a cell (m). Default 2.
    pub cell_size_m: f64,
}

impl Default for GridOptions {
    fn default() -> Self {
        Self { cell_size_m: 2.0 }
    }
}

/// The camera's viewing volume, in the camera frame (x right, y down, z
/// forward): `near_m <= z <= far_m`, distance from the centre `<= far_m`, and,
/// when known, `x_min <= x/z <= x_max`, `y_min <= y/z <= y_max` (bounds on the
/// normalised image plane).
#[derive(Clone, Debug, PartialEq)]
pub struct Frustum {
    pub cam_from_world: Rigid3,
    /// Minimum depth along the optical axis (m).
    pub near_m: f64,
    /// Maximum depth and maximum distance from the camera centre (m).
    pub far_m: f64,
    /// `[x_min, x_max, y_min, y_max]` on the normalised image plane (z = 1);
    /// `None` when the field of view is too wide for such bounds (fisheye
    /// models near or beyond 180 degrees): then only depth and distance cull.
    pub normalized_bounds: Option<[f64; 4]>,
    /// Half-angle (rad) of a cone around the optical axis holding the field of
    /// view, used when `normalized_bounds` is `None` (wide fisheyes); `None`
    /// when unknown too (then only depth and distance cull).
    pub cone_half_angle_rad: Option<f64>,
}

/// Normalised coordinates beyond this (about 84 degrees off axis) are treated
/// as "too wide": the side planes are dropped.
const MAX_TAN_HALF_FOV: f64 = 10.0;

impl Frustum {
    /// The frustum of `camera` at `cam_from_world`, widened by `margin_px`
    /// pixels on every side (so that points just outside the image whose splat
    /// reaches inside are kept).
    ///
    /// The side bounds come from unprojecting samples of the widened image
    /// border (64 per edge) with the camera model, widened again by 2% of the
    /// span for what lies between samples; if any sample fails to unproject or
    /// lies more than ~84 degrees off axis, the side bounds are dropped.
    pub fn from_camera(
        camera: &Camera,
        cam_from_world: &Rigid3,
        near_m: f64,
        far_m: f64,
        margin_px: f64,
    ) -> Self {
        let normalized_bounds = normalized_bounds(camera, margin_px);
        let cone_half_angle_rad = if normalized_bounds.is_some() {
            None
        } else {
            // The margin as an angle: at most ~1/f rad a pixel for the models
            // here; doubled for safety.
            let focal_px = camera.mean_focal_length().abs().max(1e-9);
            camera
                .max_half_fov_rad()
                .map(|a| a + 2.0 * margin_px / focal_px)
                .filter(|a| a.is_finite() && *a < std::f64::consts::FRAC_PI_2)
        };
        Self {
            cam_from_world: *cam_from_world,
            near_m,
            far_m,
            normalized_bounds,
            cone_half_angle_rad,
        }
    }

    /// Whether a point in the camera frame lies inside the frustum.
    pub fn contains_point_in_cam(&self, p: &Vector3<f64>) -> bool {
        if p.z < self.near_m || p.z > self.far_m || p.norm_squared() > self.far_m * self.far_m {
            return false;
        }
        match self.normalized_bounds {
            Some([x0, x1, y0, y1]) => {
                p.x >= x0 * p.z && p.x <= x1 * p.z && p.y >= y0 * p.z && p.y <= y1 * p.z
            }
            None => match self.cone_half_angle_rad {
                Some(a) => p.xy().norm().atan2(p.z) <= a,
                None => true,
            },
        }
    }

    /// Whether the axis-aligned box `[lo, hi]` (map frame relative to
    /// `origin_in_map`, given as `box_min_rel`, `box_max_rel` with
    /// `centre_rel` the camera centre relative to the same origin) may
    /// intersect the frustum. Conservative.
    fn may_intersect_box(
        &self,
        rotation: &Matrix3<f64>,
        centre_rel: &Vector3<f64>,
        box_min_rel: &Vector3<f64>,
        box_max_rel: &Vector3<f64>,
    ) -> bool {
        // Sphere of radius far around the centre vs box.
        let mut d_sq = 0.0;
        for a in 0..3 {
            let v = if centre_rel[a] < box_min_rel[a] {
                box_min_rel[a] - centre_rel[a]
            } else if centre_rel[a] > box_max_rel[a] {
                centre_rel[a] - box_max_rel[a]
            } else {
                0.0
            };
            d_sq += v * v;
        }
        if d_sq > self.far_m * self.far_m {
            return false;
        }
        // The 8 corners in the camera frame (translation: the centre is the origin).
        let mut corners = [Vector3::zeros(); 8];
        for (k, c) in corners.iter_mut().enumerate() {
            let p = Vector3::new(
                if k & 1 == 0 {
                    box_min_rel.x
                } else {
                    box_max_rel.x
                },
                if k & 2 == 0 {
                    box_min_rel.y
                } else {
                    box_max_rel.y
                },
                if k & 4 == 0 {
                    box_min_rel.z
                } else {
                    box_max_rel.z
                },
            );
            *c = rotation * (p - centre_rel);
        }
        // A plane rejects when all corners lie strictly outside it.
        let outside_all = |f: &dyn Fn(&Vector3<f64>) -> bool| corners.iter().all(f);
        if outside_all(&|c| c.z < self.near_m) || outside_all(&|c| c.z > self.far_m) {
            return false;
        }
        if let Some([x0, x1, y0, y1]) = self.normalized_bounds {
            if outside_all(&|c| c.x < x0 * c.z)
                || outside_all(&|c| c.x > x1 * c.z)
                || outside_all(&|c| c.y < y0 * c.z)
                || outside_all(&|c| c.y > y1 * c.z)
            {
                return false;
            }
        } else if let Some(alpha) = self.cone_half_angle_rad {
            // Bounding sphere of the box against the cone.
            let half = 0.5 * (box_max_rel - box_min_rel);
            let c = rotation * (box_min_rel + half - centre_rel);
            let (dist, radius) = (c.norm(), half.norm());
            if dist > radius {
                let phi = c.xy().norm().atan2(c.z);
                if phi - (radius / dist).asin() > alpha {
                    return false;
                }
            }
        }
        true
    }
}

/// Maps a pixel to the normalised image plane; closed form for the pinhole
/// models, the camera model's iterative unprojection otherwise.
fn unproject_for_bounds(camera: &Camera, pixel: &Vector2<f64>) -> Option<Vector2<f64>> {
    let p = &camera.params;
    match camera.model {
        CameraModel::SimplePinhole if p.len() >= 3 && p[0] > 0.0 => Some(Vector2::new(
            (pixel.x - p[1]) / p[0],
            (pixel.y - p[2]) / p[0],
        )),
        CameraModel::Pinhole if p.len() >= 4 && p[0] > 0.0 && p[1] > 0.0 => Some(Vector2::new(
            (pixel.x - p[2]) / p[0],
            (pixel.y - p[3]) / p[1],
        )),
        _ => {
            let r = camera.unproject(pixel)?;
            if r.z.abs() < 1e-12 || !r.x.is_finite() || !r.y.is_finite() {
                return None;
            }
            Some(Vector2::new(r.x / r.z, r.y / r.z))
        }
    }
}

fn normalized_bounds(camera: &Camera, margin_px: f64) -> Option<[f64; 4]> {
    const SAMPLES_PER_EDGE: usize = 64;
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let (x0, x1, y0, y1) = (-margin_px, w + margin_px, -margin_px, h + margin_px);
    let mut b = [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    for s in 0..=SAMPLES_PER_EDGE {
        let t = s as f64 / SAMPLES_PER_EDGE as f64;
        let xs = x0 + t * (x1 - x0);
        let ys = y0 + t * (y1 - y0);
        for px in [
            Vector2::new(xs, y0),
            Vector2::new(xs, y1),
            Vector2::new(x0, ys),
            Vector2::new(x1, ys),
        ] {
            let n = unproject_for_bounds(camera, &px)?;
            if n.x.abs() > MAX_TAN_HALF_FOV || n.y.abs() > MAX_TAN_HALF_FOV {
                return None;
            }
            b[0] = b[0].min(n.x);
            b[1] = b[1].max(n.x);
            b[2] = b[2].min(n.y);
            b[3] = b[3].max(n.y);
        }
    }
    let pad_x = 0.02 * (b[1] - b[0]);
    let pad_y = 0.02 * (b[3] - b[2]);
    Some([b[0] - pad_x, b[1] + pad_x, b[2] - pad_y, b[3] + pad_y])
}

/// Coarse voxel grid of a [`PointCloud`] (see the module doc). Holds no
/// reference to the cloud; results are point indices into it.
#[derive(Clone, Debug)]
pub struct FrustumGrid {
    cell_size_m: f64,
    /// The cloud's local origin (map frame); cells are aligned on it.
    origin: Vector3<f64>,
    /// Integer coordinates of the cell with packed coordinate 0 on each axis.
    min_cell: [i64; 3],
    /// Largest packed coordinate of an occupied cell on each axis.
    extent: [i64; 3],
    /// Packed coordinates of the occupied cells, sorted (x major, z minor).
    cell_keys: Vec<u64>,
    /// `cell_starts[c]..cell_starts[c + 1]` indexes `point_idxs` for cell `c`.
    cell_starts: Vec<u32>,
    /// Point indices, grouped by cell, increasing within a cell.
    point_idxs: Vec<u32>,
    /// Coordinates of the same points relative to their cell's lower corner,
    /// in units of `cell_size_m / 65535`.
    cell_local: Vec<[u16; 3]>,
}

/// Quantisation steps across a cell.
const CELL_STEPS: f64 = 65535.0;

fn pack(c: [i64; 3]) -> u64 {
    ((c[0] as u64) << (2 * AXIS_BITS)) | ((c[1] as u64) << AXIS_BITS) | (c[2] as u64)
}

fn unpack(key: u64) -> [i64; 3] {
    let m = AXIS_MAX as u64;
    [
        (key >> (2 * AXIS_BITS)) as i64,
        ((key >> AXIS_BITS) & m) as i64,
        (key & m) as i64,
    ]
}

impl FrustumGrid {
    /// Builds the grid of every point of `cloud`.
    pub fn build(cloud: &PointCloud, options: &GridOptions) -> Result<Self, GridError> {
        let s = options.cell_size_m;
        if !(s.is_finite() && s > 0.0) {
            return Err(GridError::BadCellSize(s));
        }
        let n = cloud.len();
        if n >= u32::MAX as usize {
            return Err(GridError::TooManyPoints(n));
        }
        if let Some(index) = cloud.first_non_finite_point() {
            return Err(GridError::NonFinitePoint { index });
        }
        let cell_of = |p: &[f32; 3]| -> [i64; 3] {
            [
                (f64::from(p[0]) / s).floor() as i64,
                (f64::from(p[1]) / s).floor() as i64,
                (f64::from(p[2]) / s).floor() as i64,
            ]
        };
        let (mut min_cell, max_cell) = super::cloud::cell_bounds(&cloud.points, cell_of);
        if n == 0 {
            min_cell = [0; 3];
        }
        for a in 0..3 {
            let cells = max_cell[a] - min_cell[a] + 1;
            if n > 0 && cells > AXIS_MAX {
                return Err(GridError::TooLarge {
                    cells,
                    cell_size_m: s,
                    max: AXIS_MAX,
                });
            }
        }
        // (cell key, point index) pairs sorted: deterministic, one pass to CSR.
        let mut pairs: Vec<(u64, u32)> = cloud
            .points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let c = cell_of(p);
                (
                    pack([c[0] - min_cell[0], c[1] - min_cell[1], c[2] - min_cell[2]]),
                    i as u32,
                )
            })
            .collect();
        pairs.par_sort_unstable();
        let mut cell_keys = Vec::new();
        let mut cell_starts = Vec::new();
        for (k, &(key, _)) in pairs.iter().enumerate() {
            if cell_keys.last() != Some(&key) {
                cell_keys.push(key);
                cell_starts.push(k as u32);
            }
        }
        cell_starts.push(n as u32);
        let step = s / CELL_STEPS;
        let (point_idxs, cell_local): (Vec<u32>, Vec<[u16; 3]>) = pairs
            .par_iter()
            .map(|&(key, idx)| {
                let c = unpack(key);
                let p = cloud.points[idx as usize];
                let mut q = [0u16; 3];
                for a in 0..3 {
                    let lo = (c[a] + min_cell[a]) as f64 * s;
                    let steps = (f64::from(p[a]) - lo) / step;
                    // Non-negative by construction (up to rounding): `as`
                    // saturates, +0.5 rounds.
                    q[a] = (steps + 0.5).clamp(0.0, CELL_STEPS) as u16;
                }
                (idx, q)
            })
            .unzip();
        drop(pairs);
        cell_keys.shrink_to_fit();
        cell_starts.shrink_to_fit();
        let extent = if n == 0 {
            [0; 3]
        } else {
            [0, 1, 2].map(|a| max_cell[a] - min_cell[a])
        };
        Ok(Self {
            cell_size_m: s,
            origin: cloud.origin,
            min_cell,
            extent,
            cell_keys,
            cell_starts,
            point_idxs,
            cell_local,
        })
    }

    pub fn cell_size_m(&self) -> f64 {
        self.cell_size_m
    }

    pub fn num_cells(&self) -> usize {
        self.cell_keys.len()
    }

    pub fn num_points(&self) -> usize {
        self.point_idxs.len()
    }

    /// Heap bytes held by the grid.
    pub fn memory_bytes(&self) -> usize {
        self.cell_keys.capacity() * 8
            + self.cell_starts.capacity() * 4
            + self.point_idxs.capacity() * 4
            + self.cell_local.capacity() * 6
    }

    /// Point indices of occupied cell `cell` (an index below [`num_cells`](Self::num_cells)).
    pub fn cell_points(&self, cell: u32) -> &[u32] {
        let c = cell as usize;
        &self.point_idxs[self.cell_starts[c] as usize..self.cell_starts[c + 1] as usize]
    }

    /// Point indices of occupied cell `cell` and their coordinates relative
    /// to the cell's lower corner [`cell_corner_rel`](Self::cell_corner_rel),
    /// in steps of [`cell_step_m`](Self::cell_step_m).
    pub fn cell_points_local(&self, cell: u32) -> (&[u32], &[[u16; 3]]) {
        let c = cell as usize;
        let range = self.cell_starts[c] as usize..self.cell_starts[c + 1] as usize;
        (&self.point_idxs[range.clone()], &self.cell_local[range])
    }

    /// Quantisation step of the cell-local coordinates (m).
    pub fn cell_step_m(&self) -> f64 {
        self.cell_size_m / CELL_STEPS
    }

    /// Lower corner of occupied cell `cell`, relative to the cloud's origin (m).
    pub fn cell_corner_rel(&self, cell: u32) -> Vector3<f64> {
        let c = unpack(self.cell_keys[cell as usize]);
        Vector3::new(
            (c[0] + self.min_cell[0]) as f64 * self.cell_size_m,
            (c[1] + self.min_cell[1]) as f64 * self.cell_size_m,
            (c[2] + self.min_cell[2]) as f64 * self.cell_size_m,
        )
    }

    /// Box of occupied cell `cell`, relative to the cloud's origin (m).
    fn cell_box_rel(&self, key: u64) -> (Vector3<f64>, Vector3<f64>) {
        let c = unpack(key);
        let lo = Vector3::new(
            (c[0] + self.min_cell[0]) as f64 * self.cell_size_m,
            (c[1] + self.min_cell[1]) as f64 * self.cell_size_m,
            (c[2] + self.min_cell[2]) as f64 * self.cell_size_m,
        );
        // Cells are computed from f32 coordinates: pad by a hair for rounding.
        let pad = 1e-4 * self.cell_size_m + 1e-6 * lo.amax();
        let hi = lo + Vector3::repeat(self.cell_size_m + pad);
        (lo - Vector3::repeat(pad), hi)
    }

    /// Occupied cells (indices, increasing) that may hold points inside
    /// `frustum`. Visits only the columns of cells within `far_m` of the camera
    /// centre.
    pub fn cells_in_frustum(&self, frustum: &Frustum) -> Vec<u32> {
        let mut out = Vec::new();
        if self.cell_keys.is_empty() || !(frustum.far_m > 0.0) {
            return out;
        }
        let centre_rel = frustum.cam_from_world.camera_center() - self.origin;
        let rotation = frustum.cam_from_world.rotation_matrix();
        let s = self.cell_size_m;
        // Packed-coordinate range of the cells within far of the centre, per
        // axis, clamped to the occupied cells before the cast (a far distance
        // of kilometres would otherwise loop over empty columns, and one
        // beyond i64 would saturate).
        let range = |a: usize| -> Option<(i64, i64)> {
            let min = self.min_cell[a] as f64;
            let lo = ((centre_rel[a] - frustum.far_m) / s).floor() - min - 1.0;
            let hi = ((centre_rel[a] + frustum.far_m) / s).floor() - min + 1.0;
            let top = self.extent[a] as f64;
            (lo <= top && hi >= 0.0).then(|| (lo.max(0.0) as i64, hi.min(top) as i64))
        };
        let (Some((x0, x1)), Some((y0, y1)), Some((z0, z1))) = (range(0), range(1), range(2))
        else {
            return out;
        };
        for ix in x0..=x1 {
            for iy in y0..=y1 {
                let first = pack([ix, iy, z0]);
                let last = pack([ix, iy, z1]);
                let start = self.cell_keys.partition_point(|&k| k < first);
                for (offset, &key) in self.cell_keys[start..].iter().enumerate() {
                    if key > last {
                        break;
                    }
                    let (lo, hi) = self.cell_box_rel(key);
                    if frustum.may_intersect_box(&rotation, &centre_rel, &lo, &hi) {
                        out.push((start + offset) as u32);
                    }
                }
            }
        }
        out
    }

    /// Point indices of every point in the cells returned by
    /// [`cells_in_frustum`](Self::cells_in_frustum) (a superset of the points
    /// inside the frustum), increasing by cell then by index.
    pub fn points_in_frustum(&self, frustum: &Frustum) -> Vec<u32> {
        let cells = self.cells_in_frustum(frustum);
        let mut out = Vec::new();
        for c in cells {
            out.extend_from_slice(self.cell_points(c));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::ids::CameraId;
    use nalgebra::UnitQuaternion;

    #[test]
    fn pack_round_trip() {
        for c in [
            [0, 0, 0],
            [1, 2, 3],
            [AXIS_MAX, 0, AXIS_MAX],
            [5, AXIS_MAX, 7],
        ] {
            assert_eq!(unpack(pack(c)), c);
        }
    }

    #[test]
    fn pinhole_bounds_and_culling() {
        let camera = Camera {
            id: CameraId(1),
            model: CameraModel::Pinhole,
            width: 200,
            height: 100,
            params: vec![100.0, 100.0, 100.0, 50.0],
        };
        let b = normalized_bounds(&camera, 0.0).unwrap();
        // x/z in [-1, 1] and y/z in [-0.5, 0.5], padded by 2%.
        assert!((b[0] + 1.04).abs() < 1e-9 && (b[1] - 1.04).abs() < 1e-9);
        assert!((b[2] + 0.52).abs() < 1e-9 && (b[3] - 0.52).abs() < 1e-9);

        // Points: one in front, one behind, one far, one to the side.
        let cloud = PointCloud {
            origin: Vector3::new(1000.0, 2000.0, 0.0),
            points: vec![
                [0.0, 0.0, 10.0],
                [0.0, 0.0, -10.0],
                [0.0, 0.0, 100.0],
                [30.0, 0.0, 5.0],
            ],
            normals: None,
            planarity: None,
        };
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        assert_eq!(grid.num_cells(), 4);
        // Camera at the origin looking along +z (identity rotation).
        let cam_from_world = Rigid3::new(UnitQuaternion::identity(), -cloud.origin);
        let frustum = Frustum::from_camera(&camera, &cam_from_world, 0.5, 40.0, 0.0);
        assert_eq!(grid.points_in_frustum(&frustum), vec![0]);
        // Far limits of kilometres up to beyond i64 cells visit only the
        // occupied cells (they looped over 2^42 empty columns, or wrapped
        // into an empty range): the same points as 200 m.
        let within = |far_m| {
            let f = Frustum::from_camera(&camera, &cam_from_world, 0.5, far_m, 0.0);
            grid.points_in_frustum(&f)
        };
        assert_eq!(within(200.0), vec![0, 2]);
        for far_m in [1e6, 1e20, 1e300, f64::INFINITY] {
            assert_eq!(within(far_m), vec![0, 2], "{far_m}");
        }
        // A camera far outside the occupied cells sees none of them.
        let away = Rigid3::new(
            UnitQuaternion::identity(),
            -cloud.origin - Vector3::new(0.0, 0.0, 1e4),
        );
        let f = Frustum::from_camera(&camera, &away, 0.5, 40.0, 0.0);
        assert!(grid.points_in_frustum(&f).is_empty());
    }
}
