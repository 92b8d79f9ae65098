// cxx bridge entry point for the C++ camera models (cpp/camera_models.h), used by
// Rust tests and tools to check them against src/scene/camera.rs.
#include "colmap-lidar/cpp/camera_bridge.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "camera_models.h"

namespace colmap_lidar {

void project_points(int32_t model_id, rust::Slice<const double> params,
                    rust::Slice<const double> points_in_cam,
                    rust::Slice<double> pixels) {
  const int num_params = NumParams(model_id);
  if (num_params < 0) {
    throw std::invalid_argument("project_points: unknown camera model id " +
                                std::to_string(model_id) + " (COLMAP ids are 0..10)");
  }
  if (params.size() != static_cast<size_t>(num_params)) {
    throw std::invalid_argument(
        "project_points: camera model id " + std::to_string(model_id) + " takes " +
        std::to_string(num_params) + " parameters, got " + std::to_string(params.size()));
  }
  if (points_in_cam.size() % 3 != 0) {
    throw std::invalid_argument("project_points: points_in_cam has " +
                                std::to_string(points_in_cam.size()) +
                                " values, not a multiple of 3");
  }
  const size_t num_points = points_in_cam.size() / 3;
  if (pixels.size() != 2 * num_points) {
    throw std::invalid_argument("project_points: pixels has " + std::to_string(pixels.size()) +
                                " values, expected " + std::to_string(2 * num_points) +
                                " for " + std::to_string(num_points) + " points");
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (size_t i = 0; i < num_points; ++i) {
    double pixel[2];
    const bool ok = ProjectPoint(model_id, params.data(), points_in_cam.data() + 3 * i, pixel);
    const bool finite = ok && std::isfinite(pixel[0]) && std::isfinite(pixel[1]);
    pixels[2 * i] = finite ? pixel[0] : nan;
    pixels[2 * i + 1] = finite ? pixel[1] : nan;
  }
}

}  // namespace colmap_lidar
