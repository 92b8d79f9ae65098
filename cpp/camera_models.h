// COLMAP camera models, templated for Ceres autodiff.
//
// ProjectPoint maps a point in the camera frame (x right, y down, z forward) to
// pixel coordinates (COLMAP convention: the upper-left pixel's centre is at
// (0.5, 0.5)) with COLMAP's model ids and parameter orders:
//
//   id model                  params
//    0 SIMPLE_PINHOLE         f, cx, cy
//    1 PINHOLE                fx, fy, cx, cy
//    2 SIMPLE_RADIAL          f, cx, cy, k
//    3 RADIAL                 f, cx, cy, k1, k2
//    4 OPENCV                 fx, fy, cx, cy, k1, k2, p1, p2
//    5 OPENCV_FISHEYE         fx, fy, cx, cy, k1, k2, k3, k4
//    6 FULL_OPENCV            fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6
//    7 FOV                    fx, fy, cx, cy, omega
//    8 SIMPLE_RADIAL_FISHEYE  f, cx, cy, k
//    9 RADIAL_FISHEYE         f, cx, cy, k1, k2
//   10 THIN_PRISM_FISHEYE     fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1
//
// With (u, v) = (x / z, y / z) and r^2 = u^2 + v^2:
// * perspective models distort (u, v) directly;
// * fisheye models first map to equidistant coordinates
//   (a, b) = (u, v) * theta / r with theta = atan(r), then distort (a, b) with
//   theta^2 = a^2 + b^2;
// * FOV scales (u, v) by atan(2 r tan(omega / 2)) / (r omega).
// The removable singularities at r = 0 and omega = 0 are evaluated by Taylor
// series (AtanOverX, TanOverX), so values and autodiff derivatives stay finite.
//
// The Rust twin is src/scene/camera.rs; tests/camera_models.rs checks that the
// two agree to 1e-9 px. Only operations defined for ceres::Jet are used (found by
// ADL after `using std::...`), so the header needs no Ceres include.
#pragma once

#include <cmath>
#include <type_traits>

