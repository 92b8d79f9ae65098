//! Surfels: the map's surfaces summarised cell by cell, for plane fits wider
//! than a point's neighbourhood.
//!
//! The map is cut into cubic cells; in each, the usable points (those with a
//! normal that may give a plane) are grouped by normal (within
//! `same_plane_max_angle`) and then by offset along it (a gap wider than the
//! plane window starts another surface), and each group keeps its count,
//! mean and scatter matrix: a surfel. A plane over a wide patch is then the
//! least-squares fit of the surfels' pooled moments, which costs a few
//! hundred surfels however many map points they hold.
//!
//! Why: a plane's offset from the map points within a few centimetres of a
//! point carries the map's range noise divided by the square root of their
//! number, and image points cluster, so neighbouring points share that
//! error. On the synthetic yard (5.4 cm spacing, 15 mm noise) the map's
//! noise entered a 24-image model only through those offsets: the same
//! noisy map with the true planes' offsets put it 2.0 mm off instead of
//! 3.9 mm, as the noise-free map did (2.1 mm). A flat surface's plane fitted
//! over a metre averages thousands of points. [`SurfelMap::fit_around`]
//! widens the patch in steps while the wider plane agrees with the narrower
//! one within their noise, so a curved or stepped surface keeps its local
//! plane. The mapper uses it on request
//! (`[mapper.association] plane_fit_max_radius_m`; session 72,
//! `docs/results.md`).
use std::collections::HashMap;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;

/// One cell's points of one surface: their count, mean (relative to the
/// cloud's origin) and scatter about the mean, and their mean normal.
#[derive(Clone, Debug)]
struct Surfel {
    count: u32,
    mean: Vector3<f64>,
    scatter: Matrix3<f64>,
    normal: Vector3<f64>,
}

/// A plane fitted over a patch of surfels around one surfel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FittedPlane {
    /// Unit normal (on the side of the surfel's normal).
    pub normal: Vector3<f64>,
    /// The patch's mean, map frame (metres).
    pub centroid: Vector3<f64>,
    /// Map points in the fit.
    pub count: u32,
    /// The patch's in-plane scatter: its two axes (unit, in the plane) and
    /// their sums of squares (m²), for the plane's uncertainty away from the
    /// centroid.
    pub axes: [(Vector3<f64>, f64); 2],
    /// The radius of the patch (metres).
    pub radius_m: f64,
}

impl FittedPlane {
    /// Where the plane crosses the line `at + t n` (`n` a unit normal near
    /// the plane's): the offset `n . x` of that crossing, and its variance
    /// in units of the map's noise variance (`1 / count` at the centroid,
    /// growing with the distance from it; measured along the plane's
    /// normal, about right for `n` within a few degrees of it). `None` when
    /// `n` is more than 60 degrees from the plane's normal.
    pub fn offset_along(&self, at: &Vector3<f64>, n: &Vector3<f64>) -> Option<(f64, f64)> {
        let c = self.normal.dot(n);
        if c.abs() < 0.5 {
            return None;
        }
        let t = self.normal.dot(&(self.centroid - at)) / c;
        let crossing = at + n * t;
        let away = crossing - self.centroid;
        let mut var = 1.0 / f64::from(self.count.max(1));
        for (axis, sum_sq) in &self.axes {
            let u = axis.dot(&away);
            var += u * u / sum_sq.max(1e-12);
        }
        Some((n.dot(at) + t, var))
    }
}

/// What [`SurfelMap::build`] groups and how.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfelOptions {
    /// Edge of a cell (metres).
    pub cell_m: f64,
    /// Normals within this cosine share a surface.
    pub cos_same: f64,
    /// Points further apart than this along the normal are on different
    /// surfaces (metres); also the window a fit takes surfels in.
    pub window_m: f64,
}

/// The map's surfels, and which surfel each map point is in.
#[derive(Debug)]
pub struct SurfelMap {
    origin: Vector3<f64>,
    surfels: Vec<Surfel>,
    /// Per map point, its surfel, or `u32::MAX` for a point left out.
    of_point: Vec<u32>,
    /// Surfels by coarse cell (`search_m` edge), for neighbourhood queries.
    buckets: HashMap<[i64; 3], Vec<u32>>,
    search_m: f64,
    options: SurfelOptions,
    /// The map's range noise read from the surfels (metres; see
    /// [`Self::read_noise`]).
    noise_m: f64,
}

const NONE: u32 = u32::MAX;

