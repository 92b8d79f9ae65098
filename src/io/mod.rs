//! Formats at the edges: the COLMAP database, COLMAP model files, `pose.ply` pose
//! files, atomic outputs.
pub mod atomic;
pub mod database;
pub mod model;
pub mod pose_ply;