namespace colmap_lidar {

// COLMAP's camera model ids.
enum CameraModelId : int {
  kSimplePinhole = 0,
  kPinhole = 1,
  kSimpleRadial = 2,
  kRadial = 3,
  kOpenCv = 4,
  kOpenCvFisheye = 5,
  kFullOpenCv = 6,
  kFov = 7,
  kSimpleRadialFisheye = 8,
  kRadialFisheye = 9,
  kThinPrismFisheye = 10,
};

// Number of parameters of COLMAP model `model_id`, or -1 if unknown.
inline int NumParams(int model_id) {
  switch (model_id) {
    case kSimplePinhole:
      return 3;
    case kPinhole:
      return 4;
    case kSimpleRadial:
      return 4;
    case kRadial:
      return 5;
    case kOpenCv:
      return 8;
    case kOpenCvFisheye:
      return 8;
    case kFullOpenCv:
      return 12;
    case kFov:
      return 5;
    case kSimpleRadialFisheye:
      return 4;
    case kRadialFisheye:
      return 5;
    case kThinPrismFisheye:
      return 12;
    default:
      return -1;
  }
}

// Calls f(std::integral_constant<int, N>{}) for N = num_params, one of the
// models' parameter counts (3, 4, 5, 8 or 12), so that code templated on the
// count (Ceres' fixed-size parameter blocks) is chosen at run time. False,
// without calling f, for any other count.
template <typename F>
bool WithNumParams(int num_params, F&& f) {
  switch (num_params) {
    case 3:
      f(std::integral_constant<int, 3>{});
      return true;
    case 4:
      f(std::integral_constant<int, 4>{});
      return true;
    case 5:
      f(std::integral_constant<int, 5>{});
      return true;
    case 8:
      f(std::integral_constant<int, 8>{});
      return true;
    case 12:
      f(std::integral_constant<int, 12>{});
      return true;
    default:
      return false;
  }
}

// Below this squared argument, atan(x)/x and tan(x)/x are evaluated by their
// Taylor series (truncation error < 1e-20). Same constant in src/scene/camera.rs.
constexpr double kSeriesMaxArgSq = 1e-4;

// atan(x) / x as a function of x^2 (>= 0); 1 at x = 0.
template <typename T>
T AtanOverX(const T& x_sq) {
  using std::atan;
  using std::sqrt;
  if (x_sq < T(kSeriesMaxArgSq)) {
    // 1 - x^2/3 + x^4/5 - x^6/7 + x^8/9
    return T(1.0) +
           x_sq * (T(-1.0 / 3.0) +
                   x_sq * (T(1.0 / 5.0) +
                           x_sq * (T(-1.0 / 7.0) + x_sq * T(1.0 / 9.0))));
  }
  const T x = sqrt(x_sq);
  return atan(x) / x;
}

// tan(x) / x as a function of x^2 (>= 0, x < pi/2); 1 at x = 0.
template <typename T>
T TanOverX(const T& x_sq) {
  using std::sqrt;
  using std::tan;
  if (x_sq < T(kSeriesMaxArgSq)) {
    // 1 + x^2/3 + 2x^4/15 + 17x^6/315 + 62x^8/2835
    return T(1.0) +
           x_sq * (T(1.0 / 3.0) +
                   x_sq * (T(2.0 / 15.0) +
                           x_sq * (T(17.0 / 315.0) + x_sq * T(62.0 / 2835.0))));
  }
  const T x = sqrt(x_sq);
  return tan(x) / x;
}

// OpenCV's tangential terms added to (*x, *y) for the point (a, b) with
// r_sq = a^2 + b^2.
template <typename T>
void AddTangential(const T& p1, const T& p2, const T& a, const T& b,
                   const T& r_sq, T* x, T* y) {
  const T ab = a * b;
  *x += T(2.0) * p1 * ab + p2 * (r_sq + T(2.0) * a * a);
  *y += T(2.0) * p2 * ab + p1 * (r_sq + T(2.0) * b * b);
}

// Maps a point (u, v) on the normalised image plane (z = 1) to pixel
// coordinates. Returns false for an unknown model.
template <typename T>
bool ProjectNormalized(int model_id, const T* params, const T& u, const T& v,
                       T* pixel) {
  T fx, fy, cx, cy;  // focal lengths and principal point
  T x, y;            // distorted coordinates: pixel = f * (x, y) + c
  switch (model_id) {
    case kSimplePinhole:
      fx = fy = params[0];
      cx = params[1];
      cy = params[2];
      x = u;
      y = v;
      break;
    case kPinhole:
      fx = params[0];
      fy = params[1];
      cx = params[2];
      cy = params[3];
      x = u;
      y = v;
      break;
    case kSimpleRadial: {
      fx = fy = params[0];
      cx = params[1];
      cy = params[2];
      const T r_sq = u * u + v * v;
      const T radial = T(1.0) + params[3] * r_sq;
      x = u * radial;
      y = v * radial;
      break;
    }
    case kRadial: {
      fx = fy = params[0];
      cx = params[1];
      cy = params[2];
      const T r_sq = u * u + v * v;
      const T radial = T(1.0) + r_sq * (params[3] + r_sq * params[4]);
      x = u * radial;
      y = v * radial;
      break;
    }
    case kOpenCv: {
      fx = params[0];
      fy = params[1];
      cx = params[2];
      cy = params[3];
      const T r_sq = u * u + v * v;
      const T radial = T(1.0) + r_sq * (params[4] + r_sq * params[5]);
      x = u * radial;
      y = v * radial;
      AddTangential(params[6], params[7], u, v, r_sq, &x, &y);
      break;
    }
    case kFullOpenCv: {
      fx = params[0];
      fy = params[1];
      cx = params[2];
      cy = params[3];
      const T r_sq = u * u + v * v;
      // (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
      const T numerator =
          T(1.0) + r_sq * (params[4] + r_sq * (params[5] + r_sq * params[8]));
      const T denominator =
          T(1.0) + r_sq * (params[9] + r_sq * (params[10] + r_sq * params[11]));
      const T radial = numerator / denominator;
      x = u * radial;
      y = v * radial;
      AddTangential(params[6], params[7], u, v, r_sq, &x, &y);
      break;
    }
    case kFov: {
      fx = params[0];
      fy = params[1];
      cx = params[2];
      cy = params[3];
      const T omega = params[4];
      // atan(2 r tan(omega/2)) / (r omega) = AtanOverX((r a)^2) * a / omega
      // with a = 2 tan(omega/2) = omega * TanOverX((omega/2)^2).
      const T a_over_omega = TanOverX(T(0.25) * omega * omega);
      const T a = omega * a_over_omega;
      const T r_sq = u * u + v * v;
      const T factor = a_over_omega * AtanOverX(r_sq * a * a);
      x = u * factor;
      y = v * factor;
      break;
    }
    case kOpenCvFisheye:
    case kSimpleRadialFisheye:
    case kRadialFisheye:
    case kThinPrismFisheye: {
      const bool one_focal = model_id == kSimpleRadialFisheye || model_id == kRadialFisheye;
      const T* extra = params + (one_focal ? 3 : 4);
      fx = params[0];
      fy = one_focal ? params[0] : params[1];
      cx = one_focal ? params[1] : params[2];
      cy = one_focal ? params[2] : params[3];
      // Equidistant coordinates (a, b) = (u, v) * theta / r, theta = atan(r).
      const T theta_over_r = AtanOverX(u * u + v * v);
      const T a = u * theta_over_r;
      const T b = v * theta_over_r;
      const T theta_sq = a * a + b * b;
      T radial;
      if (model_id == kSimpleRadialFisheye) {
        radial = T(1.0) + extra[0] * theta_sq;
      } else if (model_id == kRadialFisheye) {
        radial = T(1.0) + theta_sq * (extra[0] + theta_sq * extra[1]);
      } else if (model_id == kOpenCvFisheye) {
        radial = T(1.0) +
                 theta_sq * (extra[0] +
                             theta_sq * (extra[1] +
                                         theta_sq * (extra[2] + theta_sq * extra[3])));
      } else {  // kThinPrismFisheye: k1, k2, p1, p2, k3, k4, sx1, sy1
        radial = T(1.0) +
                 theta_sq * (extra[0] +
                             theta_sq * (extra[1] +
                                         theta_sq * (extra[4] + theta_sq * extra[5])));
      }
      x = a * radial;
      y = b * radial;
      if (model_id == kThinPrismFisheye) {
        AddTangential(extra[2], extra[3], a, b, theta_sq, &x, &y);
        x += extra[6] * theta_sq;
        y += extra[7] * theta_sq;
      }
      break;
    }
    default:
      return false;
  }
  pixel[0] = fx * x + cx;
  pixel[1] = fy * y + cy;
  return true;
}

// Projects a point in the camera frame to pixel coordinates with COLMAP model
// `model_id` (COLMAP's ids, parameter order as in COLMAP). Returns false for an
// unknown model or a point that cannot be projected (z <= 0 or NaN).
template <typename T>
bool ProjectPoint(int model_id, const T* params, const T* point_in_cam, T* pixel) {
  if (!(point_in_cam[2] > T(0.0))) {
    return false;
  }
  const T u = point_in_cam[0] / point_in_cam[2];
  const T v = point_in_cam[1] / point_in_cam[2];
  return ProjectNormalized(model_id, params, u, v, pixel);
}

}  // namespace colmap_lidar