/// The cosine of the angle within which a fit looks for its members'
/// normals before choosing them about its plane (45 degrees).
const LOOSE_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// The cell of `p` (coordinates saturate far out: such cells merge, no
/// overflow).
fn cell_of(p: &Vector3<f64>, size: f64) -> [i64; 3] {
    [
        (p.x / size).floor() as i64,
        (p.y / size).floor() as i64,
        (p.z / size).floor() as i64,
    ]
}

/// Moments of a set of points: count, mean, scatter about the mean.
fn moments(points: &[Vector3<f64>]) -> (u32, Vector3<f64>, Matrix3<f64>) {
    let n = points.len();
    let mean = points.iter().sum::<Vector3<f64>>() / n.max(1) as f64;
    let scatter = points
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum::<Matrix3<f64>>();
    (n as u32, mean, scatter)
}

impl SurfelMap {
    /// Surfels of `cloud`'s points for which `normal_of` gives a normal;
    /// `search_m` is the coarse cell of the neighbourhood queries (about
    /// half the widest fit's radius).
    pub fn build(
        cloud: &PointCloud,
        normal_of: impl Fn(usize) -> Option<Vector3<f64>> + Sync,
        options: SurfelOptions,
        search_m: f64,
    ) -> Self {
        let mut by_cell: Vec<([i64; 3], u32)> = (0..cloud.len())
            .into_par_iter()
            .filter_map(|i| {
                normal_of(i)?;
                let p = cloud.points[i];
                let p = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                Some((cell_of(&p, options.cell_m), i as u32))
            })
            .collect();
        by_cell.par_sort_unstable();
        let mut starts: Vec<usize> = (0..by_cell.len())
            .filter(|&k| k == 0 || by_cell[k].0 != by_cell[k - 1].0)
            .collect();
        starts.push(by_cell.len());
        let point = |i: u32| {
            let p = cloud.points[i as usize];
            Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
        };
        // Each cell's groups, in cell order (deterministic).
        let groups: Vec<Vec<(Surfel, Vec<u32>)>> = starts
            .par_windows(2)
            .map(|w| {
                let members: Vec<(u32, Vector3<f64>)> = by_cell[w[0]..w[1]]
                    .iter()
                    .filter_map(|&(_, i)| Some((i, normal_of(i as usize)?)))
                    .collect();
                group_cell(&members, &point, &options)
            })
            .collect();
        drop(by_cell);
        let mut surfels = Vec::new();
        let mut of_point = vec![NONE; cloud.len()];
        let mut buckets: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
        for (surfel, ids) in groups.into_iter().flatten() {
            let id = surfels.len() as u32;
            for i in ids {
                of_point[i as usize] = id;
            }
            buckets
                .entry(cell_of(&surfel.mean, search_m))
                .or_default()
                .push(id);
            surfels.push(surfel);
        }
        let mut map = Self {
            origin: cloud.origin,
            surfels,
            of_point,
            buckets,
            search_m,
            options,
            noise_m: 0.0,
        };
        map.noise_m = map.read_noise();
        map
    }

    /// The map's range noise (metres): over a sample of up to 2000
    /// surfels, the RMS distance of the map points within two cells of each
    /// to their pooled plane (a surface crossing a cell's face is cut in
    /// two surfels, each with a clipped spread); the median.
    fn read_noise(&self) -> f64 {
        let radius = 2.0 * self.options.cell_m;
        let stride = self.surfels.len().div_ceil(2000).max(1);
        let mut spreads: Vec<f64> = (0..self.surfels.len())
            .step_by(stride)
            .collect::<Vec<usize>>()
            .par_iter()
            .filter_map(|&s| {
                let seed = &self.surfels[s];
                let near = self.same_surface_near(s as u32, radius, LOOSE_COS);
                let (mut n, mut at) = (seed.normal, seed.mean);
                let fit = self.pool_about(&near, radius, &mut n, &mut at, seed)?;
                (fit.plane.count >= 10)
                    .then(|| (fit.residual_sq / f64::from(fit.plane.count - 3)).sqrt())
            })
            .collect();
        spreads.sort_by(f64::total_cmp);
        spreads.get(spreads.len() / 2).copied().unwrap_or(0.0)
    }

