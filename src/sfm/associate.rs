//! LiDAR point-to-plane associations for bundle adjustment (method.md 4.6).
//!
//! Before every solve the mapper asks a [`PlaneAssociator`] for planes of the
//! solve's variable 3D points; each plane becomes a residual
//! `w * (n . X - n . l)`. Three associators exist: [`NoAssociation`] (plain
//! SfM, option `--no-lidar-constraints`), [`NearestNeighbourAssociator`]
//! (nearest map point within a radius that shrinks as the point takes part in
//! global BAs; the smallest radius in the final rounds after the first) and
//! [`ProjectionAssociator`] (short tracks: the map point seen at the point's
//! features; longer ones: nearest). A plane is a map point's
//! normal with the offset of the map's surface around it
//! ([`NearestNeighbourAssociator::plane_offset_at`]).
use nalgebra::Vector3;
use rayon::prelude::*;

use super::options::AssociationOptions;
use super::state::MapState;
use crate::map::grid::FrustumGrid;
use crate::map::index::MapIndex;
use crate::map::projection::{project_map_at_pixels, ProjectionOptions};
use crate::map::surfels::{FittedPlane, SurfelMap, SurfelOptions};
use crate::map::PointCloud;
use crate::scene::{ImageId, Point3DId};
use crate::solver::{LossFunction, PlaneConstraint, PlaneFamily};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::OnceLock;

/// Which solve the planes are for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SolveKind {
    /// Local BA, first pass (robust plane losses).
    Local,
    /// Local BA, later passes (plain least squares on the planes).
    LocalRefine,
    Global,
    /// The first round of the final bundle adjustment: the final weights
    /// with a Huber loss (`final_first_round_huber_m`).
    FinalFirst,
    /// A later round of the final bundle adjustment while the model still
    /// moves by centimetres (`bundle.final_huber_above_move_m`): the final
    /// weights and radius with a Huber loss at `final_loss_scale_m`.
    FinalMoving,
    Final,
}

impl SolveKind {
    /// A round of the final bundle adjustment (the first or a later one).
    pub fn is_final(self) -> bool {
        matches!(self, Self::FinalFirst | Self::FinalMoving | Self::Final)
    }
}

/// A variable 3D point of a solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AssociationQuery {
    /// Index of the point in the solve's problem.
    pub point_idx: u32,
    pub point_id: Point3DId,
    pub position_in_world: Vector3<f64>,
    /// Global BAs the point took part in.
    pub num_global_ba: u32,
    pub track_len: usize,
}

/// Computes the planes of one solve.
pub trait PlaneAssociator {
    fn name(&self) -> &'static str;
    /// Planes for some of `queries` (at most one per point), in query order.
    /// `state` gives the tracks and the current poses.
    fn associate(
        &self,
        kind: SolveKind,
        state: &MapState,
        queries: &[AssociationQuery],
    ) -> Vec<PlaneConstraint>;
    /// Robust loss per plane family this associator produces in a solve of `kind`.
    fn losses(&self, _kind: SolveKind) -> Vec<(PlaneFamily, LossFunction)> {
        Vec::new()
    }
}

/// No LiDAR terms.
pub struct NoAssociation;

impl PlaneAssociator for NoAssociation {
    fn name(&self) -> &'static str {
        "none"
    }

    fn associate(
        &self,
        _: SolveKind,
        _: &MapState,
        _: &[AssociationQuery],
    ) -> Vec<PlaneConstraint> {
        Vec::new()
    }
}

/// Among the `num_neighbours` nearest map points within
/// `r = max(max_radius - k * radius_drop, min_radius)` (k = global BAs the
/// point took part in), the one whose tangent plane lies closest to the point
/// gives the plane: its normal, and the offset of the map's surface there
/// ([`Self::plane_offset_at`]); kept when the point lies within
/// `max_plane_distance_m` of that plane. Ground planes (normal near vertical)
/// get `ground_weight`.
pub struct NearestNeighbourAssociator<'a> {
    pub cloud: &'a PointCloud,
    pub index: &'a MapIndex,
    pub options: AssociationOptions,
    /// [`Self::plane_offset_at`] per map point, once computed: the f32 bits
    /// of the offset minus the point's own `n . l`; [`NOT_YET`] before,
    /// [`NO_PLANE`] for a point without enough support.
    offsets: Vec<AtomicU32>,
    /// The map's surfels and each surfel's wide plane, once computed
    /// ([`Self::wide_offset`]); `None` when the option is off. Built in
    /// [`Self::new`], outside the parallel loops that ask for offsets: a
    /// lazy build there (itself parallel) could run a piece of such a loop
    /// on its own thread while it builds, which would wait for itself.
    wide: Option<Wide>,
}

/// [`NearestNeighbourAssociator`]'s wide plane fits.
struct Wide {
    surfels: SurfelMap,
    /// The patch radii tried in turn.
    radii: Vec<f64>,
    /// Per surfel, its fitted plane once computed (boxed: most surfels of
    /// a large map are never asked for one).
    fits: Vec<OnceLock<Option<Box<FittedPlane>>>>,
}

/// The map's noise a wide fit assumes at least (metres): on a map without
/// noise its planes still grow while they agree within this.
const WIDE_MIN_NOISE_M: f64 = 0.001;

/// A wider patch is refused when its points' RMS distance to its plane is
/// more than this many times the map's noise (a bend or a step inside it).
const WIDE_MAX_SPREAD: f64 = 1.5;

/// Map points a wide fit needs at least.
const WIDE_MIN_COUNT: u32 = 20;

/// Patch radii a wide fit tries at most (doublings of twice the plane
/// radius; the last one is the option's).
const MAX_WIDE_STEPS: usize = 12;

/// The standard deviation of a normal distribution cut at 3 sigma, in
/// sigmas: `sqrt(1 - 6 phi(3) / (2 Phi(3) - 1))`.
const CLIPPED_SIGMA: f64 = 0.986_58;

