//! Nearest-neighbour index of the LiDAR map, behind a small API of our own.
//!
//! A kiddo 6 immutable kd-tree (`f32`, 3D, items = point indices `u32`) holds
//! the map points **rotated by a fixed generic rotation** (`index_from_local`).
//! Building maps are made of floors and walls parallel to the axes, and
//! kd-tree queries on such axis-aligned planar clouds are 17-35x slower than on
//! generic clouds (many points share a split coordinate); a fixed rotation of
//! the cloud inside the index removes the degeneracy. Distances are invariant
//! under rotation, so callers never see the rotated frame: queries take points
//! in the map frame (f64), the index subtracts the cloud's local origin once and
//! rotates the offset.
//!
//! Accuracy: coordinates inside the tree are f32 offsets from the local origin,
//! so returned squared distances carry a relative error of about 1e-7 of the
//! map's extent (0.1 mm for a map 1 km across). Use
//! [`PointCloud::point_in_map`] for the exact point.
use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3, Vector3};

use super::cloud::PointCloud;

/// Errors building a [`MapIndex`].
#[derive(Debug, thiserror::Error)]
pub enum IndexError {
    #[error("the map has {0} points; the index holds at most 2^32 - 1")]
    TooManyPoints(usize),
    #[error("map point {index} has a non-finite coordinate")]
    NonFinitePoint { index: usize },
    #[error("building the kd-tree failed: {0}")]
    Construction(String),
}

/// One neighbour found by a query.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbour {
    /// Index of the point in the [`PointCloud`] the index was built from.
    pub point_idx: u32,
    /// Squared Euclidean distance to the query point (m²).
    pub dist_sq: f64,
}

/// Nearest-neighbour index of a [`PointCloud`]. Holds no reference to the
/// cloud; results are point indices into it.
pub struct MapIndex {
    /// The cloud's local origin (map frame, metres).
    origin: Vector3<f64>,
    /// Fixed generic rotation applied to local offsets before they enter the tree.
    index_from_local: Matrix3<f64>,
    /// `None` for an empty map (kiddo does not build empty trees).
    tree: Option<ImmutableKdTree<f32, 3>>,
    num_points: usize,
}

impl std::fmt::Debug for MapIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapIndex")
            .field("origin", &self.origin)
            .field("num_points", &self.num_points)
            .finish()
    }
}

/// The fixed rotation applied inside the index: generic angles (no multiple of
/// a simple fraction of pi), so no map axis stays aligned with a tree axis.
fn generic_rotation() -> Matrix3<f64> {
    Rotation3::from_euler_angles(0.371_4, 0.517_3, 0.834_2).into_inner()
}

impl MapIndex {
    /// Builds the index of every point of `cloud`. Parallel (rayon) for large
    /// maps; the tree does not depend on the number of threads.
    pub fn build(cloud: &PointCloud) -> Result<Self, IndexError> {
        let n = cloud.len();
        if n >= u32::MAX as usize {
            return Err(IndexError::TooManyPoints(n));
        }
        let index_from_local = generic_rotation();
        let tree = if n == 0 {
            None
        } else {
            let r = index_from_local;
            let mut rotated = vec![[0f32; 3]; n];
            {
                use rayon::prelude::*;
                rotated
                    .par_chunks_mut(1 << 16)
                    .zip(cloud.points.par_chunks(1 << 16))
                    .for_each(|(dst, src)| {
                        for (d, p) in dst.iter_mut().zip(src) {
                            let v = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                            let q = r * v;
                            *d = [q.x as f32, q.y as f32, q.z as f32];
                        }
                    });
            }
            if let Some(index) = rotated
                .iter()
                .position(|p| !p.iter().all(|c| c.is_finite()))
            {
                return Err(IndexError::NonFinitePoint { index });
            }
            let tree = ImmutableKdTree::<f32, 3>::new_from_slice_parallel(&rotated)
                .map_err(|e| IndexError::Construction(e.to_string()))?;
            Some(tree)
        };
        Ok(Self {
            origin: cloud.origin,
            index_from_local,
            tree,
            num_points: n,
        })
    }

    pub fn len(&self) -> usize {
        self.num_points
    }

    pub fn is_empty(&self) -> bool {
        self.num_points == 0
    }

    /// Query point in the tree's (rotated, local) frame.
    fn to_index_frame(&self, point_in_map: &Vector3<f64>) -> [f32; 3] {
        let q = self.index_from_local * (point_in_map - self.origin);
        [q.x as f32, q.y as f32, q.z as f32]
    }

