//! Map preparation: voxel downsampling, and normal estimation by PCA over each
//! point's neighbours, with a planarity score and a consistent orientation.
//!
//! Both use a sorted cell grid (points sorted by a packed integer cell key;
//! no hashing), which is exact, deterministic and fast on building-like maps
//! whose walls are parallel to the axes (where kd-trees slow down, see
//! `docs/toolchain-facts.md`).
//!
//! **Normals.** For a point `q` with neighbours `p_j` (all points within
//! `radius_m`, or the `k` nearest within `radius_m`), the covariance
//! `C = 1/n sum (p_j - m)(p_j - m)^T` (m = mean) has eigenvalues
//! `l1 >= l2 >= l3 >= 0`. The normal is the eigenvector of `l3`; the
//! planarity is `(l2 - l3) / l1` in [0, 1] (1 for a flat, isotropic patch;
//! 0 for a line or an isotropic blob), after Weinmann et al.'s
//! dimensionality features. Eigenvalues come in closed form (trigonometric
//! solution of the characteristic cubic), the eigenvector from cross products
//! of the rows of `C - l3 I`.
//!
//! **Orientation** ([`NormalOrientation`]): towards a known sensor position;
//! or, by default, near-vertical normals (within 30 degrees of the z axis)
//! point up (+z: ground and floors face up, ceilings too), and the others
//! point horizontally towards the vertical axis through the centre of the
//! map's bounding box (indoors: into the rooms; along a street: towards the
//! street).
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::map::PointCloud;

/// Errors of the preparation stage.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("invalid option: {0}")]
    InvalidOption(String),
    #[error(
        "the map spans too many cells of {cell_m} m ({bits} bits needed, 64 available); \
         use a larger cell or split the map"
    )]
    GridTooLarge { cell_m: f64, bits: u32 },
    #[error("the map has {0} points; at most 4294967295 are supported")]
    TooManyPoints(usize),
    #[error(
        "the crop box holds none of the {points} points (box x {}..{}, y {}..{}, z {}..{}; \
         the map spans x {:.2}..{:.2}, y {:.2}..{:.2}, z {:.2}..{:.2}, in its own coordinates)",
        crop.min.x, crop.max.x, crop.min.y, crop.max.y, crop.min.z, crop.max.z,
        spans.0.x, spans.1.x, spans.0.y, spans.1.y, spans.0.z, spans.1.z
    )]
    CropHoldsNothing {
        points: usize,
        crop: CropBox,
        /// The map's smallest and largest coordinates.
        spans: (Vector3<f64>, Vector3<f64>),
    },
}

/// How estimated normals are oriented (their sign).
#[derive(Clone, Debug, PartialEq)]
pub enum NormalOrientation {
    /// Towards this position in the map frame (metres), e.g. the sensor.
    TowardsViewpoint(Vector3<f64>),
    /// Near-vertical normals up (+z); the others horizontally towards the
    /// vertical axis through the bounding-box centre.
    UpThenTowardsCentre,
}

/// Options of [`estimate_normals`].
#[derive(Clone, Debug, PartialEq)]
pub struct NormalOptions {
    /// Neighbourhood radius (metres). Default 0.15.
    pub radius_m: f64,
    /// When set, use the `k` nearest neighbours within `radius_m` (the point
    /// itself included) instead of all of them. Default `None`.
    pub k_nearest: Option<usize>,
    /// Fewest neighbours (the point included) for an estimate; points with
    /// fewer get no normal. Default 6.
    pub min_neighbours: usize,
    /// In radius mode, dense neighbourhoods are subsampled (a regular stride
    /// through the candidates) to about this many neighbours, which bounds
    /// the cost on very dense clouds. Default 512.
    pub max_neighbours: usize,
    /// Default [`NormalOrientation::UpThenTowardsCentre`].
    pub orientation: NormalOrientation,
    /// Re-estimate every normal, also the valid ones read from the file.
    /// Default false (valid input normals are kept, with the input's
    /// planarity or 1; estimated ones get their fit's).
    pub recompute_all: bool,
    /// Robust refits of each plane (radius mode; the `k_nearest` mode fits
    /// once): Tukey biweights on the neighbours' distances to the plane,
    /// zero from [`ROBUST_C_PER_NOISE`] times the map's noise on (the
    /// median RMS distance of the plain fits over a sample of the map). 0:
    /// the plain fit. Default 3. Near edges the plain fit leans toward the
    /// other surface: on the synthetic room (seed 0, 15 mm noise, 2 cm
    /// spacing, 0.15 m radius) 11.2 % of the normals were more than 10 deg
    /// off, 7.0 % after the refits (90th percentile 12.1 -> 6.2 deg); the
    /// map's noise came out 14.8 mm. Only the neighbourhoods that do not
    /// look flat are refitted ([`ROBUST_REFIT_ABOVE_NOISE`]): the 20 M-point
    /// map of `scripts/bench_map.sh`, a normal for every point, took 31.9 s
    /// against 11.6 s for the plain fit (41.3 s refitting every point); the
    /// room above 0.78 s against 0.47 s.
    pub robust_iterations: usize,
    /// The robust refits start from the plane of the point's own
    /// neighbours within a third of the radius (when there are
    /// `min_neighbours` of them; else, or when those refits fail, from the
    /// plain fit). Near an edge the plain fit leans toward the other
    /// surface and refits from it stay between the two; the small
    /// neighbourhood lies mostly on the point's own surface. On
    /// the synthetic room (seed 0, 15 mm noise, `prepare-map` defaults)
    /// the normals 5-10 cm from an edge came out 9.2 deg off (median)
    /// refitted from the plain fit and 5.7 deg from the small
    /// neighbourhood's plane, 0-5 cm 25.1 and 13.2 deg; six 24-image scenes
    /// on such maps then mapped at 9.80 mm summed instead of 10.69 mm,
    /// better on all six (session 79, `docs/results.md`). At 30 mm of noise
    /// the small neighbourhood is too noisy to help (the same normals).
    /// false: refits from the plain fit only. Default true.
    pub seeded_refit: bool,
    /// Points left without a normal at `radius_m` (mostly fewer than
    /// `min_neighbours` there) are tried again at twice the radius, this
    /// many times over, where the map is sparser than its spacing says:
    /// the walls of an airborne scan, sampled a few times less densely than
    /// the ground and roofs its spacing follows. At a wider radius a point
    /// gets a normal only if it lies on its fitted plane within
    /// [`WIDENED_ON_PLANE_NOISE`] times the map's noise (a stray return
    /// beside a surface does not). 0: the one radius. Default 2.
    pub sparse_widenings: usize,
}

/// At a widened radius ([`NormalOptions::sparse_widenings`]) a point's
/// distance to its fitted plane may be at most this many times the map's
/// noise (read at the given radius).
pub const WIDENED_ON_PLANE_NOISE: f64 = 4.0;

/// Most [`NormalOptions::sparse_widenings`] (a radius 256 times the given).
pub const MAX_SPARSE_WIDENINGS: usize = 8;

/// Only neighbourhoods whose plain fit leaves an RMS distance above this
/// many times the map's noise are refitted (one flat surface leaves about
/// the noise; the refit changes nothing there and the plain fit costs a
/// third of it).
pub const ROBUST_REFIT_ABOVE_NOISE: f64 = 1.5;