/// The median of `values` (the upper one of an even count), which it sorts;
/// `values` must not be empty.
pub(crate) fn median_in_place(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Marks an offset not computed yet (a NaN no arithmetic produces).
const NOT_YET: u32 = u32::MAX;
/// Marks a map point that gives no plane (another such NaN).
const NO_PLANE: u32 = u32::MAX - 1;

impl<'a> NearestNeighbourAssociator<'a> {
    pub fn new(cloud: &'a PointCloud, index: &'a MapIndex, options: AssociationOptions) -> Self {
        let mut assoc = Self {
            cloud,
            index,
            options,
            offsets: (0..cloud.len()).map(|_| AtomicU32::new(NOT_YET)).collect(),
            wide: None,
        };
        assoc.wide = assoc.build_wide();
        assoc
    }
}

impl NearestNeighbourAssociator<'_> {
    pub fn radius_m(&self, num_global_ba: u32) -> f64 {
        let o = &self.options;
        (o.max_radius_m - f64::from(num_global_ba) * o.radius_drop_m).max(o.min_radius_m)
    }

    /// The search radius of a point in a solve of `kind`: shrinking with the
    /// global BAs the point took part in ([`Self::radius_m`]), except in the
    /// final rounds after the first ([`SolveKind::Final`],
    /// [`SolveKind::FinalMoving`]), where every point
    /// gets the smallest radius. The first final round still pulls in the
    /// younger points (those of the last images, of the re-triangulation,
    /// placed at a known pose) from afar, e.g. when the whole-model alignment
    /// was not applied; a radius still shrinking in the later rounds changed
    /// the objective from one round to the next, and the rounds' stop rule
    /// then took a dip in the camera moves for convergence. Seed-0 corridor,
    /// perturbed initial pose, the map shifted by 20 um or offset by
    /// 500000,4400000,200: 4.1-4.3 mm after 3 rounds against 3.0 mm for the
    /// unshifted map after 6 rounds; now 2.9 / 3.0 mm (shifted / offset)
    /// and 2.8 mm unshifted, after 3-4 rounds.
    pub fn radius_for(&self, kind: SolveKind, num_global_ba: u32) -> f64 {
        if matches!(kind, SolveKind::Final | SolveKind::FinalMoving) {
            self.options.min_radius_m
        } else {
            self.radius_m(num_global_ba)
        }
    }
}

impl PlaneAssociator for NearestNeighbourAssociator<'_> {
    fn name(&self) -> &'static str {
        "nearest"
    }

    /// Huber (or the final solves' `final_loss`) with the scale `loss_scale_m`
    /// (metres) times the family's weight.
    fn losses(&self, kind: SolveKind) -> Vec<(PlaneFamily, LossFunction)> {
        if kind == SolveKind::LocalRefine {
            return vec![
                (PlaneFamily::Nearest, LossFunction::Trivial),
                (PlaneFamily::Ground, LossFunction::Trivial),
            ];
        }
        let w = self.options.weights(kind);
        vec![
            (PlaneFamily::Nearest, w.loss(w.weight)),
            (PlaneFamily::Ground, w.loss(w.ground_weight)),
        ]
    }

    fn associate(
        &self,
        kind: SolveKind,
        state: &MapState,
        queries: &[AssociationQuery],
    ) -> Vec<PlaneConstraint> {
        let planes = self.associate_points(kind, queries);
        self.keep_consistent(kind, state, queries, planes)
    }
}

