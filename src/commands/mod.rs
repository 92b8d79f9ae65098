//! One module per command of the `colmap-lidar` binary.
pub mod bench_map;
pub mod depth;
pub mod inspect;
pub mod prepare_map;
