//! Synthetic scenes with exact ground truth: geometry, textures, ray-cast rendering, LiDAR sampling.