impl NearestNeighbourAssociator<'_> {
    /// In a final solve, the planes whose points can lie on them (see
    /// [`on_plane_error_px`] and `final_max_on_plane_error_px`); other solves
    /// keep all.
    pub fn keep_consistent(
        &self,
        kind: SolveKind,
        state: &MapState,
        queries: &[AssociationQuery],
        planes: Vec<PlaneConstraint>,
    ) -> Vec<PlaneConstraint> {
        let max_px = self.options.final_max_on_plane_error_px;
        if !kind.is_final() || max_px <= 0.0 {
            return planes;
        }
        let ids: BTreeMap<u32, Point3DId> =
            queries.iter().map(|q| (q.point_idx, q.point_id)).collect();
        planes
            .into_par_iter()
            .filter(|p| {
                ids.get(&p.point_idx).is_some_and(|&id| {
                    let normal = Vector3::from(p.normal);
                    on_plane_error_px(state, id, &normal, p.offset_m).is_some_and(|e| e <= max_px)
                })
            })
            .collect()
    }

    /// Offset `d` of the map's plane `n . X = d` through map point `i` (`n`
    /// its normal), estimated from the map around it: the mean of `n . l`
    /// over the map points `l` with (about) the same normal inside a
    /// cylinder along `n` of radius `plane_radius_m`, reaching
    /// `plane_window_m` either side of the plane (the window re-centred on
    /// the mean, three passes). `None` when the point has no normal, or
    /// when fewer than `min_plane_support` map points (itself included)
    /// are in that window: a stray point, not a surface (see
    /// [`AssociationOptions::min_plane_support`]).
    ///
    /// This averages the map's range noise without favouring either side:
    /// the neighbours are chosen by where they lie along the surface, not by
    /// their distance to a point that may sit off it. The nearest map points
    /// to a point off the surface are those whose noise moved them toward
    /// it (their mean follows the point, weakening its residual), and the
    /// map point a camera sees at a pixel is the nearest of the splats there
    /// (moved toward the camera by about the noise's sigma): offsets
    /// averaged over nearest neighbours carried both biases (on a floor
    /// with the synthetic maps' 15 mm noise: 11 mm at the points a camera
    /// sees, see the test), and the mapper's models came out a little too
    /// large inside rooms and corridors. With `plane_fit_max_radius_m` on,
    /// a wide plane fitted around the point replaces that mean where it is
    /// known better and agrees with it ([`Self::wide_offset`]). Cached per
    /// map point.
    pub fn plane_offset_at(&self, i: usize) -> Option<f64> {
        let normal = self.normal_of(i)?;
        let point = self.cloud.point_in_map(i);
        let own = normal.dot(&point);
        match self.offsets[i].load(Ordering::Relaxed) {
            NOT_YET => {}
            NO_PLANE => return None,
            cached => return Some(own + f64::from(f32::from_bits(cached))),
        }
        let Some((local, support)) = self.surface_offset(&point, &normal) else {
            self.offsets[i].store(NO_PLANE, Ordering::Relaxed);
            return None;
        };
        let offset = self
            .wide_offset(i, &point, &normal, local, support)
            .unwrap_or(local);
        // Stored relative to the point's own offset: centimetres, exact
        // enough in f32 at any map coordinates.
        let delta = (offset - own) as f32;
        let bits = if matches!(delta.to_bits(), NOT_YET | NO_PLANE) {
            f32::NAN.to_bits()
        } else {
            delta.to_bits()
        };
        self.offsets[i].store(bits, Ordering::Relaxed);
        Some(own + f64::from(delta))
    }

    /// The offset of the wide plane fitted around map point `i` (at
    /// `point`, normal `normal`) where it crosses the normal through the
    /// point, when `plane_fit_max_radius_m` allows a patch of at least twice
    /// the plane radius, one was fitted ([`SurfelMap::fit_around`]), it is
    /// known better there than `local` (the mean of `support` map points
    /// within the plane radius), and the two agree within 3 sigma of the
    /// map's noise (their variances summed: loose, as the patch holds the
    /// local points too).
    fn wide_offset(
        &self,
        i: usize,
        point: &Vector3<f64>,
        normal: &Vector3<f64>,
        local: f64,
        support: usize,
    ) -> Option<f64> {
        let wide = self.wide.as_ref()?;
        let s = wide.surfels.surfel_of(i)?;
        // `fit_around` runs on this thread only (no rayon inside), so a
        // surfel's fit may be computed here from inside a parallel loop.
        let fit = wide.fits[s as usize]
            .get_or_init(|| {
                wide.surfels
                    .fit_around(
                        s,
                        &wide.radii,
                        WIDE_MIN_NOISE_M,
                        WIDE_MAX_SPREAD,
                        WIDE_MIN_COUNT,
                    )
                    .map(Box::new)
            })
            .as_ref()?;
        let (offset, var) = fit.offset_along(point, normal)?;
        // Only a plane known better than the local mean here (a patch far
        // from the point extrapolates), and only where the two agree.
        let local_var = 1.0 / support.max(1) as f64;
        if var >= local_var {
            return None;
        }
        let noise = wide.surfels.noise_m().max(WIDE_MIN_NOISE_M);
        let sigma = noise * (local_var + var).sqrt();
        ((offset - local).abs() <= 3.0 * sigma).then_some(offset)
    }

    /// The surfels and the radii of the wide fits; `None` when they are
    /// off (`plane_fit_max_radius_m` under twice the plane radius).
    fn build_wide(&self) -> Option<Wide> {
        let (r, max) = (
            self.options.plane_radius_m,
            self.options.plane_fit_max_radius_m,
        );
        // Not for options that were never validated either: a radius of
        // zero or less would never reach `max`.
        if !(r > 0.0 && max.is_finite() && max >= 2.0 * r) {
            return None;
        }
        let mut radii = Vec::new();
        let mut radius = 2.0 * r;
        while radius < max && radii.len() < MAX_WIDE_STEPS {
            radii.push(radius);
            radius *= 2.0;
        }
        radii.push(max);
        let surfels = SurfelMap::build(
            self.cloud,
            |i| self.normal_of(i).filter(|_| self.is_planar(i)),
            SurfelOptions {
                // Cells of at least 2 cm: a tiny plane radius would make
                // every point a surfel.
                cell_m: r.max(0.02),
                cos_same: self.options.same_plane_max_angle_deg.to_radians().cos(),
                window_m: self.options.plane_window_m,
            },
            0.5 * max,
        );
        let fits = (0..surfels.len()).map(|_| OnceLock::new()).collect();
        Some(Wide {
            surfels,
            radii,
            fits,
        })
    }

    /// The cylinder mean of [`Self::plane_offset_at`] around `at` (a map
    /// point) for the plane normal `normal`, and the number of map points
    /// it averages; `None` when fewer than `min_plane_support` map points
    /// are in the final window.
    fn surface_offset(&self, at: &Vector3<f64>, normal: &Vector3<f64>) -> Option<(f64, usize)> {
        let (r, g) = (self.options.plane_radius_m, self.options.plane_window_m);
        let candidates = self.same_plane_offsets(at, normal, r);
        let mut d = normal.dot(at);
        let mut support = 0;
        for _ in 0..3 {
            let (sum, count) = candidates
                .iter()
                .filter(|&&o| (o - d).abs() <= g)
                .fold((0.0, 0usize), |(s, c), o| (s + o, c + 1));
            support = count;
            if count == 0 {
                break;
            }
            d = sum / count as f64;
        }
        let min = self.options.min_plane_support;
        // Too few: a stray point, or a surface sparser here than the map's
        // spacing, which twice the radius tells apart (the offset stays the
        // mean over the radius).
        let supported = support >= min
            || self
                .same_plane_offsets(at, normal, 2.0 * r)
                .iter()
                .filter(|&&o| (o - d).abs() <= g)
                .count()
                >= min;
        supported.then_some((d, support))
    }

    /// `n . l` of the map points `l` whose normals are within
    /// `same_plane_max_angle_deg` of `normal` and that lie within `radius`
    /// of `at` across the normal and within `plane_window_m` along it.
    fn same_plane_offsets(
        &self,
        at: &Vector3<f64>,
        normal: &Vector3<f64>,
        radius: f64,
    ) -> Vec<f64> {
        self.same_plane_offsets_within(at, normal, radius, self.options.plane_window_m)
    }

    /// [`Self::same_plane_offsets`] within `g` along the normal.
    fn same_plane_offsets_within(
        &self,
        at: &Vector3<f64>,
        normal: &Vector3<f64>,
        radius: f64,
        g: f64,
    ) -> Vec<f64> {
        let cos_same = self.options.same_plane_max_angle_deg.to_radians().cos();
        self.index
            .within_radius(at, (radius * radius + g * g).sqrt())
            .iter()
            .filter_map(|nb| {
                let i = nb.point_idx as usize;
                self.normal_of(i).filter(|m| m.dot(normal) >= cos_same)?;
                let l = self.cloud.point_in_map(i);
                let v = l - at;
                let along = normal.dot(&v);
                ((v - normal * along).norm_squared() <= radius * radius).then(|| normal.dot(&l))
            })
            .collect()
    }

    /// The map's range noise as its planes see it, metres: over a sample of
    /// up to `max_samples` map points that may give a plane (every k-th in
    /// index order), the spread of the offsets `n . l` of the map points on
    /// the same plane within `plane_radius_m` ([`Self::same_plane_offsets`],
    /// `window_m` either side), 1.4826 times their median absolute deviation
    /// (robust to a parallel surface in the window), then twice the
    /// standard deviation of those within 3 sigma (corrected for the cut);
    /// the median over the sample. Patches with fewer than 8 points are
    /// skipped; `None` when none is left. On the synthetic rooms and
    /// corridors with 30 and 50 mm of noise along the normals it read
    /// 29.5-29.8 and 49.2-49.7 mm with the true normals, 30.8 and 51.3-52.1
    /// mm from `prepare-map` (3 cm voxels, estimated normals); the seed-0
    /// room and yard at 15 mm 14.8 and 14.3 mm.
    pub fn plane_noise_m(&self, max_samples: usize, window_m: f64) -> Option<f64> {
        let n = self.cloud.len();
        let stride = n.div_ceil(max_samples.max(1)).max(1);
        let mut spreads: Vec<f64> = (0..n)
            .step_by(stride)
            .collect::<Vec<usize>>()
            .par_iter()
            .filter_map(|&i| {
                let normal = self.normal_of(i).filter(|_| self.is_planar(i))?;
                let at = self.cloud.point_in_map(i);
                let mut offsets = self.same_plane_offsets_within(
                    &at,
                    &normal,
                    self.options.plane_radius_m,
                    window_m,
                );
                if offsets.len() < 8 {
                    return None;
                }
                let mut centre = median_in_place(&mut offsets);
                let mut deviations: Vec<f64> = offsets.iter().map(|o| (o - centre).abs()).collect();
                let mut sigma = 1.4826 * median_in_place(&mut deviations);
                // The MAD reads high when another surface holds a good share
                // of the window (1.6 times with a quarter 8 sigma away):
                // two passes of the standard deviation within 3 sigma.
                for _ in 0..2 {
                    let (mut n, mut sum, mut sum_sq) = (0usize, 0.0, 0.0);
                    for o in offsets
                        .iter()
                        .filter(|o| (*o - centre).abs() <= 3.0 * sigma)
                    {
                        n += 1;
                        sum += o - centre;
                        sum_sq += (o - centre) * (o - centre);
                    }
                    if n < 8 {
                        return None;
                    }
                    let mean = sum / n as f64;
                    centre += mean;
                    sigma = (sum_sq / n as f64 - mean * mean).max(0.0).sqrt() / CLIPPED_SIGMA;
                }
                Some(sigma)
            })
            .collect();
        (!spreads.is_empty()).then(|| median_in_place(&mut spreads))
    }

    /// Whether map point `i` may give a plane: its planarity reaches
    /// `min_planarity` (always when the map has no planarity).
    pub fn is_planar(&self, i: usize) -> bool {
        let min = self.options.min_planarity as f32;
        min <= 0.0 || self.cloud.planarity.as_ref().is_none_or(|p| p[i] >= min)
    }

    /// Unit normal of map point `i`; `None` when the map has no normals or
    /// this one is zero or not finite.
    pub fn normal_of(&self, i: usize) -> Option<Vector3<f64>> {
        let m = self.cloud.normals.as_ref()?[i];
        Vector3::new(f64::from(m[0]), f64::from(m[1]), f64::from(m[2]))
            .try_normalize(1e-9)
            .filter(|n| n.iter().all(|c| c.is_finite()))
    }

    /// The map's plane near `x` (world frame): among the `num_neighbours`
    /// nearest map points within `radius_m` ([`Self::is_planar`] ones that
    /// give a plane), the one whose tangent plane lies closest to `x` (at a
    /// corner the nearest point may belong to the other surface) gives the
    /// plane: its normal and [`Self::plane_offset_at`]. `None` without such
    /// a neighbour.
    pub fn plane_near(&self, x: &Vector3<f64>, radius_m: f64) -> Option<(Vector3<f64>, f64)> {
        let neighbours = self
            .index
            .k_nearest_within(x, self.options.num_neighbours, radius_m);
        let mut candidates: Vec<(f64, usize, Vector3<f64>)> = neighbours
            .iter()
            .filter_map(|nb| {
                let i = nb.point_idx as usize;
                let n = self.normal_of(i).filter(|_| self.is_planar(i))?;
                Some((n.dot(&(x - self.cloud.point_in_map(i))).abs(), i, n))
            })
            .collect();
        // Stable: ties keep the neighbours' (distance) order.
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0));
        candidates
            .into_iter()
            .find_map(|(_, i, normal)| Some((normal, self.plane_offset_at(i)?)))
    }

    /// The nearest-neighbour planes of `queries` (needs no tracks or poses).
    pub fn associate_points(
        &self,
        kind: SolveKind,
        queries: &[AssociationQuery],
    ) -> Vec<PlaneConstraint> {
        let weights = self.options.weights(kind);
        let cos_ground = self.options.ground_max_tilt_deg.to_radians().cos();
        // In parallel, in the queries' order (the result does not depend on
        // the number of threads: each query's plane is its own, and the
        // cached plane offsets are the same whichever thread computes them).
        queries
            .par_iter()
            .filter_map(|q| {
                let x = q.position_in_world;
                let (normal, offset_m) =
                    self.plane_near(&x, self.radius_for(kind, q.num_global_ba))?;
                if (normal.dot(&x) - offset_m).abs() > self.options.max_plane_distance_m {
                    return None;
                }
                let ground = normal.z.abs() >= cos_ground;
                Some(PlaneConstraint {
                    point_idx: q.point_idx,
                    normal: [normal.x, normal.y, normal.z],
                    offset_m,
                    weight: if ground {
                        weights.ground_weight
                    } else {
                        weights.weight
                    },
                    family: if ground {
                        PlaneFamily::Ground
                    } else {
                        PlaneFamily::Nearest
                    },
                })
            })
            .collect()
    }
}