/// The robust refit's zero-weight distance, in units of the map's noise
/// (measured on the room above: 2 -> 8.3 %, 3 -> 7.1 %, 4 -> 6.9 % of the
/// normals more than 10 deg off).
pub const ROBUST_C_PER_NOISE: f64 = 4.0;

impl Default for NormalOptions {
    fn default() -> Self {
        NormalOptions {
            radius_m: 0.15,
            k_nearest: None,
            min_neighbours: 6,
            max_neighbours: 512,
            orientation: NormalOrientation::UpThenTowardsCentre,
            recompute_all: false,
            robust_iterations: 3,
            seeded_refit: true,
            sparse_widenings: 2,
        }
    }
}

impl NormalOptions {
    pub fn validate(&self) -> Result<(), PrepareError> {
        if !(self.radius_m.is_finite() && self.radius_m > 0.0) {
            return Err(PrepareError::InvalidOption(format!(
                "normal radius must be a positive number of metres, got {}",
                self.radius_m
            )));
        }
        if self.min_neighbours < 3 {
            return Err(PrepareError::InvalidOption(
                "at least 3 neighbours are needed to fit a plane".into(),
            ));
        }
        if let Some(k) = self.k_nearest {
            if k < self.min_neighbours {
                return Err(PrepareError::InvalidOption(format!(
                    "k ({k}) is below the minimum neighbour count ({})",
                    self.min_neighbours
                )));
            }
        }
        if self.max_neighbours < self.min_neighbours {
            return Err(PrepareError::InvalidOption(
                "max_neighbours is below min_neighbours".into(),
            ));
        }
        if self.sparse_widenings > MAX_SPARSE_WIDENINGS {
            return Err(PrepareError::InvalidOption(format!(
                "sparse_widenings is {}, at most {MAX_SPARSE_WIDENINGS} (each doubles the radius)",
                self.sparse_widenings
            )));
        }
        if let NormalOrientation::TowardsViewpoint(v) = &self.orientation {
            if !v.iter().all(|c| c.is_finite()) {
                return Err(PrepareError::InvalidOption(
                    "viewpoint is not finite".into(),
                ));
            }
        }
        Ok(())
    }
}

/// What [`estimate_normals`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NormalReport {
    /// Valid normals from the input that were kept.
    pub kept: usize,
    /// Normals estimated by PCA.
    pub estimated: usize,
    /// Points left without a normal (too few neighbours, or a degenerate
    /// neighbourhood); their normal is `[0, 0, 0]`, planarity 0.
    pub failed: usize,
    /// Of `estimated`, those estimated at a widened radius
    /// ([`NormalOptions::sparse_widenings`]).
    pub widened: usize,
    /// The widest radius at which a normal was estimated, metres (0 when
    /// none was widened).
    pub widest_radius_m: f64,
}

impl NormalReport {
    /// For a log line: how many normals took a widened radius, or nothing.
    pub fn widened_note(&self) -> String {
        if self.widened == 0 {
            return String::new();
        }
        format!(
            ", {} of them at radii up to {:.3} m where the map is sparser",
            self.widened, self.widest_radius_m
        )
    }
}

/// Options of [`prepare`].
#[derive(Clone, Debug, PartialEq)]
pub struct PrepareOptions {
    /// Voxel size (metres) for downsampling; 0 disables it. Default 0.03.
    pub voxel_size_m: f64,
    /// The voxel grid thins only clouds of more than this many points
    /// (after the crop); smaller ones are kept whole. Default 0 (always
    /// thinned); `prepare-map` without `--voxel` uses
    /// [`KEEP_WHOLE_MAX_POINTS`].
    pub voxel_above_points: usize,
    pub normals: NormalOptions,
    /// Raise the normal radius to [`NORMAL_RADIUS_PER_SPACING`] times the
    /// (downsampled) cloud's spacing when that is larger, and for a cloud too
    /// noisy for it to [`NORMAL_RADIUS_PER_NOISE`] times its range noise
    /// ([`widen_normal_radius`]). Default true.
    pub radius_follows_spacing: bool,
    /// Drop points left without a normal. Default true.
    pub drop_without_normal: bool,
    /// Keep only the points inside this box (map frame), before anything
    /// else. Default none.
    pub crop: Option<CropBox>,
}

/// An axis-aligned box in the map frame (metres, absolute: a
/// georeferenced map's box is in its own coordinates), bounds included.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropBox {
    pub min: Vector3<f64>,
    pub max: Vector3<f64>,
}

impl CropBox {
    /// Parses `xmin,ymin,zmin,xmax,ymax,zmax`.
    pub fn parse(text: &str) -> Result<CropBox, PrepareError> {
        let bad = |why: &str| {
            PrepareError::InvalidOption(format!(
                "crop box `{text}` is not `xmin,ymin,zmin,xmax,ymax,zmax` ({why})"
            ))
        };
        let values: Vec<f64> = text
            .split(',')
            .map(|v| v.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad("not numbers"))?;
        let [x0, y0, z0, x1, y1, z1] = values[..] else {
            return Err(bad("six numbers needed"));
        };
        let crop = CropBox {
            min: Vector3::new(x0, y0, z0),
            max: Vector3::new(x1, y1, z1),
        };
        crop.validate().map_err(|why| bad(&why))?;
        Ok(crop)
    }

    fn validate(&self) -> Result<(), String> {
        if !self
            .min
            .iter()
            .chain(self.max.iter())
            .all(|v| v.is_finite())
        {
            return Err("a bound is not finite".into());
        }
        if (0..3).any(|a| self.min[a] > self.max[a]) {
            return Err("a minimum above its maximum".into());
        }
        Ok(())
    }

    /// Whether `p` (map frame) lies inside, bounds included.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        (0..3).all(|a| self.min[a] <= p[a] && p[a] <= self.max[a])
    }

    /// Keeps the points of `cloud` inside the box; returns how many were
    /// dropped. Compared in f64 in the map frame, so a bound means the same
    /// whatever the cloud's local origin. A box that holds none of a
    /// non-empty cloud's points is an error that says where the map is
    /// (most often a box in local coordinates for a georeferenced map).
    pub fn apply(&self, cloud: &mut PointCloud) -> Result<usize, PrepareError> {
        let keep = self.inside_flags(cloud);
        if !keep.iter().any(|&k| k) {
            if let Some(spans) = cloud.bounds() {
                return Err(PrepareError::CropHoldsNothing {
                    points: cloud.len(),
                    crop: *self,
                    spans,
                });
            }
        }
        let before = cloud.len();
        cloud.retain_flagged(&keep);
        Ok(before - cloud.len())
    }

    /// Keeps the points of `cloud` inside the box, as [`CropBox::apply`]
    /// does, but a box that holds none of them is no error (one tile of
    /// several); returns how many were dropped.
    pub fn retain(&self, cloud: &mut PointCloud) -> usize {
        let keep = self.inside_flags(cloud);
        let before = cloud.len();
        cloud.retain_flagged(&keep);
        before - cloud.len()
    }

    fn inside_flags(&self, cloud: &PointCloud) -> Vec<bool> {
        (0..cloud.len())
            .into_par_iter()
            .map(|i| self.contains(&cloud.point_in_map(i)))
            .collect()
    }
}