    /// The surfels within `radius` of surfel `s`'s mean whose normals'
    /// cosine with its normal is at least `cos_min`, with their distances, nearest first
    /// (ties by id); `radius` at most twice the search cell.
    fn same_surface_near(&self, s: u32, radius: f64, cos_min: f64) -> Vec<(f64, u32)> {
        let seed = &self.surfels[s as usize];
        let reach = (radius / self.search_m).ceil() as i64;
        let home = cell_of(&seed.mean, self.search_m);
        let mut near: Vec<(f64, u32)> = Vec::new();
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    let key = [
                        home[0].saturating_add(dx),
                        home[1].saturating_add(dy),
                        home[2].saturating_add(dz),
                    ];
                    let Some(ids) = self.buckets.get(&key) else {
                        continue;
                    };
                    for &t in ids {
                        let other = &self.surfels[t as usize];
                        if other.normal.dot(&seed.normal) < cos_min {
                            continue;
                        }
                        let d = (other.mean - seed.mean).norm();
                        if d <= radius {
                            near.push((d, t));
                        }
                    }
                }
            }
        }
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        near
    }

    /// The map's range noise the surfels read (metres).
    pub fn noise_m(&self) -> f64 {
        self.noise_m
    }

    pub fn len(&self) -> usize {
        self.surfels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.surfels.is_empty()
    }

    /// The surfel map point `i` is in.
    pub fn surfel_of(&self, i: usize) -> Option<u32> {
        self.of_point.get(i).copied().filter(|&s| s != NONE)
    }

    /// The pooled fit of the candidates `near` (distance, surfel; nearest
    /// first) within `radius` whose normals are within `cos_same` of the
    /// plane `(plane_n, plane_at)` and whose means lie within the window of
    /// it, twice: about the given plane, then about the first pass's fit
    /// (a noisy map's normals scatter by degrees, and members chosen about a
    /// seed's own normal are those tilted its way). The plane is left at the
    /// last fit.
    fn pool_about(
        &self,
        near: &[(f64, u32)],
        radius: f64,
        plane_n: &mut Vector3<f64>,
        plane_at: &mut Vector3<f64>,
        seed: &Surfel,
    ) -> Option<Pooled> {
        let mut fit = None;
        for _ in 0..2 {
            let (n, at) = (*plane_n, *plane_at);
            let members = near
                .iter()
                .take_while(|(d, _)| *d <= radius)
                .map(|&(_, t)| &self.surfels[t as usize])
                .filter(|o| {
                    o.normal.dot(&n) >= self.options.cos_same
                        && n.dot(&(o.mean - at)).abs() <= self.options.window_m
                });
            fit = pool(members, &seed.mean, &seed.normal, radius);
            if let Some(f) = &fit {
                *plane_n = f.plane.normal;
                *plane_at = f.plane.centroid;
            }
        }
        fit
    }

    /// The plane around surfel `s`, fitted over the surfels of its surface
    /// within each of `radii` (increasing, metres) in turn: a wider patch
    /// replaces the narrower one while its plane, where it crosses the
    /// surfel's mean along the surfel's normal, lies within 3 sigma of the
    /// narrower plane's (both planes' uncertainty from `noise_m`, at least
    /// `min_noise_m`) and its points lie within `max_spread` times the noise of
    /// it (RMS). A patch of fewer than `min_count` points is skipped (the
    /// next radius is compared with the last patch taken); `None` when no
    /// patch is taken.
    pub fn fit_around(
        &self,
        s: u32,
        radii: &[f64],
        min_noise_m: f64,
        max_spread: f64,
        min_count: u32,
    ) -> Option<FittedPlane> {
        let seed = &self.surfels[s as usize];
        let noise = self.noise_m.max(min_noise_m);
        let widest = radii.last().copied()?;
        // Candidates by a loose normal gate: a noisy map's estimated normals
        // scatter by several degrees, and a gate about the seed's own normal
        // would keep the surfels tilted its way (a tilted fit); members are
        // chosen about the fitted plane instead.
        let near = self.same_surface_near(s, widest, LOOSE_COS);
        let mut best: Option<FittedPlane> = None;
        // The plane members are chosen about: the seed's, then each fit's.
        let (mut plane_n, mut plane_at) = (seed.normal, seed.mean);
        for &radius in radii {
            let before = (plane_n, plane_at);
            let fit = self.pool_about(&near, radius, &mut plane_n, &mut plane_at, seed);
            // Too few points: the next radius chooses its members about the
            // last plane taken, not about this one.
            let Some(fit) = fit.filter(|f| f.plane.count >= min_count) else {
                (plane_n, plane_at) = before;
                continue;
            };
            let spread =
                (fit.residual_sq / f64::from(fit.plane.count.saturating_sub(3).max(1))).sqrt();
            if spread > max_spread * noise {
                break;
            }
            if let Some(prev) = &best {
                let (Some((d0, v0)), Some((d1, v1))) = (
                    prev.offset_along(&seed.mean, &seed.normal),
                    fit.plane.offset_along(&seed.mean, &seed.normal),
                ) else {
                    break;
                };
                if (d1 - d0).abs() > 3.0 * noise * (v0 + v1).sqrt() {
                    break;
                }
            }
            plane_n = fit.plane.normal;
            plane_at = fit.plane.centroid;
            best = Some(fit.plane);
        }
        best.map(|p| FittedPlane {
            centroid: p.centroid + self.origin,
            ..p
        })
    }
}