    /// The nearest map point within `radius_m` (inclusive) of `point_in_map`,
    /// or `None` when there is none. Radius-bounded, so fast even far from the
    /// map.
    pub fn nearest_within(&self, point_in_map: &Vector3<f64>, radius_m: f64) -> Option<Neighbour> {
        let tree = self.tree.as_ref()?;
        if !(radius_m >= 0.0) {
            return None;
        }
        let q = self.to_index_frame(point_in_map);
        let radius_sq = (radius_m * radius_m) as f32;
        // NonZero literal: 1 is not zero.
        let one = NonZeroUsize::MIN;
        let found = tree
            .query(&q)
            .nearest_n::<SquaredEuclidean<f32>>(one)
            .within(radius_sq)
            .execute();
        found.first().map(|r| Neighbour {
            point_idx: r.item,
            dist_sq: f64::from(r.distance),
        })
    }

    /// [`nearest_within`](Self::nearest_within) for many query points at
    /// once: the answer for `points_in_map[i]` is at `i`. Queries run in a
    /// space-filling-curve order (consecutive queries touch the same tree
    /// nodes, so far fewer cache misses than in arbitrary order), in parallel
    /// over chunks (rayon); the result does not depend on the thread count.
    pub fn nearest_within_batch(
        &self,
        points_in_map: &[Vector3<f64>],
        radius_m: f64,
    ) -> Vec<Option<Neighbour>> {
        use rayon::prelude::*;
        let n = points_in_map.len();
        if self.tree.is_none() || n == 0 {
            return vec![None; n];
        }
        let order = spatial_order(points_in_map);
        let answers: Vec<(u32, Option<Neighbour>)> = order
            .par_chunks(1024)
            .flat_map_iter(|chunk| {
                chunk
                    .iter()
                    .map(|&i| (i, self.nearest_within(&points_in_map[i as usize], radius_m)))
            })
            .collect();
        let mut out = vec![None; n];
        for (i, a) in answers {
            out[i as usize] = a;
        }
        out
    }

    /// The nearest map point, whatever its distance (`None` for an empty map).
    /// Prefer [`nearest_within`](Self::nearest_within): unbounded queries far
    /// from any surface visit many tree nodes.
    pub fn nearest(&self, point_in_map: &Vector3<f64>) -> Option<Neighbour> {
        let tree = self.tree.as_ref()?;
        let q = self.to_index_frame(point_in_map);
        let r = tree
            .query(&q)
            .nearest_one::<SquaredEuclidean<f32>>()
            .execute();
        Some(Neighbour {
            point_idx: r.item,
            dist_sq: f64::from(r.distance),
        })
    }

    /// The `k` nearest map points, nearest first (ties by point index). Fewer
    /// than `k` when the map is smaller.
    pub fn k_nearest(&self, point_in_map: &Vector3<f64>, k: usize) -> Vec<Neighbour> {
        let (Some(tree), Some(k)) = (self.tree.as_ref(), NonZeroUsize::new(k)) else {
            return Vec::new();
        };
        let q = self.to_index_frame(point_in_map);
        let found = tree
            .query(&q)
            .nearest_n::<SquaredEuclidean<f32>>(k)
            .execute();
        sorted_neighbours(found.into_iter().map(|r| (r.item, r.distance)))
    }

    /// The `k` nearest map points within `radius_m` (inclusive), nearest first
    /// (ties by point index).
    pub fn k_nearest_within(
        &self,
        point_in_map: &Vector3<f64>,
        k: usize,
        radius_m: f64,
    ) -> Vec<Neighbour> {
        let (Some(tree), Some(k)) = (self.tree.as_ref(), NonZeroUsize::new(k)) else {
            return Vec::new();
        };
        if !(radius_m >= 0.0) {
            return Vec::new();
        }
        let q = self.to_index_frame(point_in_map);
        let found = tree
            .query(&q)
            .nearest_n::<SquaredEuclidean<f32>>(k)
            .within((radius_m * radius_m) as f32)
            .execute();
        sorted_neighbours(found.into_iter().map(|r| (r.item, r.distance)))
    }

    /// Every map point within `radius_m` (inclusive) of `point_in_map`,
    /// nearest first (ties by point index).
    pub fn within_radius(&self, point_in_map: &Vector3<f64>, radius_m: f64) -> Vec<Neighbour> {
        let Some(tree) = self.tree.as_ref() else {
            return Vec::new();
        };
        if !(radius_m >= 0.0) {
            return Vec::new();
        }
        let q = self.to_index_frame(point_in_map);
        let found = tree
            .query(&q)
            .within::<SquaredEuclidean<f32>>((radius_m * radius_m) as f32)
            .unsorted()
            .execute();
        sorted_neighbours(found.into_iter().map(|r| (r.item, r.distance)))
    }
}

