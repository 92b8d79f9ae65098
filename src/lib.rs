//! colmap-lidar: incremental structure-from-motion of photos inside a metric
//! LiDAR map. Reads a COLMAP database and a point-cloud map; writes a COLMAP
//! model in the map's frame and scale.
//!
//! Layout: `scene` (plain data), `io` (formats at the edges), `solver` (Ceres
//! bridge), `map` (the LiDAR map), `synth` (synthetic scenes), `commands`
//! (one module per CLI command).
pub mod commands;
pub mod estimators;
pub mod eval;
pub mod io;
pub mod map;
pub mod scene;
pub mod sfm;
pub mod solver;
pub mod synth;
