#include "colmap-lidar/cpp/camera_bridge.h"

#include <stdexcept>

#include "camera_models.h"

namespace colmap_lidar {

int NumParams(int model_id) {
  (void)model_id;
  return -1;
}

void project_points(int32_t model_id, rust::Slice<const double> params,
                    rust::Slice<const double> points_in_cam,
                    rust::Slice<double> pixels) {
  (void)model_id; (void)params; (void)points_in_cam; (void)pixels;
  throw std::runtime_error("camera models not implemented yet");
}

}  // namespace colmap_lidar
