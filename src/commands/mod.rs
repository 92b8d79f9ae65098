//! One module per command of the `colmap-lidar` binary.
pub mod evaluate;
pub mod inspect;
pub mod synth;
