//! Plain data: cameras, poses, images, tracks, reconstructions, the correspondence
//! graph. No SQLite, no FFI, no logging here.
pub mod body_pose;
pub mod camera;
pub mod correspondence_graph;
pub mod ids;
pub mod merge;
pub mod pose;
pub mod reconstruction;

pub use body_pose::BodyPose;
pub use camera::{Camera, CameraModel};
pub use ids::{CameraId, ImageId, Point2DIdx, Point3DId};
pub use pose::Rigid3;
pub use reconstruction::{Image, Point2D, Point3D, Reconstruction, TrackElement};
