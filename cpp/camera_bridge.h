#pragma once
#include "rust/cxx.h"

namespace colmap_lidar {

void project_points(int32_t model_id, rust::Slice<const double> params,
                    rust::Slice<const double> points_in_cam,
                    rust::Slice<double> pixels);

}  // namespace colmap_lidar