/// The smallest RMS reprojection error (pixels, over the point's registered
/// observations) of `point` moved onto the plane `normal . X = offset_m`
/// (any non-zero `normal`):
/// Gauss-Newton over the plane's two coordinates from the point's orthogonal
/// projection onto it (central-difference Jacobian; the problem is nearly
/// linear at these scales, a few steps converge). `None` when the point is
/// unknown, has fewer than two registered observations, or falls behind a
/// camera.
pub fn on_plane_error_px(
    state: &MapState,
    point: Point3DId,
    normal: &Vector3<f64>,
    offset_m: f64,
) -> Option<f64> {
    let p = state.points.get(&point)?;
    let mut views = Vec::with_capacity(p.track.len());
    for e in &p.track {
        if let Some(pose) = state.pose(e.image_id) {
            views.push((state.camera_of(e.image_id), pose, state.keypoint(*e)));
        }
    }
    if views.len() < 2 {
        return None;
    }
    let length = normal.norm();
    let normal = normal.try_normalize(1e-12)?;
    let offset_m = offset_m / length;
    // Orthonormal basis (u, v) of the plane.
    let helper = if normal.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = normal.cross(&helper).normalize();
    let v = normal.cross(&u);
    let origin = p.xyz - (normal.dot(&p.xyz) - offset_m) * normal;
    let residuals = |a: f64, b: f64| -> Option<Vec<f64>> {
        let x = origin + a * u + b * v;
        let mut r = Vec::with_capacity(2 * views.len());
        for (camera, pose, pixel) in &views {
            let in_cam = pose.transform_point(&x);
            if in_cam.z <= 1e-9 {
                return None;
            }
            let q = camera.project(&in_cam)? - pixel;
            r.extend([q.x, q.y]);
        }
        Some(r)
    };
    // Step of the numerical derivative: 1e-6 of the distance to a camera.
    let h = ((views[0].1.camera_center() - origin).norm() * 1e-6).max(1e-9);
    let norm_sq = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
    let (mut a, mut b) = (0.0, 0.0);
    let mut r = residuals(a, b)?;
    for _ in 0..5 {
        let (ra_p, ra_m) = (residuals(a + h, b)?, residuals(a - h, b)?);
        let (rb_p, rb_m) = (residuals(a, b + h)?, residuals(a, b - h)?);
        let (mut jtj, mut jtr) = (
            nalgebra::Matrix2::<f64>::zeros(),
            nalgebra::Vector2::zeros(),
        );
        for i in 0..r.len() {
            let j = nalgebra::Vector2::new(
                (ra_p[i] - ra_m[i]) / (2.0 * h),
                (rb_p[i] - rb_m[i]) / (2.0 * h),
            );
            jtj += j * j.transpose();
            jtr += j * r[i];
        }
        let Some(step) = jtj.try_inverse().map(|inv| -(inv * jtr)) else {
            break;
        };
        let next = residuals(a + step.x, b + step.y)?;
        if norm_sq(&next) >= norm_sq(&r) {
            break;
        }
        (a, b, r) = (a + step.x, b + step.y, next);
        if step.norm() < 1e-9 {
            break;
        }
    }
    Some((norm_sq(&r) / views.len() as f64).sqrt())
}

