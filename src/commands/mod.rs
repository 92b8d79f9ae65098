//! One module per command of the `colmap-lidar` binary.
pub mod bench_map;
pub mod colour_map;
pub mod depth;
pub mod evaluate;
pub mod inspect;
pub mod map;
pub mod merge;
pub mod plot;
pub mod prepare_map;
pub mod synth;