/// `prepare-map` without `--voxel` keeps a cloud of at most this many
/// points (after the crop) whole, and thins a larger one with 3 cm voxels.
/// A room or corridor scanned at 2 cm (about 1 M points) maps closer to the
/// truth whole: on six synthetic 24-image scenes (session 80) the rooms
/// and corridors summed 2.71 mm of camera-centre medians from maps prepared
/// whole (all six within 1.5x of `colmap mapper` + oracle) against 4.91 mm
/// with 3 cm voxels (three of six; corridor 3 1.67 mm against 0.43), which
/// average about half as many map points per plane and mix the two
/// surfaces at creases. 20 M points take about 50 s and 1.4 GB
/// (`scripts/bench_map.sh`).
pub const KEEP_WHOLE_MAX_POINTS: usize = 20_000_000;

impl Default for PrepareOptions {
    fn default() -> Self {
        PrepareOptions {
            voxel_size_m: 0.03,
            voxel_above_points: 0,
            normals: NormalOptions::default(),
            radius_follows_spacing: true,
            drop_without_normal: true,
            crop: None,
        }
    }
}

/// Normal radius per map spacing, for clouds sparser than the default
/// radius suits (a 10 cm map got no normal for 12 % of its points at
/// 0.15 m, a 20 cm one none).
pub const NORMAL_RADIUS_PER_SPACING: f64 = 3.0;

/// A radius under this many times the map's range noise is too small for
/// it: a flat patch of radius `r` with noise `s` along its normal has a
/// planarity of about `1 - 4 s^2 / r^2` less the sampling's spread, and on
/// the synthetic room (3 cm voxels, 0.15 m radius) the median was 0.87 at
/// 15 mm noise, 0.74 at 30 mm (72 % of the map passed the mapper's
/// planarity gate of 0.7) and 0.53 at 50 mm (0.2 % passed, and no model
/// fitted the map). Maps that read up to 33 mm at the default radius keep
/// it (30 mm reads 30 mm there).
pub const MIN_NORMAL_RADIUS_PER_NOISE: f64 = 4.5;

/// The normal radius of a map too noisy for the given one, per unit of its
/// noise ([`MIN_NORMAL_RADIUS_PER_NOISE`]): on the 50 mm room 0.41 m, where
/// the median planarity is 0.86; a wider fit also steadies the normal (its
/// error falls with the radius), at the price of rounder edges. At 6
/// times the noise (0.31 m) three 24-image models from such maps came out
/// 3.8, 9.2 and 6.3 mm off instead of 2.7, 3.6 and 2.7 mm.
pub const NORMAL_RADIUS_PER_NOISE: f64 = 8.0;

/// Largest normal radius the noise widens to, metres (a map noisier than
/// 10 cm is not a surface map the mapper can use).
const MAX_NOISE_NORMAL_RADIUS_M: f64 = 0.8;

/// What [`widen_normal_radius`] measured.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MapScales {
    /// The map's spacing on its surfaces, metres (`None`: not estimated).
    pub spacing_m: Option<f64>,
    /// The map's range noise at the radius chosen, metres
    /// ([`estimate_noise_m`]; `None`: not estimated).
    pub noise_m: Option<f64>,
}

/// Raises `options.radius_m` to [`NORMAL_RADIUS_PER_SPACING`] times the
/// spacing of `cloud` on its surfaces
/// ([`crate::map::index::MapIndex::surface_spacing_m`]) when that is
/// larger; then, when the radius is under [`MIN_NORMAL_RADIUS_PER_NOISE`]
/// times the map's range noise ([`estimate_noise_m`]), to
/// [`NORMAL_RADIUS_PER_NOISE`] times it, measured once more at that radius
/// (a noisy map reads noisier at a wider one: 42 mm at 0.15 m, 48-52 mm at
/// 0.35-0.41 m on a map of 50 mm noise). The noise returned is the last
/// measured.
pub fn widen_normal_radius(
    options: &mut NormalOptions,
    cloud: &PointCloud,
) -> Result<MapScales, PrepareError> {
    let spacing_m = crate::map::index::MapIndex::spacing_of(cloud);
    if let Some(spacing) = spacing_m {
        options.radius_m = options.radius_m.max(NORMAL_RADIUS_PER_SPACING * spacing);
    }
    let mut noise_m = estimate_noise_m(cloud, options)?;
    let widen = |noise: f64, options: &mut NormalOptions| {
        let wanted = (NORMAL_RADIUS_PER_NOISE * noise).min(MAX_NOISE_NORMAL_RADIUS_M);
        options.radius_m = options.radius_m.max(wanted);
    };
    if let Some(noise) = noise_m.filter(|n| MIN_NORMAL_RADIUS_PER_NOISE * n > options.radius_m) {
        widen(noise, options);
        if let Some(again) = estimate_noise_m(cloud, options)? {
            widen(again, options);
            noise_m = Some(again);
        }
    }
    Ok(MapScales { spacing_m, noise_m })
}

impl PrepareOptions {
    pub fn validate(&self) -> Result<(), PrepareError> {
        if !(self.voxel_size_m.is_finite() && self.voxel_size_m >= 0.0) {
            return Err(PrepareError::InvalidOption(format!(
                "voxel size must be a non-negative number of metres, got {}",
                self.voxel_size_m
            )));
        }
        if let Some(crop) = &self.crop {
            crop.validate()
                .map_err(|why| PrepareError::InvalidOption(format!("crop box: {why}")))?;
        }
        self.normals.validate()
    }
}

/// What [`prepare`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PrepareReport {
    pub input_points: usize,
    /// Points outside the crop box, dropped first.
    pub dropped_by_crop: usize,
    pub after_voxel: usize,
    /// The cloud was kept whole although a voxel size was set (it held at
    /// most [`PrepareOptions::voxel_above_points`] points).
    pub kept_whole: bool,
    /// The normal radius used, metres.
    pub normal_radius_m: f64,
    /// The map's range noise at that radius, metres, when the radius
    /// followed the map ([`widen_normal_radius`]).
    pub noise_m: Option<f64>,
    pub normals: NormalReport,
    pub dropped_without_normal: usize,
    pub output_points: usize,
}

/// Crops, downsamples, estimates normals where needed, and drops points left
/// without a normal (when asked).
pub fn prepare(
    cloud: PointCloud,
    options: &PrepareOptions,
) -> Result<(PointCloud, PrepareReport), PrepareError> {
    options.validate()?;
    let mut report = PrepareReport {
        input_points: cloud.len(),
        ..Default::default()
    };
    let mut cloud = cloud;
    if let Some(crop) = &options.crop {
        report.dropped_by_crop = crop.apply(&mut cloud)?;
    }
    report.kept_whole = options.voxel_size_m > 0.0 && cloud.len() <= options.voxel_above_points;
    let mut cloud = if options.voxel_size_m > 0.0 && !report.kept_whole {
        voxel_downsample(&cloud, options.voxel_size_m)?
    } else {
        cloud
    };
    report.after_voxel = cloud.len();
    let mut normals = options.normals.clone();
    if options.radius_follows_spacing {
        let scales = widen_normal_radius(&mut normals, &cloud)?;
        report.noise_m = scales.noise_m;
    }
    report.normal_radius_m = normals.radius_m;
    report.normals = estimate_normals(&mut cloud, &normals)?;
    if options.drop_without_normal && report.normals.failed > 0 {
        let before = cloud.len();
        retain_with_normal(&mut cloud);
        report.dropped_without_normal = before - cloud.len();
    }
    report.output_points = cloud.len();
    Ok((cloud, report))
}

