//! Tests of the incremental mapper (`colmap-lidar map`).
//!
//! * `toy`: an in-memory room (planes), exact features and matches, no COLMAP:
//!   registration, accuracy against ground truth in the map frame, scale,
//!   determinism, bad inputs, track merging and filtering.
//! * `colmap_e2e`: the synthetic scenes of the `synth` module with real
//!   COLMAP databases (skipped loudly when colmap or the scenes are absent).
mod colmap_e2e;
mod toy;
