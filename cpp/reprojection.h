// The reprojection residual and its Jacobians in closed form, for the
// solver's most frequent residual blocks.
//
//   X_cam = R(q) X + t               q = (w, x, y, z), cam_from_world
//   (u, v) = (x_cam / z_cam, y_cam / z_cam)
//   r      = weight * (pi_model(K, u, v) - x_observed)        [pixels * weight]
//
// The chain rule is written out: d(pixel)/d(u, v) (and d(pixel)/dK when the
// intrinsics vary) is the only part that depends on the camera model, and it
// comes from ceres::Jet with two (2 + #params) dual parts through
// ProjectNormalized (camera_models.h), so every COLMAP model is covered by
// the one code path. The rest is closed form:
//   d(u, v)/d(X_cam) = [1/z 0 -x/z^2; 0 1/z -y/z^2]
//   d(X_cam)/dt      = I
//   d(X_cam)/dX      = R(q)  (the rotation's linear map, exact for any q)
//   d(X_cam)/dq      = with v = (q1, q2, q3) and R(q) X = X + 2 q0 (v x X)
//                      + 2 (v (v.X) - X |v|^2):
//                      d/dq0 = 2 (v x X),
//                      d/dv  = -2 q0 [X]x + 2 ((v.X) I + v X^T - 2 X v^T).
// Automatic differentiation of the whole expression carries 10 (10 + #params)
// dual parts through every operation, the rotation included; measured on the
// 100-image corridor, the local solves' Ceres time fell by a fifth.
// cpp/camera_models_jet_check.cc compares both for every model.
//
// Header-only, Ceres' Jet only (no Ceres library).
#pragma once

#include <ceres/jet.h>

#include "camera_models.h"

