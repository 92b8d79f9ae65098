//! The one integration-test binary (`autotests = false`): Ceres is linked once.
mod common;

mod camera_models;
mod database;
mod estimators;
mod map;
mod mapper;
mod model_io;
mod solver;
mod synth;