/// A pooled fit and its residual sum of squares along its normal.
struct Pooled {
    plane: FittedPlane,
    residual_sq: f64,
}

/// The least-squares plane of the surfels' pooled moments (coordinates
/// relative to the cloud's origin, taken about `about` for precision);
/// the normal turned to the side of `side`.
fn pool<'a>(
    members: impl Iterator<Item = &'a Surfel>,
    about: &Vector3<f64>,
    side: &Vector3<f64>,
    radius_m: f64,
) -> Option<Pooled> {
    let mut n = 0.0;
    let mut sum = Vector3::zeros();
    let mut second = Matrix3::zeros();
    for s in members {
        let c = f64::from(s.count);
        let m = s.mean - about;
        n += c;
        sum += m * c;
        second += s.scatter + m * m.transpose() * c;
    }
    if n < 3.0 {
        return None;
    }
    let mean = sum / n;
    let scatter = second - mean * mean.transpose() * n;
    let eig = SymmetricEigen::new(scatter);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let mut normal: Vector3<f64> = eig.eigenvectors.column(order[0]).into_owned();
    if normal.dot(side) < 0.0 {
        normal = -normal;
    }
    let axis = |k: usize| {
        (
            eig.eigenvectors.column(order[k]).into_owned(),
            eig.eigenvalues[order[k]],
        )
    };
    Some(Pooled {
        plane: FittedPlane {
            normal,
            centroid: mean + about,
            count: n as u32,
            axes: [axis(1), axis(2)],
            radius_m,
        },
        residual_sq: eig.eigenvalues[order[0]].max(0.0),
    })
}

