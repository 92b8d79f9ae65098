//! Typed ids with COLMAP's widths. "No point" is `Option<Point3DId>`, never a sentinel.
use serde::{Deserialize, Serialize};
use std::fmt;

macro_rules! id_type {
    ($(#[$doc:meta])* $name:ident, $inner:ty) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
        pub struct $name(pub $inner);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                self.0.fmt(f)
            }
        }
    };
}

id_type!(
    /// `cameras.camera_id` (u32 in COLMAP).
    CameraId,
    u32
);
id_type!(
    /// `images.image_id` (u32 in COLMAP; 1-based, < 2^31 so pair ids fit).
    ImageId,
    u32
);
id_type!(
    /// A 3D point id (u64 in COLMAP's model files).
    Point3DId,
    u64
);

/// Index of a keypoint within its image (row of the `keypoints` blob).
pub type Point2DIdx = u32;
