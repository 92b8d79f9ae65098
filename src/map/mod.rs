//! The LiDAR map: readers, preparation (downsampling, normals), spatial index,
//! projection into cameras.
pub mod cloud;

pub use cloud::PointCloud;