fn normal_is_set(n: &[f32; 3]) -> bool {
    n[0] != 0.0 || n[1] != 0.0 || n[2] != 0.0
}

/// Keeps only the points with a non-zero normal (all points when the cloud
/// has no normals at all: nothing to judge by).
fn retain_with_normal(cloud: &mut PointCloud) {
    let Some(normals) = &cloud.normals else {
        return;
    };
    let keep: Vec<bool> = normals.iter().map(normal_is_set).collect();
    cloud.retain_flagged(&keep);
}

/// Points sorted into cubic cells of side `cell_m`, aligned on the map frame
/// (multiples of `cell_m` from the map's zero, not from the local origin).
struct CellGrid {
    /// Sorted distinct cell keys.
    keys: Vec<u64>,
    /// `order[starts[c]..starts[c + 1]]` are the points of cell `c`.
    starts: Vec<u32>,
    /// Point indices sorted by (cell key, index).
    order: Vec<u32>,
    /// Bit position of the x, y, z cell coordinates in a key.
    shifts: [u32; 3],
}

impl CellGrid {
    fn new(cloud: &PointCloud, cell_m: f64) -> Result<CellGrid, PrepareError> {
        if cloud.len() > u32::MAX as usize {
            return Err(PrepareError::TooManyPoints(cloud.len()));
        }
        let origin = cloud.origin;
        let cell_of = move |p: &[f32; 3]| -> [i64; 3] {
            [
                ((origin.x + f64::from(p[0])) / cell_m).floor() as i64,
                ((origin.y + f64::from(p[1])) / cell_m).floor() as i64,
                ((origin.z + f64::from(p[2])) / cell_m).floor() as i64,
            ]
        };
        let (lo, hi) = super::cloud::cell_bounds(&cloud.points, cell_of);
        // One spare cell on each side so that neighbour keys never wrap.
        let mut bits = [1u32; 3];
        for a in 0..3 {
            if cloud.is_empty() {
                break;
            }
            let span = (hi[a] - lo[a]) as u64 + 3;
            bits[a] = 64 - span.leading_zeros();
        }
        let total: u32 = bits.iter().sum();
        if total > 64 {
            return Err(PrepareError::GridTooLarge {
                cell_m,
                bits: total,
            });
        }
        let shifts = [bits[2] + bits[1], bits[2], 0];
        let mut pairs: Vec<(u64, u32)> = cloud
            .points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let c = cell_of(p);
                let mut key = 0u64;
                for a in 0..3 {
                    key |= ((c[a] - lo[a] + 1) as u64) << shifts[a];
                }
                (key, i as u32)
            })
            .collect();
        pairs.par_sort_unstable();
        let mut keys = Vec::new();
        let mut starts = Vec::new();
        for (slot, &(key, _)) in pairs.iter().enumerate() {
            if keys.last() != Some(&key) {
                keys.push(key);
                starts.push(slot as u32);
            }
        }
        starts.push(pairs.len() as u32);
        let order = pairs.into_iter().map(|(_, i)| i).collect();
        Ok(CellGrid {
            keys,
            starts,
            order,
            shifts,
        })
    }

    /// Positions in `order` of the points of cell `c`.
    fn cell_range(&self, c: usize) -> std::ops::Range<usize> {
        self.starts[c] as usize..self.starts[c + 1] as usize
    }

    fn cell_points(&self, c: usize) -> &[u32] {
        &self.order[self.cell_range(c)]
    }

    /// Index of the cell with `key`, if occupied.
    fn find(&self, key: u64) -> Option<usize> {
        self.keys.binary_search(&key).ok()
    }

    /// The key of the cell offset by `d` (each in -1..=1) from `key`.
    fn neighbour_key(&self, key: u64, d: [i64; 3]) -> u64 {
        let mut k = key;
        for (da, shift) in d.iter().zip(self.shifts) {
            k = k.wrapping_add((da << shift) as u64);
        }
        k
    }
}

/// Centroid per voxel of side `voxel_size_m` (aligned on multiples of the
/// size in the map frame). Normals, when present, are averaged over the
/// voxel's valid normals and renormalised (zero when none is valid or they
/// cancel); planarity is averaged. Output order: sorted voxel keys (x major),
/// deterministic.
pub fn voxel_downsample(cloud: &PointCloud, voxel_size_m: f64) -> Result<PointCloud, PrepareError> {
    if !(voxel_size_m.is_finite() && voxel_size_m > 0.0) {
        return Err(PrepareError::InvalidOption(format!(
            "voxel size must be a positive number of metres, got {voxel_size_m}"
        )));
    }
    let grid = CellGrid::new(cloud, voxel_size_m)?;
    let merged: Vec<([f32; 3], [f32; 3], f32)> = (0..grid.keys.len())
        .into_par_iter()
        .map(|c| {
            let members = grid.cell_points(c);
            let mut sum = [0.0f64; 3];
            let mut nsum = [0.0f64; 3];
            let mut psum = 0.0f64;
            for &i in members {
                let p = cloud.points[i as usize];
                for a in 0..3 {
                    sum[a] += f64::from(p[a]);
                }
                if let Some(normals) = &cloud.normals {
                    let n = normals[i as usize];
                    for a in 0..3 {
                        nsum[a] += f64::from(n[a]);
                    }
                }
                if let Some(planarity) = &cloud.planarity {
                    psum += f64::from(planarity[i as usize]);
                }
            }
            let count = members.len() as f64;
            let centroid = [
                (sum[0] / count) as f32,
                (sum[1] / count) as f32,
                (sum[2] / count) as f32,
            ];
            let len = (nsum[0] * nsum[0] + nsum[1] * nsum[1] + nsum[2] * nsum[2]).sqrt();
            let normal = if len > 1e-6 * count {
                [
                    (nsum[0] / len) as f32,
                    (nsum[1] / len) as f32,
                    (nsum[2] / len) as f32,
                ]
            } else {
                [0.0; 3]
            };
            (centroid, normal, (psum / count) as f32)
        })
        .collect();
    Ok(PointCloud {
        origin: cloud.origin,
        points: merged.iter().map(|m| m.0).collect(),
        normals: cloud
            .normals
            .as_ref()
            .map(|_| merged.iter().map(|m| m.1).collect()),
        planarity: cloud
            .planarity
            .as_ref()
            .map(|_| merged.iter().map(|m| m.2).collect()),
    })
}

