//! The in-memory LiDAR map.
//!
//! Coordinates are stored as f32 offsets from a local origin (f64), chosen once
//! at load time: georeferenced maps (UTM, 10^5..10^7 m) keep sub-millimetre
//! resolution for maps up to several kilometres across, and a point costs 12
//! bytes instead of 24. `origin + point` is the point in the map frame.
use nalgebra::Vector3;
use rayon::prelude::*;

#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Local origin in the map frame (metres).
    pub origin: Vector3<f64>,
    /// Points relative to `origin` (metres).
    pub points: Vec<[f32; 3]>,
    /// Unit normals, one per point, when known.
    pub normals: Option<Vec<[f32; 3]>>,
    /// Planarity score per point in [0, 1] (1 = perfectly planar neighbourhood),
    /// when normals were estimated.
    pub planarity: Option<Vec<f32>>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Index of the first point with a NaN or infinite coordinate, if any.
    pub fn first_non_finite_point(&self) -> Option<usize> {
        self.points
            .par_iter()
            .position_first(|p| !p.iter().all(|c| c.is_finite()))
    }

    /// Point `i` in the map frame (f64).
    pub fn point_in_map(&self, i: usize) -> Vector3<f64> {
        let p = self.points[i];
        self.origin + Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
    }

    /// The smallest and largest coordinate along each axis (map frame);
    /// `None` for an empty cloud.
    pub fn bounds(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        if self.is_empty() {
            return None;
        }
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for i in 0..self.len() {
            let p = self.point_in_map(i);
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        Some((lo, hi))
    }

    /// Keeps the points whose `keep` flag is set, with their normals and
    /// planarity, in order.
    pub fn retain_flagged(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.points.len(), "one flag per point");
        fn filter<T: Copy>(values: &mut Vec<T>, keep: &[bool]) {
            let mut flags = keep.iter();
            values.retain(|_| *flags.next().unwrap_or(&false));
        }
        filter(&mut self.points, keep);
        if let Some(normals) = &mut self.normals {
            filter(normals, keep);
        }
        if let Some(planarity) = &mut self.planarity {
            filter(planarity, keep);
        }
    }
}

impl PointCloud {
    /// One cloud of several (e.g. the tiles of a survey), in order. When
    /// the non-empty clouds share a local origin it is kept and their points
    /// are appended as they are to the first one's; otherwise the origin is the middle of their
    /// bounds ([`crate::map::io::choose_origin`]: whole metres), so the
    /// largest offset is half the span, and every point is re-expressed from
    /// it (a second f32 rounding, under one f32 step at that offset).
    /// Normals are kept when any cloud has them (a cloud without gets zero
    /// normals, i.e. to be estimated); planarity only when every non-empty
    /// cloud has it.
    pub fn concatenate(clouds: Vec<PointCloud>) -> PointCloud {
        let filled: Vec<PointCloud> = clouds.into_iter().filter(|c| !c.is_empty()).collect();
        let Some(first) = filled.first() else {
            return PointCloud::default();
        };
        let first_origin = first.origin;
        let origin = if filled.iter().all(|c| c.origin == first_origin) {
            first_origin
        } else {
            let (lo, hi) = filled
                .iter()
                .filter_map(PointCloud::bounds)
                .reduce(|(l, h), (lo, hi)| (l.inf(&lo), h.sup(&hi)))
                .unwrap_or((first_origin, first_origin));
            let middle = 0.5 * (lo + hi);
            crate::map::io::choose_origin([middle.x, middle.y, middle.z])
        };
        let total: usize = filled.iter().map(PointCloud::len).sum();
        let any_normals = filled.iter().any(|c| c.normals.is_some());
        let all_planarity = filled.iter().all(|c| c.planarity.is_some());
        let mut clouds = filled.into_iter();
        // Sharing the origin, the first cloud's buffers grow in place (one
        // cloud: returned as it is); else the points go into new ones.
        let mut out = if origin == first_origin {
            clouds.next().expect("a non-empty cloud")
        } else {
            PointCloud {
                origin,
                ..Default::default()
            }
        };
        out.points.reserve(total - out.len());
        if any_normals && out.normals.is_none() {
            out.normals = Some(vec![[0.0; 3]; out.len()]);
        }
        if !all_planarity {
            out.planarity = None;
        }
        for cloud in clouds {
            let shift = cloud.origin - origin;
            if shift == Vector3::zeros() {
                out.points.extend_from_slice(&cloud.points);
            } else {
                out.points.extend(cloud.points.iter().map(|p| {
                    [
                        (shift.x + f64::from(p[0])) as f32,
                        (shift.y + f64::from(p[1])) as f32,
                        (shift.z + f64::from(p[2])) as f32,
                    ]
                }));
            }
            if let Some(normals) = &mut out.normals {
                match &cloud.normals {
                    Some(n) => normals.extend_from_slice(n),
                    None => normals.resize(out.points.len(), [0.0; 3]),
                }
            }
            if let (Some(values), Some(v)) = (&mut out.planarity, &cloud.planarity) {
                values.extend_from_slice(v);
            }
        }
        out
    }

    /// Scales every coordinate by `factor` (a change of length unit: feet to
    /// metres, say), the origin with them; normals and planarity stay.
    pub fn scale_coordinates(&mut self, factor: f64) {
        self.origin *= factor;
        self.points.par_iter_mut().for_each(|p| {
            for c in p.iter_mut() {
                *c = (f64::from(*c) * factor) as f32;
            }
        });
    }

