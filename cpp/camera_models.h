// COLMAP camera models, templated for Ceres autodiff.
// The Rust twin is src/scene/camera.rs; tests check the two agree.
#pragma once

namespace colmap_lidar {

// Projects a point in the camera frame to pixel coordinates with COLMAP model
// `model_id` (COLMAP's ids, parameter order as in COLMAP). Returns false for an
// unknown model or a point that cannot be projected.
template <typename T>
bool ProjectPoint(int model_id, const T* params, const T* point_in_cam, T* pixel) {
  (void)model_id; (void)params; (void)point_in_cam; (void)pixel;
  return false;  // implemented by the camera-model work
}

// Number of parameters of COLMAP model `model_id`, or -1 if unknown.
int NumParams(int model_id);

}  // namespace colmap_lidar
