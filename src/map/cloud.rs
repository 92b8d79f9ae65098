//! The in-memory LiDAR map.
//!
//! Coordinates are stored as f32 offsets from a local origin (f64), chosen once
//! at load time: georeferenced maps (UTM, 10^5..10^7 m) keep sub-millimetre
//! resolution for maps up to several kilometres across, and a point costs 12
//! bytes instead of 24. `origin + point` is the point in the map frame.
use nalgebra::Vector3;

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

    /// Point `i` in the map frame (f64).
    pub fn point_in_map(&self, i: usize) -> Vector3<f64> {
        let p = self.points[i];
        self.origin + Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
    }
}
