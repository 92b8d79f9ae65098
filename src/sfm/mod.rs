//! Incremental structure-from-motion inside a LiDAR map (method.md section 4),
//! in GLOMAP-like stages: each stage is one module with one options struct
//! ([`options`]) and one entry point; [`mapper`] runs them as numbered,
//! timed, logged stages, and [`runs`] wraps that run in the early look, the
//! retries, the restart and the search that a rough initial pose calls for.
//!
//! * [`state`]: the reconstruction under construction (tracks, next-best-view
//!   book-keeping);
//! * [`initialize`]: the initial image at the user's pose, features on the
//!   map's tangent planes, the second image by PnP;
//! * [`register`]: next-best view, P3P LO-RANSAC, refinement;
//! * [`triangulate`]: new points, track continuation and merging;
//! * [`bundle`] + [`associate`]: local/global BA through Ceres with LiDAR
//!   point-to-plane terms from a pluggable associator;
//! * [`align`]: the whole model moved onto the map (similarity, shape held);
//! * [`localise`]: a model placed on the map from a rough initial pose;
//! * [`positions`]: the rough pose from the images' GPS positions;
//! * [`existing`]: an earlier model to extend, matched to the database;
//! * [`groups`]: one run per group of images no match links, one model;
//! * [`filter`]: outlier filters; [`report`]: `report.json`.
pub mod align;
pub mod associate;
pub mod bundle;
pub mod existing;
pub mod filter;
pub mod focal;
pub mod geometry;
pub mod groups;
pub mod initialize;
pub mod keypoints;
pub mod localise;
pub mod mapper;
pub mod options;
pub mod positions;
pub mod register;
pub mod report;
pub mod runs;
pub mod state;
pub mod triangulate;

pub use groups::{map_groups, GroupStart};
pub use mapper::{extend_model, KnownPose, MapperError, MapperInputs, MapperOutput};
pub use options::MapperOptions;
pub use runs::{run_mapper, run_mapper_from_pose, run_mapper_searching, run_mapper_with_priors};