/// Indices of `points` sorted along a Morton (z-order) curve over their
/// bounding box (10 bits an axis), ties by index.
fn spatial_order(points: &[Vector3<f64>]) -> Vec<u32> {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for p in points.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let scale = (hi - lo).map(|e| if e > 0.0 { 1023.0 / e } else { 0.0 });
    let spread = |mut v: u64| -> u64 {
        // Inserts two zero bits between the 10 low bits of v.
        v &= 0x3ff;
        v = (v | (v << 16)) & 0x0300_00ff;
        v = (v | (v << 8)) & 0x0300_f00f;
        v = (v | (v << 4)) & 0x030c_30c3;
        (v | (v << 2)) & 0x0924_9249
    };
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let q = (p - lo).component_mul(&scale);
            // NaN and out-of-range values saturate in `as`.
            let c = |a: usize| (q[a].clamp(0.0, 1023.0)) as u64;
            (
                spread(c(0)) | (spread(c(1)) << 1) | (spread(c(2)) << 2),
                i as u32,
            )
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Sorts by (distance, index): deterministic whatever the tree's visiting order.
fn sorted_neighbours(found: impl Iterator<Item = (u32, f32)>) -> Vec<Neighbour> {
    let mut v: Vec<(f32, u32)> = found.map(|(i, d)| (d, i)).collect();
    v.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    v.into_iter()
        .map(|(d, i)| Neighbour {
            point_idx: i,
            dist_sq: f64::from(d),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(points: Vec<[f32; 3]>) -> PointCloud {
        PointCloud {
            origin: Vector3::new(500_000.0, 4_000_000.0, 100.0),
            points,
            normals: None,
            planarity: None,
        }
    }

    #[test]
    fn hand_computed_queries() {
        let c = cloud(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]);
        let index = MapIndex::build(&c).unwrap();
        let q = c.origin + Vector3::new(0.9, 0.0, 0.0);
        let n = index.nearest_within(&q, 0.5).unwrap();
        assert_eq!(n.point_idx, 1);
        assert!((n.dist_sq - 0.01).abs() < 1e-5);
        assert!(index.nearest_within(&q, 0.05).is_none());
        let k = index.k_nearest(&q, 5);
        assert_eq!(
            k.iter().map(|n| n.point_idx).collect::<Vec<_>>(),
            vec![1, 0, 2]
        );
        let w = index.within_radius(&q, 1.0);
        assert_eq!(
            w.iter().map(|n| n.point_idx).collect::<Vec<_>>(),
            vec![1, 0]
        );
        assert_eq!(index.k_nearest_within(&q, 5, 1.0).len(), 2);
    }

    #[test]
    fn batch_equals_single_queries() {
        let mut points = Vec::new();
        for i in 0..2000u32 {
            let t = i as f32 * 0.01;
            points.push([t.sin() * 5.0, t.cos() * 3.0, t * 0.1]);
        }
        let c = cloud(points);
        let index = MapIndex::build(&c).unwrap();
        let queries: Vec<Vector3<f64>> = (0..500)
            .map(|i| {
                let t = i as f64 * 0.37;
                c.origin + Vector3::new(t.sin() * 6.0, t.cos() * 2.0, (t * 0.05) % 2.0)
            })
            .collect();
        let batch = index.nearest_within_batch(&queries, 0.5);
        assert_eq!(batch.len(), queries.len());
        let mut some = 0;
        for (q, b) in queries.iter().zip(&batch) {
            assert_eq!(*b, index.nearest_within(q, 0.5));
            some += usize::from(b.is_some());
        }
        assert!(some > 50 && some < 500, "{some}");
    }

    #[test]
    fn empty_map() {
        let index = MapIndex::build(&cloud(Vec::new())).unwrap();
        assert!(index.is_empty());
        let q = Vector3::zeros();
        assert!(index.nearest_within(&q, 10.0).is_none());
        assert!(index.nearest(&q).is_none());
        assert!(index.k_nearest(&q, 3).is_empty());
        assert!(index.within_radius(&q, 3.0).is_empty());
    }

    #[test]
    fn rejects_nan() {
        let c = cloud(vec![[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0]]);
        assert!(matches!(
            MapIndex::build(&c),
            Err(IndexError::NonFinitePoint { index: 1 })
        ));
    }
}