/// Eigen-decomposition of a symmetric 3x3 matrix for plane fitting: returns
/// the eigenvalues in decreasing order and the unit eigenvector of the
/// smallest one, or `None` when the matrix is a multiple of the identity
/// (including zero: no preferred direction).
pub fn smallest_eigenvector(a: &[[f64; 3]; 3]) -> Option<([f64; 3], [f64; 3])> {
    let p1 = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
    let q = (a[0][0] + a[1][1] + a[2][2]) / 3.0;
    let d = [a[0][0] - q, a[1][1] - q, a[2][2] - q];
    let p2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + 2.0 * p1;
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(p2 > (1e-14 * scale) * (1e-14 * scale)) || !p2.is_finite() {
        return None;
    }
    let p = (p2 / 6.0).sqrt();
    // B = (A - q I) / p; r = det(B) / 2.
    let b = [
        [d[0] / p, a[0][1] / p, a[0][2] / p],
        [a[1][0] / p, d[1] / p, a[1][2] / p],
        [a[2][0] / p, a[2][1] / p, d[2] / p],
    ];
    let det = b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1])
        - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0])
        + b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0]);
    let r = (det / 2.0).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let l1 = q + 2.0 * p * phi.cos();
    let l3 = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let l2 = 3.0 * q - l1 - l3;
    let rows = [
        [a[0][0] - l3, a[0][1], a[0][2]],
        [a[1][0], a[1][1] - l3, a[1][2]],
        [a[2][0], a[2][1], a[2][2] - l3],
    ];
    let cross = |u: &[f64; 3], v: &[f64; 3]| {
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    };
    let norm_sq = |u: &[f64; 3]| u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
    let candidates = [
        cross(&rows[0], &rows[1]),
        cross(&rows[0], &rows[2]),
        cross(&rows[1], &rows[2]),
    ];
    let mut best = candidates[0];
    for c in &candidates[1..] {
        if norm_sq(c) > norm_sq(&best) {
            best = *c;
        }
    }
    let row_scale = rows.iter().map(norm_sq).fold(0.0f64, f64::max);
    let v = if norm_sq(&best) > 1e-20 * row_scale * row_scale {
        best
    } else {
        // l2 == l3 (a line): any direction orthogonal to the dominant row.
        let mut r = rows[0];
        for row in &rows[1..] {
            if norm_sq(row) > norm_sq(&r) {
                r = *row;
            }
        }
        let axis = if r[0].abs() < 0.9 * norm_sq(&r).sqrt() {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        cross(&r, &axis)
    };
    let len = norm_sq(&v).sqrt();
    if !(len > 0.0) {
        return None;
    }
    Some(([l1, l2, l3], [v[0] / len, v[1] / len, v[2] / len]))
}

/// A plane fitted to (weighted) moments: unit normal, planarity, the mean
/// offset from the query point and the RMS distance of the points to the
/// plane (metres).
#[derive(Clone, Copy, Debug)]
struct PlaneFit {
    normal: [f64; 3],
    planarity: f32,
    mean: [f64; 3],
    rms_m: f64,
}

/// The plane of a neighbourhood given as offsets `d` from the query point
/// (metres), by its moments: `s1 = sum w d`, `s2 = sum w d d^T`, the
/// weights `w` summing to `weight` (1 each for a plain fit).
fn fit_plane_weighted(weight: f64, s1: &[f64; 3], s2: &[[f64; 3]; 3]) -> Option<PlaneFit> {
    if !(weight > 0.0) {
        return None;
    }
    let inv = 1.0 / weight;
    let m = [s1[0] * inv, s1[1] * inv, s1[2] * inv];
    let mut cov = [[0.0; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            cov[r][c] = s2[r][c] * inv - m[r] * m[c];
        }
    }
    let (l, normal) = smallest_eigenvector(&cov)?;
    let planarity = if l[0] > 0.0 {
        ((l[1] - l[2].max(0.0)) / l[0]).clamp(0.0, 1.0)
    } else {
        0.0
    };
    Some(PlaneFit {
        normal,
        planarity: planarity as f32,
        mean: m,
        rms_m: l[2].max(0.0).sqrt(),
    })
}

/// Lanes of the neighbour accumulation (the compiler vectorises them).
const LANES: usize = 8;

/// Neighbour candidates of one cell, structure of arrays in blocks of
/// [`LANES`], the last block padded with far-away points.
#[derive(Default)]
struct Candidates {
    x: Vec<[f32; LANES]>,
    y: Vec<[f32; LANES]>,
    z: Vec<[f32; LANES]>,
    len: usize,
}

impl Candidates {
    /// Far enough never to be a neighbour, small enough that `0 * d` is 0.
    const FAR_M: f32 = 1.0e9;

    /// Every `stride`-th point of the concatenation of `slices`.
    fn fill<'a>(&mut self, slices: impl Iterator<Item = &'a [[f32; 3]]>, stride: usize) {
        self.x.clear();
        self.y.clear();
        self.z.clear();
        self.len = 0;
        // Position in the concatenation of the next point to take.
        let mut skip = 0usize;
        for slice in slices {
            let mut k = skip;
            while k < slice.len() {
                let p = slice[k];
                let (b, l) = (self.len / LANES, self.len % LANES);
                if l == 0 {
                    self.x.push([Self::FAR_M; LANES]);
                    self.y.push([Self::FAR_M; LANES]);
                    self.z.push([Self::FAR_M; LANES]);
                }
                self.x[b][l] = p[0];
                self.y[b][l] = p[1];
                self.z[b][l] = p[2];
                self.len += 1;
                k += stride;
            }
            skip = k - slice.len();
        }
    }

    fn offset(&self, j: usize, q: [f32; 3]) -> [f32; 3] {
        let (b, l) = (j / LANES, j % LANES);
        [
            self.x[b][l] - q[0],
            self.y[b][l] - q[1],
            self.z[b][l] - q[2],
        ]
    }

    /// Count, first and second moments of the offsets `p - q` of the
    /// candidates within `sqrt(radius_sq)` of `q`. Accumulated in f32 per
    /// lane (offsets are below the radius, so sums of a few hundred squares
    /// lose nothing that matters), lanes summed in f64 in a fixed order.
    fn radius_moments(&self, q: [f32; 3], radius_sq: f32) -> (usize, [f64; 3], [[f64; 3]; 3]) {
        let (n, s1, s2) = self.weighted_moments(q, radius_sq, |_| 1.0);
        (n.round() as usize, s1, s2)
    }

    /// [`Self::radius_moments`], each offset `d` weighted by Tukey's
    /// biweight of its distance to the plane through `q + mean` with unit
    /// normal `normal` (`c_m`: the distance at which the weight reaches 0);
    /// the count is the weights' sum.
    fn biweight_moments(
        &self,
        q: [f32; 3],
        radius_sq: f32,
        normal: [f64; 3],
        mean: [f64; 3],
        c_m: f64,
    ) -> (f64, [f64; 3], [[f64; 3]; 3]) {
        let nf = [normal[0] as f32, normal[1] as f32, normal[2] as f32];
        let offset = (normal[0] * mean[0] + normal[1] * mean[1] + normal[2] * mean[2]) as f32;
        let inv_c_sq = (1.0 / (c_m * c_m)) as f32;
        self.weighted_moments(q, radius_sq, |d| {
            let r = nf[0] * d[0] + nf[1] * d[1] + nf[2] * d[2] - offset;
            let u = (1.0 - r * r * inv_c_sq).max(0.0);
            u * u
        })
    }

    /// Weight sum, first and second moments of the offsets `d = p - q` of
    /// the candidates within `sqrt(radius_sq)` of `q`, each weighted by
    /// `weight(d)`.
    #[inline(always)]
    fn weighted_moments(
        &self,
        q: [f32; 3],
        radius_sq: f32,
        weight: impl Fn([f32; 3]) -> f32,
    ) -> (f64, [f64; 3], [[f64; 3]; 3]) {
        let mut n = [0.0f32; LANES];
        let (mut sx, mut sy, mut sz) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        let (mut sxx, mut sxy, mut sxz) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        let (mut syy, mut syz, mut szz) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        for ((xb, yb), zb) in self.x.iter().zip(&self.y).zip(&self.z) {
            for l in 0..LANES {
                let dx = xb[l] - q[0];
                let dy = yb[l] - q[1];
                let dz = zb[l] - q[2];
                let w = if dx * dx + dy * dy + dz * dz <= radius_sq {
                    weight([dx, dy, dz])
                } else {
                    0.0
                };
                let (wx, wy, wz) = (w * dx, w * dy, w * dz);
                n[l] += w;
                sx[l] += wx;
                sy[l] += wy;
                sz[l] += wz;
                sxx[l] += wx * dx;
                sxy[l] += wx * dy;
                sxz[l] += wx * dz;
                syy[l] += wy * dy;
                syz[l] += wy * dz;
                szz[l] += wz * dz;
            }
        }
        let total = |a: &[f32; LANES]| a.iter().map(|v| f64::from(*v)).sum::<f64>();
        let (xx, xy, xz) = (total(&sxx), total(&sxy), total(&sxz));
        let (yy, yz, zz) = (total(&syy), total(&syz), total(&szz));
        (
            total(&n),
            [total(&sx), total(&sy), total(&sz)],
            [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]],
        )
    }
}

