//! Incremental structure-from-motion inside a LiDAR map (method.md section 4).
pub mod body_pose;
pub mod geometry;
