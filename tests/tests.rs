//! The one integration-test binary (`autotests = false`): Ceres is linked once.
// `!(a < b)` is written on purpose throughout: it is true for NaN as well,
// so a NaN input is rejected by the same test as an out-of-range one.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
mod common;

mod camera_models;
mod database;
mod estimators;
mod map;
mod mapper;
mod model_io;
mod solver;
mod synth;