/// Projection associations for short tracks (method.md 4.6): for a point
/// with at most `projection_max_track_len` observations, the map is
/// projected into each registered image of its track and the LiDAR point
/// splatted at the point's feature there is a candidate; the candidate whose
/// offset `X - l` is most parallel to its plane (smallest |cos(n, X - l)|)
/// wins, kept when `X` lies within `max_plane_distance_m` of that plane.
/// Longer tracks (and short ones without a hit) use the nearest-neighbour
/// association.
pub struct ProjectionAssociator<'a> {
    pub nearest: &'a NearestNeighbourAssociator<'a>,
    pub grid: &'a FrustumGrid,
    pub projection: ProjectionOptions,
}

impl PlaneAssociator for ProjectionAssociator<'_> {
    fn name(&self) -> &'static str {
        "projection+nearest"
    }

    fn losses(&self, kind: SolveKind) -> Vec<(PlaneFamily, LossFunction)> {
        let mut losses = self.nearest.losses(kind);
        let w = self.nearest.options.weights(kind);
        let loss = if kind == SolveKind::LocalRefine {
            LossFunction::Trivial
        } else {
            w.loss(w.projection_weight)
        };
        losses.push((PlaneFamily::Projection, loss));
        losses
    }

    fn associate(
        &self,
        kind: SolveKind,
        state: &MapState,
        queries: &[AssociationQuery],
    ) -> Vec<PlaneConstraint> {
        let o = &self.nearest.options;
        let weights = o.weights(kind);
        // Feature pixels to look up, grouped by image (one projection each).
        let mut per_image: BTreeMap<ImageId, Vec<(usize, nalgebra::Vector2<f64>)>> =
            BTreeMap::new();
        for (qi, q) in queries.iter().enumerate() {
            if q.track_len > o.projection_max_track_len {
                continue;
            }
            let Some(point) = state.points.get(&q.point_id) else {
                continue;
            };
            for e in &point.track {
                if state.pose(e.image_id).is_some() {
                    per_image
                        .entry(e.image_id)
                        .or_default()
                        .push((qi, state.keypoint(*e)));
                }
            }
        }
        // Best candidate per query: (|cos|, normal, offset).
        let mut best: Vec<Option<(f64, Vector3<f64>, f64)>> = vec![None; queries.len()];
        for (image, pixels) in &per_image {
            let pose = state.pose(*image).expect("registered, checked above");
            let query_px: Vec<nalgebra::Vector2<f64>> = pixels.iter().map(|(_, p)| *p).collect();
            let Ok(hits) = project_map_at_pixels(
                self.nearest.cloud,
                self.grid,
                state.camera_of(*image),
                &pose,
                &query_px,
                &self.projection,
            ) else {
                continue;
            };
            for ((qi, _), hit) in pixels.iter().zip(hits) {
                let Some(hit) = hit.filter(|h| self.nearest.is_planar(h.point_idx as usize)) else {
                    continue;
                };
                let Some(n) = hit.normal_in_map.and_then(|n| n.try_normalize(1e-9)) else {
                    continue;
                };
                let x = queries[*qi].position_in_world;
                let offset = x - hit.point_in_map;
                let cos = offset.try_normalize(1e-12).map_or(0.0, |d| n.dot(&d).abs());
                if best[*qi].as_ref().is_none_or(|(c, _, _)| cos < *c) {
                    if let Some(offset) = self.nearest.plane_offset_at(hit.point_idx as usize) {
                        best[*qi] = Some((cos, n, offset));
                    }
                }
            }
        }
        let mut planes = Vec::new();
        let mut rest = Vec::new();
        for (q, b) in queries.iter().zip(best) {
            match b {
                Some((_, n, offset_m))
                    if (n.dot(&q.position_in_world) - offset_m).abs() <= o.max_plane_distance_m =>
                {
                    planes.push(PlaneConstraint {
                        point_idx: q.point_idx,
                        normal: [n.x, n.y, n.z],
                        offset_m,
                        weight: weights.projection_weight,
                        family: PlaneFamily::Projection,
                    });
                }
                _ => rest.push(*q),
            }
        }
        planes.extend(self.nearest.associate_points(kind, &rest));
        planes.sort_by_key(|p| p.point_idx);
        self.nearest.keep_consistent(kind, state, queries, planes)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::io::database::{DatabaseSnapshot, DbImage};
    use crate::scene::{Camera, CameraId, CameraModel, Rigid3, TrackElement};

    /// Two cameras 3 m above the floor z = 0, 0.5 m apart, looking straight
    /// down (SIMPLE_PINHOLE, f = 500), both seeing X = (0.1, 0.2, 0) exactly;
    /// the state's point sits 1 cm off the floor.
    pub(crate) fn two_view_state() -> (MapState, Point3DId) {
        let x = Vector3::new(0.1, 0.2, 0.0);
        two_view_state_seeing(&x, &(x + Vector3::new(0.0, 0.0, 0.01)))
    }

    /// The cameras of [`two_view_state`] seeing `x` exactly; the state's
    /// point is at `point`.
    /// Adds image `id` ("{id}.png", camera 1) with `keypoints` to `db`.
    pub(crate) fn add_test_image(
        db: &mut DatabaseSnapshot,
        id: ImageId,
        keypoints: Vec<nalgebra::Vector2<f64>>,
    ) {
        db.images.insert(
            id,
            DbImage {
                id,
                name: format!("{}.png", id.0),
                camera_id: CameraId(1),
            },
        );
        db.keypoints.insert(id, keypoints);
    }

    /// A 640 x 480 pinhole camera, focal length 500 px, id 1.
    pub(crate) fn test_camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::from_name("SIMPLE_PINHOLE").expect("known model"),
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0],
        }
    }

    pub(crate) fn two_view_state_seeing(
        x: &Vector3<f64>,
        point: &Vector3<f64>,
    ) -> (MapState, Point3DId) {
        let camera = test_camera();
        let down = nalgebra::Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(CameraId(1), camera.clone());
        let mut poses = Vec::new();
        for (i, cx) in [0.0, 0.5].into_iter().enumerate() {
            let id = ImageId(i as u32 + 1);
            let pose = Rigid3::from_rotation_matrix(&down, -(down * Vector3::new(cx, 0.0, 3.0)));
            let pixel = camera.project(&pose.transform_point(x)).expect("in front");
            add_test_image(&mut db, id, vec![pixel]);
            poses.push((id, pose));
        }
        let mut state = MapState::new(&db, 1);
        let mut track = Vec::new();
        for (id, pose) in poses {
            state.register(id, pose);
            track.push(TrackElement {
                image_id: id,
                point2d_idx: 0,
            });
        }
        let point = state.add_point(*point, track);
        (state, point)
    }

    /// The floor z = 0 under [`two_view_state`]'s cameras (2 cm grid,
    /// normals up), every point with planarity `planarity`.
    fn floor_with_planarity(planarity: f32) -> PointCloud {
        let mut points = Vec::new();
        for i in -100..=100 {
            for j in -100..=100 {
                points.push([i as f32 * 0.02, j as f32 * 0.02, 0.0]);
            }
        }
        let n = points.len();
        PointCloud {
            origin: Vector3::zeros(),
            points,
            normals: Some(vec![[0.0, 0.0, 1.0]; n]),
            planarity: Some(vec![planarity; n]),
        }
    }

    /// `plane_noise_m` reads the noise along the normals: a 4 x 4 m floor
    /// at 2 cm spacing with Gaussian noise of 0, 15 and 50 mm, and a
    /// parallel surface 25 cm above a quarter of it (a shelf inside the
    /// 0.3 m window: the patches there read higher, the median over the
    /// sample does not).
    #[test]
    fn plane_noise_reads_the_noise_along_the_normals() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        for sigma in [0.0, 0.015, 0.05] {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
            let noise = Normal::new(0.0, sigma).unwrap();
            let mut points = Vec::new();
            for i in -100..=100 {
                for j in -100..=100 {
                    let (x, y) = (i as f32 * 0.02, j as f32 * 0.02);
                    points.push([x, y, noise.sample(&mut rng) as f32]);
                    if i < -50 {
                        points.push([x + 0.01, y, 0.25 + noise.sample(&mut rng) as f32]);
                    }
                }
            }
            let n = points.len();
            let cloud = PointCloud {
                origin: Vector3::new(500_000.0, 4_400_000.0, 200.0),
                points,
                normals: Some(vec![[0.0, 0.0, 1.0]; n]),
                planarity: None,
            };
            let index = MapIndex::build(&cloud).unwrap();
            let assoc =
                NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
            let read = assoc.plane_noise_m(2000, 0.3).unwrap();
            assert!(
                (read - sigma).abs() <= 0.1 * sigma + 1e-4,
                "{read} for {sigma}"
            );
            // The same reading again (deterministic), none without normals.
            assert_eq!(assoc.plane_noise_m(2000, 0.3), Some(read));
        }
        let bare = PointCloud {
            normals: None,
            ..floor_with_planarity(1.0)
        };
        let index = MapIndex::build(&bare).unwrap();
        let assoc = NearestNeighbourAssociator::new(&bare, &index, AssociationOptions::default());
        assert_eq!(assoc.plane_noise_m(2000, 0.3), None);
    }

    /// The wide plane fits (`plane_fit_max_radius_m` 1.2 m): on a 4 x 4 m floor
    /// at 2 cm spacing with 15 mm of noise (georeferenced coordinates), and
    /// a shelf 25 cm above one quarter of it (the same normal, outside the
    /// plane window), the plane offsets of the floor's points are within
    /// about 0.5 mm of the floor instead of 1.8 mm (the mean of about 80
    /// points within the 0.1 m plane radius), and the shelf's stay the
    /// shelf's.
    #[test]
    fn wide_plane_fits_average_a_noisy_floor() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let noise = Normal::new(0.0, 0.015).unwrap();
        let (mut points, mut heights) = (Vec::new(), Vec::new());
        for i in -100..=100 {
            for j in -100..=100 {
                let (x, y) = (i as f32 * 0.02, j as f32 * 0.02);
                let h = if i < -50 && j < -50 { 0.25 } else { 0.0 };
                points.push([x, y, h + noise.sample(&mut rng) as f32]);
                heights.push(f64::from(h));
            }
        }
        let n = points.len();
        let origin = Vector3::new(500_000.0, 4_400_000.0, 200.0);
        let cloud = PointCloud {
            origin,
            points,
            normals: Some(vec![[0.0, 0.0, 1.0]; n]),
            planarity: None,
        };
        let index = MapIndex::build(&cloud).unwrap();
        let rms_error = |options: AssociationOptions, shelf: bool| {
            let assoc = NearestNeighbourAssociator::new(&cloud, &index, options);
            // In parallel, as the mapper asks (the surfels are built
            // beforehand; each surfel's fit is computed once, on any thread).
            let errors: Vec<f64> = (0..n)
                .into_par_iter()
                .step_by(37)
                .filter(|&i| (heights[i] > 0.0) == shelf)
                .map(|i| assoc.plane_offset_at(i).unwrap() - origin.z - heights[i])
                .collect();
            (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt()
        };
        let local = AssociationOptions {
            plane_fit_max_radius_m: 0.0,
            ..AssociationOptions::default()
        };
        let wide = AssociationOptions {
            plane_fit_max_radius_m: 1.2,
            ..AssociationOptions::default()
        };
        let (wide_floor, local_floor) = (
            rms_error(wide.clone(), false),
            rms_error(local.clone(), false),
        );
        // Measured: 0.54 mm (most fits 1.2 m wide; the floor's border and
        // the shelf's edge hold half discs) against 1.83 mm.
        assert!(wide_floor < 0.0008, "{wide_floor}");
        assert!(
            local_floor > 0.0015 && local_floor < 0.0022,
            "{local_floor}"
        );
        let (wide_shelf, local_shelf) = (rms_error(wide, true), rms_error(local, true));
        // 0.74 mm against 1.95 mm: the 1 x 1 m shelf, none of the floor.
        assert!(wide_shelf < 0.0011, "{wide_shelf}");
        assert!(
            local_shelf > 0.0015 && local_shelf < 0.0025,
            "{local_shelf}"
        );
    }

    #[test]
    fn projection_planes_respect_the_planarity_gate() {
        let (state, point) = two_view_state();
        let query = AssociationQuery {
            point_idx: 0,
            point_id: point,
            position_in_world: state.points[&point].xyz,
            num_global_ba: 0,
            track_len: 2,
        };
        let planes_with = |planarity: f32| {
            let cloud = floor_with_planarity(planarity);
            let index = MapIndex::build(&cloud).unwrap();
            let grid = FrustumGrid::build(&cloud, &Default::default()).unwrap();
            let nearest =
                NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
            let projection = ProjectionAssociator {
                nearest: &nearest,
                grid: &grid,
                projection: ProjectionOptions::default(),
            };
            projection.associate(SolveKind::Local, &state, &[query])
        };
        // Flat map points: the point 1 cm above the floor gets the floor
        // from the map point seen at its features.
        let planes = planes_with(0.9);
        assert_eq!(planes.len(), 1);
        assert_eq!(planes[0].family, PlaneFamily::Projection);
        assert!(planes[0].offset_m.abs() < 1e-6);
        // Below the gate: neither the projection nor the nearest fallback.
        assert!(planes_with(0.6).is_empty());
    }

    #[test]
    fn on_plane_error_is_the_best_reprojection_on_the_plane() {
        let (state, point) = two_view_state();
        let up = Vector3::z();
        // The floor holds the true point: no error, from 1 cm off.
        let on_floor = on_plane_error_px(&state, point, &up, 0.0).expect("two views");
        assert!(on_floor < 1e-6, "{on_floor}");
        // z = 0.05: the rays cross that plane at x = 0.1 * 2.95 / 3 and
        // 0.5 - 0.4 * 2.95 / 3, 8.33 mm apart at depth 2.95 m; the best point
        // is halfway, each view off by f * 4.167 mm / 2.95 m.
        let expected = 500.0 * (0.5 - 0.5 * 2.95 / 3.0) / 2.0 / 2.95;
        let lifted = on_plane_error_px(&state, point, &up, 0.05).expect("two views");
        assert!((lifted - expected).abs() < 1e-6, "{lifted} vs {expected}");
        // The normal's sign and length do not matter.
        let flipped = on_plane_error_px(&state, point, &(-2.0 * up), -0.1).expect("two views");
        assert!((flipped - expected).abs() < 1e-6, "{flipped}");
        // A plane behind the cameras cannot hold the point.
        assert_eq!(on_plane_error_px(&state, point, &up, 4.0), None);
    }

    #[test]
    fn nearest_association_gates_and_shrinks() {
        // A floor patch z = 0 around the origin, 0.1 m spacing, normals up.
        let mut points = Vec::new();
        for i in -10..=10 {
            for j in -10..=10 {
                points.push([i as f32 * 0.1, j as f32 * 0.1, 0.0]);
            }
        }
        let normals = vec![[0.0f32, 0.0, 1.0]; points.len()];
        let cloud = PointCloud {
            origin: Vector3::new(100.0, 200.0, 10.0),
            points,
            normals: Some(normals),
            planarity: None,
        };
        let index = MapIndex::build(&cloud).unwrap();
        let assoc = NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        assert_eq!(assoc.radius_m(0), 1.5);
        assert!((assoc.radius_m(3) - 0.9).abs() < 1e-12);
        assert_eq!(assoc.radius_m(100), 0.1);
        let q = |idx: u32, x: f64, y: f64, z: f64, k: u32| AssociationQuery {
            point_idx: idx,
            point_id: Point3DId(u64::from(idx)),
            position_in_world: Vector3::new(100.0 + x, 200.0 + y, 10.0 + z),
            num_global_ba: k,
            track_len: 2,
        };
        let planes = assoc.associate_points(
            SolveKind::Local,
            &[
                q(0, 0.03, 0.02, 0.05, 0), // near the floor: kept
                q(1, 0.0, 0.0, 0.5, 0),    // 0.5 m above: beyond the plane gate
                q(2, 1.5, 0.0, 0.1, 10),   // 0.5 m from the patch edge, radius 0.1: none
            ],
        );
        assert_eq!(planes.len(), 1);
        assert_eq!(planes[0].point_idx, 0);
        assert_eq!(planes[0].family, PlaneFamily::Ground);
        assert!((planes[0].offset_m - 10.0).abs() < 1e-6);
        // 0.3 m beyond the patch edge, in no global BA yet: radius 1.5 m in
        // the periodic solves and the first final round, the smallest (0.1 m)
        // in the later final rounds.
        let young = [q(3, 1.3, 0.0, 0.01, 0)];
        for kind in [SolveKind::Global, SolveKind::FinalFirst] {
            assert_eq!(assoc.radius_for(kind, 0), 1.5);
            assert_eq!(assoc.associate_points(kind, &young).len(), 1);
        }
        for kind in [SolveKind::FinalMoving, SolveKind::Final] {
            assert_eq!(assoc.radius_for(kind, 0), 0.1);
            assert!(assoc.associate_points(kind, &young).is_empty());
        }

        // A map with a planarity per point: the points below
        // `min_planarity` (0.7) give no plane, here all but one column.
        let mut scored = cloud.clone();
        scored.planarity = Some(
            scored
                .points
                .iter()
                .map(|p| if p[0] == 0.5 { 0.9 } else { 0.6 })
                .collect(),
        );
        let scored_index = MapIndex::build(&scored).unwrap();
        let gated =
            NearestNeighbourAssociator::new(&scored, &scored_index, AssociationOptions::default());
        let near = |x: f64| [q(0, x, 0.02, 0.01, 10)];
        assert!(gated
            .associate_points(SolveKind::Local, &near(0.0))
            .is_empty());
        assert_eq!(
            gated.associate_points(SolveKind::Local, &near(0.47)).len(),
            1
        );
        let open = NearestNeighbourAssociator::new(
            &scored,
            &scored_index,
            AssociationOptions {
                min_planarity: 0.0,
                ..AssociationOptions::default()
            },
        );
        assert_eq!(open.associate_points(SolveKind::Local, &near(0.0)).len(), 1);
    }
}