/// Refits `start` (a plane of `q`'s neighbourhood) with Tukey biweights
/// on the points' distances to the plane (weight 0 from `c_m` on),
/// `iterations` times: near an edge, where a plain fit leans toward the
/// other surface, the surface holding most of the neighbourhood wins.
/// `None` when a refit fails or its weights sum to less than `min_weight`
/// (the fewest neighbours of a fit).
fn robust_refit(
    candidates: &Candidates,
    q: [f32; 3],
    radius_sq: f32,
    start: PlaneFit,
    c_m: f64,
    iterations: usize,
    min_weight: f64,
) -> Option<PlaneFit> {
    let mut current = start;
    for _ in 0..iterations {
        let (w, s1, s2) =
            candidates.biweight_moments(q, radius_sq, current.normal, current.mean, c_m);
        current = fit_plane_weighted(w, &s1, &s2).filter(|_| w >= min_weight)?;
    }
    Some(current)
}

/// The plane of `q`'s neighbours within a third of the radius, when there
/// are at least `min_count` of them: the start of the robust refits with
/// [`NormalOptions::seeded_refit`].
fn seed_plane(
    candidates: &Candidates,
    q: [f32; 3],
    radius_sq: f32,
    min_count: usize,
) -> Option<PlaneFit> {
    let (count, s1, s2) = candidates.radius_moments(q, radius_sq / 9.0);
    if count < min_count {
        return None;
    }
    fit_plane_weighted(count as f64, &s1, &s2)
}

/// Cosine of the largest angle from the z axis at which a normal counts as
/// vertical for orientation (30 degrees).
const VERTICAL_COS: f64 = 0.866_025_403_784_438_6;

/// Puts the points of cell `c`'s 27 neighbouring cells (itself included)
/// into `candidates`; in radius mode a regular subsample when there are many
/// more than `options.max_neighbours`.
fn gather_candidates(
    grid: &CellGrid,
    sorted_points: &[[f32; 3]],
    options: &NormalOptions,
    c: usize,
    candidates: &mut Candidates,
) {
    let key = grid.keys[c];
    let mut cells = [usize::MAX; 27];
    let mut total = 0usize;
    let mut slot = 0;
    for dx in -1..=1 {
        for dy in -1..=1 {
            for dz in -1..=1 {
                if let Some(nc) = grid.find(grid.neighbour_key(key, [dx, dy, dz])) {
                    cells[slot] = nc;
                    total += grid.cell_range(nc).len();
                }
                slot += 1;
            }
        }
    }
    let stride = match options.k_nearest {
        Some(_) => 1,
        None => total.div_ceil(3 * options.max_neighbours).max(1),
    };
    candidates.fill(
        cells
            .iter()
            .filter(|&&nc| nc != usize::MAX)
            .map(|&nc| &sorted_points[grid.cell_range(nc)]),
        stride,
    );
}

/// The map's range noise as the plane fits see it: the median RMS distance
/// to the plain fit over the points of about 2000 cells (of side the
/// radius), counting neighbourhoods of at least `min_neighbours` points
/// that look like a surface (planarity 0.5 and more). `None` when none
/// does.
fn sampled_noise_m(
    grid: &CellGrid,
    sorted_points: &[[f32; 3]],
    options: &NormalOptions,
) -> Option<f64> {
    let radius_sq = (options.radius_m * options.radius_m) as f32;
    let step = (grid.keys.len() / 2000).max(1);
    let mut rms: Vec<f64> = (0..grid.keys.len())
        .into_par_iter()
        .step_by(step)
        .map_init(Candidates::default, |candidates, c| {
            gather_candidates(grid, sorted_points, options, c, candidates);
            sorted_points[grid.cell_range(c)]
                .iter()
                .filter_map(|&q| {
                    let (count, s1, s2) = candidates.radius_moments(q, radius_sq);
                    let fit = fit_plane_weighted(count as f64, &s1, &s2)?;
                    (count >= options.min_neighbours && fit.planarity >= 0.5).then_some(fit.rms_m)
                })
                .collect::<Vec<f64>>()
        })
        .flatten()
        .collect();
    rms.sort_by(f64::total_cmp);
    rms.get(rms.len() / 2).copied()
}

/// The map's range noise, metres, as [`estimate_normals`] with `options`
/// sees it (the median RMS distance of its plain plane fits over a sample
/// of the map; about the noise along the normal on flat surfaces). `None`
/// when no sampled neighbourhood looks like a surface.
pub fn estimate_noise_m(
    cloud: &PointCloud,
    options: &NormalOptions,
) -> Result<Option<f64>, PrepareError> {
    options.validate()?;
    if cloud.is_empty() {
        return Ok(None);
    }
    let grid = CellGrid::new(cloud, options.radius_m)?;
    let sorted_points: Vec<[f32; 3]> = grid
        .order
        .par_iter()
        .map(|&i| cloud.points[i as usize])
        .collect();
    Ok(sampled_noise_m(&grid, &sorted_points, options))
}

/// Estimates normals (and a planarity score for every point) by PCA, see the
/// module documentation. Valid input normals are kept unless
/// `recompute_all`; missing or zero ones (the readers store invalid normals
/// as zero) are estimated. The cloud keeps its point order.
pub fn estimate_normals(
    cloud: &mut PointCloud,
    options: &NormalOptions,
) -> Result<NormalReport, PrepareError> {
    options.validate()?;
    let (mut report, noise_m) = estimate_at_radius(cloud, options, None)?;
    if report.failed == 0 || options.sparse_widenings == 0 {
        return Ok(report);
    }
    // The noise as the given radius reads it: a wider one reads the
    // surfaces' curvature and edges as well.
    let noise_m = match noise_m {
        Some(noise) => noise,
        None => estimate_noise_m(cloud, options)?.unwrap_or(0.0),
    };
    let mut wider = NormalOptions {
        recompute_all: false,
        ..options.clone()
    };
    for _ in 0..options.sparse_widenings {
        if report.failed == 0 {
            break;
        }
        wider.radius_m *= 2.0;
        let (again, _) =
            estimate_at_radius(cloud, &wider, Some((WIDENED_ON_PLANE_NOISE, noise_m)))?;
        if again.estimated > 0 {
            report.estimated += again.estimated;
            report.widened += again.estimated;
            report.widest_radius_m = wider.radius_m;
        }
        report.failed = again.failed;
    }
    Ok(report)
}