/// One cell's points (cloud index, normal) grouped into surfels: greedy
/// clusters by normal (each point joins the first group whose first normal
/// is within `cos_same`), each split where its points' offsets along that
/// normal leave a gap wider than `window_m` (a group may hold one point:
/// a surface that only grazes the cell, or one the cell's face cuts).
fn group_cell(
    members: &[(u32, Vector3<f64>)],
    point: &impl Fn(u32) -> Vector3<f64>,
    options: &SurfelOptions,
) -> Vec<(Surfel, Vec<u32>)> {
    // (first normal, members) per normal group.
    type Group = (Vector3<f64>, Vec<(u32, Vector3<f64>)>);
    let mut by_normal: Vec<Group> = Vec::new();
    for &(i, n) in members {
        match by_normal
            .iter_mut()
            .find(|(first, _)| first.dot(&n) >= options.cos_same)
        {
            Some((_, list)) => list.push((i, n)),
            None => by_normal.push((n, vec![(i, n)])),
        }
    }
    let mut out = Vec::new();
    for (first, list) in by_normal {
        let mut along: Vec<(f64, u32, Vector3<f64>)> = list
            .iter()
            .map(|&(i, n)| (first.dot(&point(i)), i, n))
            .collect();
        along.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut start = 0;
        for k in 1..=along.len() {
            if k < along.len() && along[k].0 - along[k - 1].0 <= options.window_m {
                continue;
            }
            let part = &along[start..k];
            start = k;
            let pts: Vec<Vector3<f64>> = part.iter().map(|&(_, i, _)| point(i)).collect();
            let (count, mean, scatter) = moments(&pts);
            let normal = part
                .iter()
                .map(|&(_, _, n)| n)
                .sum::<Vector3<f64>>()
                .try_normalize(1e-9)
                .unwrap_or(first);
            out.push((
                Surfel {
                    count,
                    mean,
                    scatter,
                    normal,
                },
                part.iter().map(|&(_, i, _)| i).collect(),
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    /// A noisy floor (z = 0) with a 0.3 m step up at x > 2 (a platform,
    /// same normal), points 2 cm apart, 15 mm of noise along z.
    fn stepped_floor() -> (PointCloud, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 0.015).unwrap();
        let mut cloud = PointCloud::default();
        let mut normals = Vec::new();
        let mut heights = Vec::new();
        for i in 0..200 {
            for j in 0..100 {
                let x = i as f64 * 0.02 + rng.gen_range(0.0..0.02);
                let y = j as f64 * 0.02 + rng.gen_range(0.0..0.02);
                let h = if x > 2.0 { 0.3 } else { 0.0 };
                let z = h + noise.sample(&mut rng);
                cloud.points.push([x as f32, y as f32, z as f32]);
                normals.push([0.0, 0.0, 1.0]);
                heights.push(h);
            }
        }
        cloud.normals = Some(normals);
        (cloud, heights)
    }

    /// The surfels of a cloud with normals (0.1 m cells, search cells of
    /// 0.4 m).
    fn surfels_of(cloud: &PointCloud) -> SurfelMap {
        let normal_of = |i: usize| {
            let n = cloud.normals.as_ref().unwrap()[i];
            Some(Vector3::new(
                f64::from(n[0]),
                f64::from(n[1]),
                f64::from(n[2]),
            ))
        };
        SurfelMap::build(cloud, normal_of, options(), 0.4)
    }

    fn options() -> SurfelOptions {
        SurfelOptions {
            cell_m: 0.1,
            cos_same: 15f64.to_radians().cos(),
            window_m: 0.1,
        }
    }

    #[test]
    fn a_wide_fit_averages_the_noise_and_stops_at_a_step() {
        let (cloud, heights) = stepped_floor();
        let map = surfels_of(&cloud);
        // The noise read from the surfels: 15 mm within a few per cent.
        assert!((map.noise_m() - 0.015).abs() < 0.0015, "{}", map.noise_m());
        let radii = [0.2, 0.4, 0.8, 1.6];
        let up = Vector3::z();
        // Points well inside the low floor: the plane's height there within
        // 1.5 mm (15 mm / sqrt(thousands of points)); the widest patches
        // are taken.
        let mut worst: f64 = 0.0;
        let mut widest: f64 = 0.0;
        for i in (0..cloud.len()).step_by(997) {
            let p = cloud.point_in_map(i);
            if p.x > 0.3 && p.x < 1.4 && p.y > 0.3 && p.y < 1.7 {
                let s = map.surfel_of(i).unwrap();
                let fit = map.fit_around(s, &radii, 0.001, 1.5, 10).unwrap();
                let (d, _) = fit.offset_along(&p, &up).unwrap();
                worst = worst.max((d - heights[i]).abs());
                widest = widest.max(fit.radius_m);
            }
        }
        assert!(worst < 0.0015, "{worst}");
        assert!(widest >= 0.8, "{widest}");
        // Near the step, on either side: the platform (0.3 m up) is not
        // pooled with the floor (the window), and each side's plane stays
        // within 3 mm of its true height.
        for (i, height) in heights.iter().enumerate() {
            let p = cloud.point_in_map(i);
            if (p.x - 2.0).abs() < 0.15 && i % 7 == 0 {
                let s = map.surfel_of(i).unwrap();
                let fit = map.fit_around(s, &radii, 0.001, 1.5, 10).unwrap();
                let (d, _) = fit.offset_along(&p, &up).unwrap();
                assert!((d - height).abs() < 0.003, "{height} {d}");
            }
        }
    }

    #[test]
    fn a_curved_surface_keeps_a_narrow_plane() {
        // A cylinder of radius 3 m lying along y (z = sqrt(9 - x^2) - 3),
        // without noise: any fit wider than a few centimetres misses the
        // surface at its own point, so the growth stops at once.
        let mut cloud = PointCloud::default();
        let mut normals = Vec::new();
        for i in 0..150 {
            for j in 0..150 {
                let x = -1.5 + i as f64 * 0.02;
                let y = j as f64 * 0.02;
                let z = (9.0 - x * x).sqrt() - 3.0;
                cloud.points.push([x as f32, y as f32, z as f32]);
                let n = Vector3::new(x, 0.0, z + 3.0).normalize();
                normals.push([n.x as f32, n.y as f32, n.z as f32]);
            }
        }
        cloud.normals = Some(normals);
        let map = surfels_of(&cloud);
        let centre = (0..cloud.len())
            .min_by(|&a, &b| {
                let (pa, pb) = (cloud.point_in_map(a), cloud.point_in_map(b));
                (pa.x.abs() + (pa.y - 1.5).abs()).total_cmp(&(pb.x.abs() + (pb.y - 1.5).abs()))
            })
            .unwrap();
        let s = map.surfel_of(centre).unwrap();
        let fit = map.fit_around(s, &[0.2, 0.4, 0.8, 1.6], 0.001, 1.5, 10);
        // At 0.2 m the sag is 0.2^2 / 6 = 7 mm: already more than 1.5 x
        // the 1 mm floor of the noise, so no plane wider than the first is
        // accepted, and that one only if it fits.
        assert!(fit.is_none_or(|f| f.radius_m <= 0.2), "{fit:?}");
    }
}