    /// The largest distance of a point from the origin along any axis
    /// (metres; 0 for an empty cloud).
    pub fn max_offset_m(&self) -> f64 {
        self.points
            .par_iter()
            .map(|p| f64::from(p[0].abs().max(p[1].abs()).max(p[2].abs())))
            .reduce(|| 0.0, f64::max)
    }
}

/// Smallest and largest cell (per axis) of `points` under `cell_of`, in parallel.
/// For an empty slice: `([i64::MAX; 3], [i64::MIN; 3])`.
pub(crate) fn cell_bounds(
    points: &[[f32; 3]],
    cell_of: impl Fn(&[f32; 3]) -> [i64; 3] + Sync,
) -> ([i64; 3], [i64; 3]) {
    let empty = || ([i64::MAX; 3], [i64::MIN; 3]);
    let merge = |(lo, hi): ([i64; 3], [i64; 3]), (l, h): ([i64; 3], [i64; 3])| {
        (
            [lo[0].min(l[0]), lo[1].min(l[1]), lo[2].min(l[2])],
            [hi[0].max(h[0]), hi[1].max(h[1]), hi[2].max(h[2])],
        )
    };
    points
        .par_iter()
        .fold(empty, |acc, p| {
            let c = cell_of(p);
            merge(acc, (c, c))
        })
        .reduce(empty, merge)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concatenated_clouds_keep_their_map_coordinates() {
        let a = PointCloud {
            origin: Vector3::new(500_000.0, 4_400_000.0, 200.0),
            points: vec![[0.5, -1.25, 2.0], [3.0, 0.0, 0.0]],
            normals: Some(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
            planarity: Some(vec![0.9, 0.8]),
        };
        let b = PointCloud {
            origin: Vector3::new(500_010.0, 4_399_998.0, 200.0),
            points: vec![[-1.5, 2.25, 0.5]],
            normals: None,
            planarity: None,
        };
        let empty = PointCloud {
            origin: Vector3::new(1.0, 2.0, 3.0),
            ..Default::default()
        };
        let c = PointCloud::concatenate(vec![empty.clone(), a.clone(), b.clone()]);
        // The bounds: x 500000.5..500008.5, y 4399998.75..4400000.25, z
        // 200..202; the middle rounded to whole metres (halves away from 0).
        assert_eq!(c.origin, Vector3::new(500_005.0, 4_400_000.0, 201.0));
        assert_eq!(c.len(), 3);
        // All exact in f32: the same points in the map frame.
        for (i, (cloud, j)) in [(&a, 0), (&a, 1), (&b, 0)].into_iter().enumerate() {
            assert_eq!(c.point_in_map(i), cloud.point_in_map(j), "{i}");
        }
        assert_eq!(c.points[2], [3.5, 0.25, -0.5]);
        assert_eq!(
            c.normals.as_deref(),
            Some(&[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0; 3]][..])
        );
        assert_eq!(c.planarity, None);
        assert_eq!(c.max_offset_m(), 4.5);
        // Without normals anywhere, none; every cloud with planarity keeps it.
        let c = PointCloud::concatenate(vec![b.clone(), b.clone()]);
        assert_eq!((c.len(), c.normals, c.planarity), (2, None, None));
        // One origin: kept, the points copied bit for bit.
        let c = PointCloud::concatenate(vec![a.clone(), a.clone()]);
        assert_eq!(c.origin, a.origin);
        assert_eq!(c.points, [a.points.clone(), a.points.clone()].concat());
        assert_eq!(c.planarity, Some(vec![0.9, 0.8, 0.9, 0.8]));
        // Sharing the origin: a first cloud without normals gets zero ones, and
        // planarity goes when a later cloud has none.
        let mut with_normal = b.clone();
        with_normal.normals = Some(vec![[0.0, 1.0, 0.0]]);
        let c = PointCloud::concatenate(vec![b.clone(), with_normal]);
        assert_eq!(c.normals, Some(vec![[0.0; 3], [0.0, 1.0, 0.0]]));
        let mut without_planarity = a.clone();
        without_planarity.planarity = None;
        let c = PointCloud::concatenate(vec![a.clone(), without_planarity]);
        assert_eq!(
            (c.len(), c.normals.map(|n| n.len()), c.planarity),
            (4, Some(4), None)
        );
        // One cloud comes back as it is.
        assert_eq!(PointCloud::concatenate(vec![empty.clone(), a.clone()]), a);
        assert_eq!(PointCloud::concatenate(vec![empty]), PointCloud::default());
        assert_eq!(PointCloud::default().max_offset_m(), 0.0);
    }

    #[test]
    fn cell_bounds_of_a_hand_made_cloud() {
        let pts = [[0.5f32, -1.5, 2.0], [3.2, 0.0, -0.1], [-0.2, 7.9, 1.0]];
        let cell = |p: &[f32; 3]| p.map(|c| f64::from(c).floor() as i64);
        assert_eq!(cell_bounds(&pts, cell), ([-1, -2, -1], [3, 7, 2]));
        assert_eq!(cell_bounds(&[], cell), ([i64::MAX; 3], [i64::MIN; 3]));
    }
}
