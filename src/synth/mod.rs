//! Synthetic scenes with exact ground truth: geometry, textures, ray-cast
//! rendering, LiDAR sampling, the scene folder writer, and the harness that
//! runs the real COLMAP feature extraction and matching on a scene.
//!
//! * [`scenes`]: the built-in scenes (yard, room, corridor) and trajectories.
//! * [`generate`]: [`generate_scene`] writes images, LiDAR maps, the true
//!   cameras and the initial pose.
//! * [`BodyPose`] (in `scene`): body pose (x forward, y left, z up;
//!   roll/pitch/yaw) <-> `cam_from_world`, the map convention of method.md
//!   section 2.
//! * [`colmap_harness`]: [`make_database`] runs `colmap feature_extractor` and
//!   `exhaustive_matcher` headless.
use std::path::{Path, PathBuf};

pub mod colmap_harness;
pub mod generate;
pub mod geometry;
pub mod lens;
pub mod lidar;
pub mod render;
pub mod scenes;
pub mod texture;

pub use crate::scene::BodyPose;
pub use colmap_harness::{copy_with_guessed_camera, make_database, HarnessOptions};
pub use generate::{generate_scene, read_init_pose, SceneSummary, SynthOptions};
pub use scenes::SceneKind;

/// Errors of the scene generator and the harness.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// An I/O error; `path` empty when the error names its own (the
    /// output folder's preparation and replacement).
    #[error("{}{source}", if path.as_os_str().is_empty() { String::new() } else { format!("{}: ", path.display()) })]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot encode image: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("the `colmap` binary was not found ({0}); install Debian's colmap (scripts/setup.sh)")]
    ColmapNotFound(String),
    #[error("`colmap {step}` failed ({status}); last lines of its output:\n{output_tail}")]
    ColmapFailed {
        step: String,
        status: String,
        output_tail: String,
    },
}

impl SynthError {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        SynthError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

impl From<std::io::Error> for SynthError {
    fn from(source: std::io::Error) -> Self {
        SynthError::Io {
            path: PathBuf::new(),
            source,
        }
    }
}