/// Scores every point's planarity as [`estimate_normals`] would for a map
/// without normals (the same fits, refits and widenings), and keeps the
/// cloud's normals as they are. For a map that came with normals but no
/// planarity: the mapper's planarity gate then drops the map points whose
/// neighbourhood straddles a crease or a surface's border, as it does on
/// maps whose normals it estimated. A point whose fit failed (too few
/// neighbours even at the widened radii) gets 1, not judged, as a kept
/// normal does in [`estimate_normals`]: a poor fit here must not drop a
/// normal the file gave. Returns what the fits did (their normals are
/// discarded).
pub fn score_planarity(
    cloud: &mut PointCloud,
    options: &NormalOptions,
) -> Result<NormalReport, PrepareError> {
    let mut scratch = PointCloud {
        origin: cloud.origin,
        points: std::mem::take(&mut cloud.points),
        normals: None,
        planarity: None,
    };
    let result = estimate_normals(&mut scratch, options);
    cloud.points = scratch.points;
    let report = result?;
    // One score per point whatever the fits left (1: not judged).
    let n = cloud.points.len();
    let mut planarity = scratch.planarity.unwrap_or_else(|| vec![1.0; n]);
    if let Some(fitted) = &scratch.normals {
        for (score, normal) in planarity.iter_mut().zip(fitted) {
            if !normal_is_set(normal) {
                *score = 1.0;
            }
        }
    }
    cloud.planarity = Some(planarity);
    Ok(report)
}

