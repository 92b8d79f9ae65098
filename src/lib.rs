//! colmap-lidar: incremental structure-from-motion of photos inside a metric
//! LiDAR map. Reads a COLMAP database and a point-cloud map; writes a COLMAP
//! model in the map's frame and scale.
//!
//! Layout: `scene` (plain data), `io` (formats at the edges), `solver` (Ceres
//! bridge), `map` (the LiDAR map), `synth` (synthetic scenes), `commands`
//! (one module per CLI command).
// `!(a < b)` is written on purpose throughout: it is true for NaN as well,
// so a NaN input is rejected by the same test as an out-of-range one.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
pub mod commands;
pub mod estimators;
pub mod eval;
pub mod geo;
pub mod io;
pub mod map;
pub mod scene;
pub mod sfm;
pub mod solver;
pub mod synth;