namespace colmap_lidar {

// R(q) p for a unit quaternion q = (w, x, y, z): the operations of Ceres'
// UnitQuaternionRotatePoint in the same order (so the values agree to the
// last bit), templated for Jet checks.
template <typename T>
void RotateByUnitQuaternion(const T* q, const T* p, T* out) {
  T uv0 = q[2] * p[2] - q[3] * p[1];
  T uv1 = q[3] * p[0] - q[1] * p[2];
  T uv2 = q[1] * p[1] - q[2] * p[0];
  uv0 += uv0;
  uv1 += uv1;
  uv2 += uv2;
  out[0] = p[0] + q[0] * uv0;
  out[1] = p[1] + q[0] * uv1;
  out[2] = p[2] + q[0] * uv2;
  out[0] += q[2] * uv2 - q[3] * uv1;
  out[1] += q[3] * uv0 - q[1] * uv2;
  out[2] += q[1] * uv1 - q[2] * uv0;
}

// The pixel of (u, v) and d(pixel)/d(u, v) by a Jet through the camera model;
// with kWithParams also weight * d(pixel)/dK into `jacobian_params`
// (2 x kNumParams, row-major).
template <int kNumParams, bool kWithParams>
bool ProjectWithJet(int model_id, const double* params, double u, double v,
                    double weight, double pixel[2], double d_pixel_d_uv[2][2],
                    double* jacobian_params) {
  using JetT = ceres::Jet<double, kWithParams ? 2 + kNumParams : 2>;
  JetT params_jet[kNumParams];
  for (int k = 0; k < kNumParams; ++k) {
    if constexpr (kWithParams) {
      params_jet[k] = JetT(params[k], 2 + k);
    } else {
      params_jet[k] = JetT(params[k]);
    }
  }
  JetT pixel_jet[2];
  if (!ProjectNormalized(model_id, params_jet, JetT(u, 0), JetT(v, 1),
                         pixel_jet)) {
    return false;
  }
  for (int r = 0; r < 2; ++r) {
    pixel[r] = pixel_jet[r].a;
    d_pixel_d_uv[r][0] = pixel_jet[r].v[0];
    d_pixel_d_uv[r][1] = pixel_jet[r].v[1];
    if constexpr (kWithParams) {
      for (int k = 0; k < kNumParams; ++k) {
        jacobian_params[kNumParams * r + k] = weight * pixel_jet[r].v[2 + k];
      }
    }
  }
  return true;
}

// The residual (2 values) and, for each non-null pointer, its row-major
// Jacobian with respect to q (2 x 4), t (2 x 3) and X (2 x 3). `params` holds
// the model's kNumParams intrinsics. False, with nothing written, when the
// point is not in front of the camera or the model is unknown.
//
// With `jacobian_params` (2 x kNumParams, row-major) the Jet through the
// camera model carries the intrinsics too (2 + kNumParams dual parts).
template <int kNumParams>
bool EvaluateReprojection(int model_id, const double* params, const double* q,
                          const double* t, const double* point, double x_px,
                          double y_px, double weight, double* residuals,
                          double* jacobian_q, double* jacobian_t,
                          double* jacobian_point,
                          double* jacobian_params = nullptr) {
  double rotated[3];
  RotateByUnitQuaternion(q, point, rotated);
  const double xc = rotated[0] + t[0];
  const double yc = rotated[1] + t[1];
  const double zc = rotated[2] + t[2];
  if (!(zc > 0.0)) {
    return false;
  }
  const double inv_z = 1.0 / zc;
  const double u = xc * inv_z;
  const double v = yc * inv_z;

  const bool any_jacobian =
      jacobian_q || jacobian_t || jacobian_point || jacobian_params;
  double pixel[2];
  double d_pixel_d_uv[2][2] = {{0.0, 0.0}, {0.0, 0.0}};
  if (jacobian_params) {
    if (!ProjectWithJet<kNumParams, true>(model_id, params, u, v, weight, pixel,
                                          d_pixel_d_uv, jacobian_params)) {
      return false;
    }
  } else if (any_jacobian) {
    if (!ProjectWithJet<kNumParams, false>(model_id, params, u, v, weight,
                                           pixel, d_pixel_d_uv, nullptr)) {
      return false;
    }
  } else if (!ProjectNormalized(model_id, params, u, v, pixel)) {
    return false;
  }
  residuals[0] = weight * (pixel[0] - x_px);
  residuals[1] = weight * (pixel[1] - y_px);
  if (!any_jacobian) {
    return true;
  }

  // d(r)/d(X_cam) = weight * d(pixel)/d(u, v) * d(u, v)/d(X_cam)  (2 x 3).
  const double d_uv_d_cam[2][3] = {{inv_z, 0.0, -u * inv_z},
                                   {0.0, inv_z, -v * inv_z}};
  double d_r_d_cam[2][3];
  for (int r = 0; r < 2; ++r) {
    for (int c = 0; c < 3; ++c) {
      d_r_d_cam[r][c] = weight * (d_pixel_d_uv[r][0] * d_uv_d_cam[0][c] +
                                  d_pixel_d_uv[r][1] * d_uv_d_cam[1][c]);
    }
  }
  if (jacobian_t) {
    for (int r = 0; r < 2; ++r) {
      for (int c = 0; c < 3; ++c) jacobian_t[3 * r + c] = d_r_d_cam[r][c];
    }
  }
  if (jacobian_point) {
    // Columns of R(q): the rotated unit vectors.
    double rot[3][3];
    for (int c = 0; c < 3; ++c) {
      double e[3] = {0.0, 0.0, 0.0};
      e[c] = 1.0;
      double col[3];
      RotateByUnitQuaternion(q, e, col);
      for (int r = 0; r < 3; ++r) rot[r][c] = col[r];
    }
    for (int r = 0; r < 2; ++r) {
      for (int c = 0; c < 3; ++c) {
        jacobian_point[3 * r + c] = d_r_d_cam[r][0] * rot[0][c] +
                                    d_r_d_cam[r][1] * rot[1][c] +
                                    d_r_d_cam[r][2] * rot[2][c];
      }
    }
  }
  if (jacobian_q) {
    const double w = q[0];
    const double* vq = q + 1;
    const double* p = point;
    const double v_dot_p = vq[0] * p[0] + vq[1] * p[1] + vq[2] * p[2];
    // d(X_cam)/dq, 3 x 4.
    double d_cam_d_q[3][4];
    // d/dq0 = 2 (v x p).
    d_cam_d_q[0][0] = 2.0 * (vq[1] * p[2] - vq[2] * p[1]);
    d_cam_d_q[1][0] = 2.0 * (vq[2] * p[0] - vq[0] * p[2]);
    d_cam_d_q[2][0] = 2.0 * (vq[0] * p[1] - vq[1] * p[0]);
    // d/dv = -2 w [p]x + 2 ((v.p) I + v p^T - 2 p v^T).
    const double p_cross[3][3] = {
        {0.0, -p[2], p[1]}, {p[2], 0.0, -p[0]}, {-p[1], p[0], 0.0}};
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        d_cam_d_q[r][1 + c] =
            -2.0 * w * p_cross[r][c] +
            2.0 * ((r == c ? v_dot_p : 0.0) + vq[r] * p[c] - 2.0 * p[r] * vq[c]);
      }
    }
    for (int r = 0; r < 2; ++r) {
      for (int c = 0; c < 4; ++c) {
        jacobian_q[4 * r + c] = d_r_d_cam[r][0] * d_cam_d_q[0][c] +
                                d_r_d_cam[r][1] * d_cam_d_q[1][c] +
                                d_r_d_cam[r][2] * d_cam_d_q[2][c];
      }
    }
  }
  return true;
}

}  // namespace colmap_lidar
