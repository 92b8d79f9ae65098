//! The LiDAR map: readers, preparation (downsampling, normals), spatial index,
//! projection into cameras.
pub mod cloud;
pub mod colour;
pub mod depth_image;
pub mod grid;
pub mod index;
pub mod io;
pub mod prepare;
pub mod projection;
pub mod surface_depth;
pub mod surfels;

pub use cloud::PointCloud;
