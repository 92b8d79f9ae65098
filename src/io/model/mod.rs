//! COLMAP model files (cameras, images, points3D), text and binary.
