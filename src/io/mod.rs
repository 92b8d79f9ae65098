//! Formats at the edges: the COLMAP database, COLMAP model files, `pose.ply` pose
//! files, the photos (point colours), atomic outputs.
pub mod atomic;
pub mod database;
pub mod images;
pub mod model;
pub mod pose_ply;
