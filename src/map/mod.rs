//! The LiDAR map: readers, preparation (downsampling, normals), spatial index,
//! projection into cameras.
pub mod cloud;
pub mod io;
pub mod prepare;

pub use cloud::PointCloud;
