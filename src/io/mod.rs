//! Formats at the edges: the COLMAP database, COLMAP model files, atomic outputs.
pub mod atomic;
pub mod database;
pub mod model;
