//! Geometric estimators for incremental structure-from-motion (method.md 4.4-4.5).
//!
//! * [`ransac`]: generic LO-RANSAC over a small [`ransac::Estimator`] trait, with an
//!   injected seeded RNG (`ChaCha8Rng`): the same seed gives the same bits.
//! * [`p3p`]: minimal absolute pose from three bearing vectors (Lambda Twist).
//! * [`absolute_pose`]: PnP = P3P inside LO-RANSAC on pixel observations through the
//!   real camera model, then robust Levenberg-Marquardt refinement of the 6-DoF pose.
//! * [`triangulation`]: multi-view DLT, RANSAC over view pairs, cheirality /
//!   reprojection / triangulation-angle checks.
//! * [`similarity`]: Umeyama similarity (Sim3) between point sets, with RANSAC.
//! * [`ray_plane`]: ray / plane intersection in the world frame (map initialisation).
//!
//! Conventions: poses are `cam_from_world` ([`crate::scene::Rigid3`], `X_cam = R X_world + t`),
//! camera frame x right, y down, z forward; pixels in COLMAP's convention (the centre
//! of the top-left pixel is (0.5, 0.5)); residual thresholds are in pixels unless a
//! name says otherwise. Every estimator validates its options and returns typed
//! outcomes; nothing here panics on degenerate or non-finite input.
// `!(x > y)` is the intended form throughout: it rejects NaN as well.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod absolute_pose;
pub mod p3p;
pub mod ransac;
pub mod ray_plane;
pub mod similarity;
pub mod triangulation;

pub use absolute_pose::{
    estimate_absolute_pose, refine_absolute_pose, reprojection_error_px, AbsolutePoseOptions,
    AbsolutePoseOutcome, Correspondence2D3D, PoseRefinementError, PoseRefinementOptions,
    PoseRefinementSummary, RegisteredPose, RobustLoss,
};
pub use p3p::p3p;
pub use ransac::{Estimator, RansacError, RansacOptions, RansacReport};
pub use ray_plane::{
    camera_ray_in_world, intersect_pixel_ray_plane, intersect_ray_plane, RayPlaneHit, RayPlaneMiss,
    RayPlaneOptions,
};
pub use similarity::{estimate_sim3_ransac, umeyama, Sim3};
pub use triangulation::{
    triangulate_dlt, triangulate_point, triangulate_track_ransac, triangulation_angle_deg,
    PointObservation, TriangulatedPoint, TriangulationFailure, TriangulationOptions,
};

/// An options struct failed validation: names the field and the problem.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid estimator option `{field}`: {problem}")]
pub struct InvalidOptions {
    pub field: &'static str,
    pub problem: String,
}

impl InvalidOptions {
    pub(crate) fn new(field: &'static str, problem: impl Into<String>) -> Self {
        Self {
            field,
            problem: problem.into(),
        }
    }
}