#[cfg(test)]
pub(crate) mod plane_offset_tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    /// A 3 m x 3 m floor at z = 0 sampled every 2 cm, 15 mm of gaussian
    /// noise along z (the synthetic maps' noise), normals up; and each
    /// point's noise.
    pub(crate) fn noisy_floor() -> (PointCloud, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.015).unwrap();
        let mut points = Vec::new();
        let mut z = Vec::new();
        for i in -75i32..=75 {
            for j in -75i32..=75 {
                let e: f64 = noise.sample(&mut rng);
                points.push([i as f32 * 0.02, j as f32 * 0.02, e as f32]);
                z.push(f64::from(e as f32));
            }
        }
        let normals = Some(vec![[0.0f32, 0.0, 1.0]; points.len()]);
        let cloud = PointCloud {
            origin: Vector3::new(500_000.0, 4_400_000.0, 200.0),
            points,
            normals,
            planarity: None,
        };
        (cloud, z)
    }

    #[test]
    fn plane_offsets_do_not_follow_the_noise_or_the_query() {
        let (cloud, z) = noisy_floor();
        let index = MapIndex::build(&cloud).unwrap();
        let assoc = NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let inner = |i: usize| {
            let p = cloud.points[i];
            p[0].abs() < 1.2 && p[1].abs() < 1.2
        };
        // What a camera sees: the map points raised most by the noise (the
        // nearest splat at a pixel). Their own offsets average about +30 mm;
        // the plane through each must still be the floor.
        let mut raised: Vec<usize> = (0..z.len()).filter(|&i| inner(i) && z[i] > 0.025).collect();
        raised.truncate(400);
        assert!(raised.len() == 400);
        let own = raised.iter().map(|&i| z[i]).sum::<f64>() / 400.0;
        let planes = raised
            .iter()
            .map(|&i| assoc.plane_offset_at(i).unwrap() - 200.0);
        let mean = planes.clone().sum::<f64>() / 400.0;
        assert!(own > 0.029, "{own}");
        // About 80 points a cylinder: 1.7 mm each; over 400 overlapping ones
        // a bias would show above 0.5 mm.
        assert!(
            mean.abs() < 0.0005,
            "raised map points: plane offsets {mean} m"
        );
        // Cached: the same value again, to the last bit of f64 arithmetic on
        // f32-stored deltas.
        let again = assoc.plane_offset_at(raised[0]).unwrap();
        assert_eq!(again, assoc.plane_offset_at(raised[0]).unwrap());

        // A 3D point 10 mm above the floor keeps its full 10 mm residual:
        // the nearest map points to it (raised ones) do not move the plane.
        let mut residuals = Vec::new();
        for k in 0..200 {
            let (x, y) = (-1.0 + 0.01 * k as f64, 0.37 - 0.003 * k as f64);
            let at = Vector3::new(500_000.0 + x, 4_400_000.0 + y, 200.01);
            let (n, d) = assoc.plane_near(&at, 0.1).unwrap();
            assert_eq!(n, Vector3::z());
            residuals.push(n.dot(&at) - d);
        }
        let mean = residuals.iter().sum::<f64>() / residuals.len() as f64;
        assert!(
            (mean - 0.01).abs() < 0.001,
            "residual {mean} m of a point 10 mm off"
        );
    }

    /// Stray map points (LiDAR outliers) give no plane, and a 3D point next
    /// to one takes the surface's plane below it instead.
    #[test]
    fn stray_map_points_give_no_plane() {
        let (mut cloud, _) = noisy_floor();
        let floor = cloud.len();
        // Five strays 5-30 cm above the floor, each with a normal that puts
        // its tangent plane through the query point next to it.
        let strays = [
            ([0.31f32, 0.42, 0.05], [1.0f32, 0.0, 0.0]),
            ([-0.5, 0.2, 0.1], [0.0, 1.0, 0.0]),
            ([0.7, -0.6, 0.2], [0.6, 0.0, 0.8]),
            ([-0.2, -0.9, 0.3], [0.0, 0.0, 1.0]),
            ([0.0, 0.0, 0.12], [0.0, 0.8, 0.6]),
        ];
        for (p, n) in strays {
            cloud.points.push(p);
            cloud.normals.as_mut().unwrap().push(n);
        }
        let index = MapIndex::build(&cloud).unwrap();
        // The default gate (5), and none.
        let gated = NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let open = NearestNeighbourAssociator::new(
            &cloud,
            &index,
            AssociationOptions {
                min_plane_support: 0,
                ..Default::default()
            },
        );
        for (k, (_, n)) in strays.iter().enumerate() {
            let i = floor + k;
            assert_eq!(gated.plane_offset_at(i), None, "stray {k}");
            assert_eq!(gated.plane_offset_at(i), None, "stray {k}, cached");
            assert!(
                open.plane_offset_at(i).is_some(),
                "stray {k} without the gate"
            );
            // A 3D point 1 mm from the stray, on its tangent plane: without
            // the gate the stray's plane wins (the closest tangent plane);
            // with it, the floor's.
            let along = Vector3::new(f64::from(n[1]), -f64::from(n[0]), 0.0);
            let along = if along.norm() < 0.5 {
                Vector3::x()
            } else {
                along.normalize()
            };
            let at = cloud.point_in_map(i) + along * 0.001;
            let (normal, offset) = gated.plane_near(&at, 0.5).unwrap();
            assert_eq!(normal, Vector3::z(), "stray {k}");
            assert!(
                (offset - 200.0).abs() < 0.008,
                "stray {k}: floor offset {offset}"
            );
            let (normal, _) = open.plane_near(&at, 0.5).unwrap();
            let n = Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2])).normalize();
            assert_eq!(normal, n, "stray {k} without the gate");
        }
        // The floor's points keep their planes.
        for i in (0..floor).step_by(997) {
            let offset = gated.plane_offset_at(i).unwrap();
            assert!((offset - 200.0).abs() < 0.008, "floor point {i}: {offset}");
        }
    }
}