/// One pass of [`estimate_normals`] at `options.radius_m` (its
/// `sparse_widenings` not applied), and the map's noise it read (for the
/// robust refits; `None` when it read none). With `on_plane` `(k,
/// noise_m)`, that noise is used instead of reading it, and a point gets a
/// normal only if it lies within `k` times it of its fitted plane. Points
/// with a valid normal are not fitted unless `recompute_all`.
fn estimate_at_radius(
    cloud: &mut PointCloud,
    options: &NormalOptions,
    on_plane: Option<(f64, f64)>,
) -> Result<(NormalReport, Option<f64>), PrepareError> {
    let n = cloud.len();
    if n == 0 {
        cloud.normals.get_or_insert_with(Vec::new);
        cloud.planarity.get_or_insert_with(Vec::new);
        return Ok((NormalReport::default(), None));
    }
    let grid = CellGrid::new(cloud, options.radius_m)?;
    // Viewpoint in local (offset) coordinates.
    let viewpoint = match &options.orientation {
        NormalOrientation::TowardsViewpoint(v) => v - cloud.origin,
        NormalOrientation::UpThenTowardsCentre => {
            let (lo, hi) = cloud
                .points
                .par_iter()
                .fold(
                    || ([f32::MAX; 3], [f32::MIN; 3]),
                    |(mut lo, mut hi), p| {
                        for a in 0..3 {
                            lo[a] = lo[a].min(p[a]);
                            hi[a] = hi[a].max(p[a]);
                        }
                        (lo, hi)
                    },
                )
                .reduce(
                    || ([f32::MAX; 3], [f32::MIN; 3]),
                    |(l1, h1), (l2, h2)| {
                        (
                            [l1[0].min(l2[0]), l1[1].min(l2[1]), l1[2].min(l2[2])],
                            [h1[0].max(h2[0]), h1[1].max(h2[1]), h1[2].max(h2[2])],
                        )
                    },
                );
            Vector3::new(
                0.5 * (f64::from(lo[0]) + f64::from(hi[0])),
                0.5 * (f64::from(lo[1]) + f64::from(hi[1])),
                0.5 * (f64::from(lo[2]) + f64::from(hi[2])),
            )
        }
    };
    let up_first = matches!(options.orientation, NormalOrientation::UpThenTowardsCentre);
    let radius_sq = (options.radius_m * options.radius_m) as f32;
    // The points in grid order: each cell's points are contiguous, so the
    // neighbour gathers below read memory sequentially.
    let sorted_points: Vec<[f32; 3]> = grid
        .order
        .par_iter()
        .map(|&i| cloud.points[i as usize])
        .collect();

    // Results in grid order: (normal, planarity); planarity < 0 = failed.
    let mut results = vec![([0.0f32; 3], -1.0f32); n];
    let mut slices: Vec<&mut [([f32; 3], f32)]> = Vec::with_capacity(grid.keys.len());
    let mut rest: &mut [([f32; 3], f32)] = &mut results;
    for c in 0..grid.keys.len() {
        let len = (grid.starts[c + 1] - grid.starts[c]) as usize;
        let (head, tail) = rest.split_at_mut(len);
        slices.push(head);
        rest = tail;
    }
    let gather = |c: usize, candidates: &mut Candidates| {
        gather_candidates(&grid, &sorted_points, options, c, candidates)
    };
    // The points to fit, in grid order: those without a valid normal to keep.
    let skip: Option<Vec<bool>> = match &cloud.normals {
        Some(normals) if !options.recompute_all => Some(
            grid.order
                .par_iter()
                .map(|&i| normal_is_set(&normals[i as usize]))
                .collect(),
        ),
        _ => None,
    };
    let robust = options.robust_iterations > 0 && options.k_nearest.is_none();
    // The map's noise, from the plain fits of a sample of cells, for the
    // robust refit's scale and the on-plane test. Floors for noise-free
    // maps: 1 % of the radius.
    let read_noise_m = match on_plane {
        None if robust => {
            let noise_m = sampled_noise_m(&grid, &sorted_points, options).unwrap_or(0.0);
            log::debug!(
                "map noise at the {:.3} m normal radius: {:.4} m",
                options.radius_m,
                noise_m
            );
            Some(noise_m)
        }
        _ => None,
    };
    let noise_m = on_plane.map_or(read_noise_m.unwrap_or(0.0), |(_, noise)| noise);
    let floor_m = options.radius_m / 100.0;
    let robust_c_m = robust.then(|| {
        (
            (ROBUST_C_PER_NOISE * noise_m).max(floor_m),
            (ROBUST_REFIT_ABOVE_NOISE * noise_m).max(floor_m),
        )
    });
    let on_plane_m = on_plane.map(|(k, _)| k * noise_m.max(floor_m));
    slices.into_par_iter().enumerate().for_each_init(
        || (Candidates::default(), Vec::<(f32, u32)>::new()),
        |(candidates, nearest), (c, out)| {
            let range = grid.cell_range(c);
            let skipped = |at: usize| skip.as_ref().is_some_and(|s| s[range.start + at]);
            if (0..range.len()).all(skipped) {
                return;
            }
            gather(c, candidates);
            for (at, (&q, slot)) in sorted_points[range.clone()]
                .iter()
                .zip(out.iter_mut())
                .enumerate()
            {
                if skipped(at) {
                    continue;
                }
                let (count, s1, s2) = match options.k_nearest {
                    None => candidates.radius_moments(q, radius_sq),
                    Some(k) => {
                        let mut count = 0usize;
                        let mut s1 = [0.0f64; 3];
                        let mut s2 = [[0.0f64; 3]; 3];
                        nearest.clear();
                        for j in 0..candidates.len {
                            let d = candidates.offset(j, q);
                            let dist_sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                            if dist_sq <= radius_sq {
                                nearest.push((dist_sq, j as u32));
                            }
                        }
                        if nearest.len() > k {
                            nearest.select_nth_unstable_by(k - 1, |a, b| {
                                a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
                            });
                            nearest.truncate(k);
                        }
                        for &(_, j) in nearest.iter() {
                            let d = candidates.offset(j as usize, q);
                            let d = [f64::from(d[0]), f64::from(d[1]), f64::from(d[2])];
                            count += 1;
                            for r in 0..3 {
                                s1[r] += d[r];
                                for cc in 0..3 {
                                    s2[r][cc] += d[r] * d[cc];
                                }
                            }
                        }
                        (count, s1, s2)
                    }
                };
                if count < options.min_neighbours {
                    continue;
                }
                let Some(mut fit) = fit_plane_weighted(count as f64, &s1, &s2) else {
                    continue;
                };
                if let Some((c_m, _)) = robust_c_m.filter(|&(_, above_m)| fit.rms_m > above_m) {
                    let refit = |start| {
                        robust_refit(
                            candidates,
                            q,
                            radius_sq,
                            start,
                            c_m,
                            options.robust_iterations,
                            options.min_neighbours as f64,
                        )
                    };
                    let seed = options
                        .seeded_refit
                        .then(|| seed_plane(candidates, q, radius_sq, options.min_neighbours))
                        .flatten();
                    fit = seed.and_then(refit).or_else(|| refit(fit)).unwrap_or(fit);
                }
                // The fit's mean is an offset from q.
                let off_plane = (0..3)
                    .map(|a| fit.normal[a] * fit.mean[a])
                    .sum::<f64>()
                    .abs();
                if on_plane_m.is_some_and(|limit| off_plane > limit) {
                    continue;
                }
                let (mut normal, planarity) = (fit.normal, fit.planarity);
                let p = [f64::from(q[0]), f64::from(q[1]), f64::from(q[2])];
                let flip = if up_first && normal[2].abs() >= VERTICAL_COS {
                    normal[2] < 0.0
                } else if up_first {
                    let dx = viewpoint.x - p[0];
                    let dy = viewpoint.y - p[1];
                    if dx * dx + dy * dy > 0.0 {
                        normal[0] * dx + normal[1] * dy < 0.0
                    } else {
                        normal[2] < 0.0
                    }
                } else {
                    let d = [viewpoint.x - p[0], viewpoint.y - p[1], viewpoint.z - p[2]];
                    normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2] < 0.0
                };
                if flip {
                    normal = [-normal[0], -normal[1], -normal[2]];
                }
                *slot = (
                    [normal[0] as f32, normal[1] as f32, normal[2] as f32],
                    planarity,
                );
            }
        },
    );

    let mut report = NormalReport::default();
    let mut normals = cloud.normals.take().unwrap_or_else(|| vec![[0.0; 3]; n]);
    // A kept input normal keeps the input's planarity, or gets 1 (not
    // judged: the mapper's planarity gate must not drop a normal the file
    // gave because the fit here was poor, e.g. too few neighbours).
    let mut planarity = cloud.planarity.take().unwrap_or_else(|| vec![1.0; n]);
    for (slot, &i) in grid.order.iter().enumerate() {
        let i = i as usize;
        let (estimate, score) = results[slot];
        let had = normal_is_set(&normals[i]);
        if had && !options.recompute_all {
            report.kept += 1;
        } else if score >= 0.0 {
            report.estimated += 1;
            normals[i] = estimate;
            planarity[i] = score;
        } else {
            report.failed += 1;
            normals[i] = [0.0; 3];
            planarity[i] = 0.0;
        }
    }
    cloud.normals = Some(normals);
    cloud.planarity = Some(planarity);
    Ok((report, read_noise_m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, SymmetricEigen};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn closed_form_eigen_matches_nalgebra() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for trial in 0..2000 {
            let m = Matrix3::from_fn(|_, _| rng.gen_range(-1.0..1.0));
            // Mix in flat (plane-like) and line-like spectra.
            let d = match trial % 3 {
                0 => Matrix3::from_diagonal(&Vector3::new(1.0, 0.7, 1e-4)),
                1 => Matrix3::from_diagonal(&Vector3::new(1.0, 1e-3, 1e-3 * 0.999)),
                _ => Matrix3::from_diagonal(&Vector3::new(
                    rng.gen_range(0.0..1.0),
                    rng.gen_range(0.0..1.0),
                    rng.gen_range(0.0..1.0),
                )),
            };
            let q = m.qr().q();
            let a = q * d * q.transpose();
            let arr = [
                [a[(0, 0)], a[(0, 1)], a[(0, 2)]],
                [a[(1, 0)], a[(1, 1)], a[(1, 2)]],
                [a[(2, 0)], a[(2, 1)], a[(2, 2)]],
            ];
            let (l, v) = smallest_eigenvector(&arr).unwrap();
            let eig = SymmetricEigen::new(a);
            let mut vals: Vec<f64> = eig.eigenvalues.iter().copied().collect();
            vals.sort_by(|x, y| y.total_cmp(x));
            for k in 0..3 {
                assert!(
                    (l[k] - vals[k]).abs() < 1e-9,
                    "trial {trial}: {l:?} vs {vals:?}"
                );
            }
            let v = Vector3::new(v[0], v[1], v[2]);
            assert!((v.norm() - 1.0).abs() < 1e-12);
            // A v = l3 v (the residual is what matters for near-double roots).
            let residual = (a * v - v * l[2]).norm();
            assert!(residual < 1e-7, "trial {trial}: residual {residual}");
            if trial % 3 == 0 {
                let truth = q.column(2);
                assert!(v.dot(&truth).abs() > 1.0 - 1e-9);
            }
        }
        assert!(
            smallest_eigenvector(&[[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0]]).is_none()
        );
        assert!(smallest_eigenvector(&[[0.0; 3]; 3]).is_none());
    }

    #[test]
    fn cell_grid_groups_points_by_cell_in_key_order() {
        let cloud = PointCloud {
            origin: Vector3::new(0.0, 0.0, 0.0),
            points: vec![
                [0.5, 0.5, 0.5],
                [-0.5, 0.5, 0.5],
                [0.6, 0.4, 0.1],
                [1.5, 0.0, 0.0],
            ],
            normals: None,
            planarity: None,
        };
        let grid = CellGrid::new(&cloud, 1.0).unwrap();
        assert_eq!(grid.keys.len(), 3);
        assert_eq!(grid.cell_points(0), &[1]);
        assert_eq!(grid.cell_points(1), &[0, 2]);
        assert_eq!(grid.cell_points(2), &[3]);
        let k = grid.neighbour_key(grid.keys[1], [1, 0, 0]);
        assert_eq!(grid.find(k), Some(2));
        let k = grid.neighbour_key(grid.keys[1], [-1, 0, 0]);
        assert_eq!(grid.find(k), Some(0));
        assert_eq!(grid.find(grid.neighbour_key(grid.keys[1], [0, 1, 0])), None);
    }
}
