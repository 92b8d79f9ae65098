// Standalone check of cpp/camera_models.h under Ceres autodiff (ceres::Jet):
// for every model, at points on the optical axis (r = 0), near it, at the
// series threshold and far off it, the Jet derivatives with respect to every
// parameter and point coordinate must be finite and match central finite
// differences, and the Jet values must equal the double evaluation exactly.
//
// Then the closed-form reprojection Jacobians of cpp/reprojection.h must
// equal Ceres autodiff (10 dual parts: q, t, X) of the same residual for every
// model, at several poses and points, to 1e-9 relative; so must the Jacobian
// with respect to the intrinsics, and the fixed-intrinsics path and every
// subset of the Jacobians must give the same values bit for bit.
//
// Not part of the library: tests/camera_models.rs compiles and runs it
// (header-only: needs Eigen and the Ceres headers, no linking).
// Exit code 0 when every check passes; prints each failure.
#include <ceres/jet.h>

#include <cmath>
#include <cstdio>

#include "camera_models.h"
#include "reprojection.h"

namespace {

constexpr int kMaxParams = 12;
constexpr int kNumDerivs = kMaxParams + 3;
using Jet = ceres::Jet<double, kNumDerivs>;

struct Case {
  int model_id;
  double params[kMaxParams];
};

// Realistic parameters with strong distortion, plus FOV at omega = 0.
const Case kCases[] = {
    {colmap_lidar::kSimplePinhole, {1000, 960, 540}},
    {colmap_lidar::kPinhole, {1000, 1010, 955, 545}},
    {colmap_lidar::kSimpleRadial, {1400, 960, 540, -0.15}},
    {colmap_lidar::kRadial, {1400, 958, 541, -0.2, 0.05}},
    {colmap_lidar::kOpenCv, {1400, 1390, 962, 538, -0.25, 0.08, 0.001, -0.0015}},
    {colmap_lidar::kOpenCvFisheye, {800, 801, 960, 540, 0.05, -0.02, 0.01, -0.002}},
    {colmap_lidar::kFullOpenCv,
     {1400, 1390, 962, 538, -0.25, 0.08, 0.001, -0.0015, 0.01, 0.05, 0.01, 0.001}},
    {colmap_lidar::kFov, {800, 805, 960, 540, 0.9}},
    {colmap_lidar::kFov, {800, 805, 960, 540, 0.0}},
    {colmap_lidar::kSimpleRadialFisheye, {800, 960, 540, 0.04}},
    {colmap_lidar::kRadialFisheye, {800, 960, 540, 0.04, -0.01}},
    {colmap_lidar::kThinPrismFisheye,
     {800, 805, 960, 540, 0.05, -0.02, 0.001, -0.0015, 0.01, -0.002, 0.0008, -0.0006}},
};

// Normalised radii to test along the direction (0.6, 0.8): the axis, tiny, the
// series threshold (r^2 = 1e-4), typical and wide.
const double kRadii[] = {0.0, 1e-12, 1e-5, 0.01, 0.0101, 0.3, 1.2};

// EvaluateReprojection for the model's parameter count.
bool EvaluateAnyModel(int num_params, int model_id, const double* params, const double* q,
                      const double* t, const double* point, double x_px, double y_px,
                      double weight, double* residuals, double* jq, double* jt, double* jx,
                      double* jp) {
  bool ok = false;
  const bool known = colmap_lidar::WithNumParams(num_params, [&](auto n) {
    ok = colmap_lidar::EvaluateReprojection<decltype(n)::value>(
        model_id, params, q, t, point, x_px, y_px, weight, residuals, jq, jt, jx, jp);
  });
  return known && ok;
}

}  // namespace

int main() {
  int failures = 0;
  int checks = 0;
  for (const Case& c : kCases) {
    const int num_params = colmap_lidar::NumParams(c.model_id);
    for (const double r : kRadii) {
      const double depth = 2.5;
      const double point[3] = {0.6 * r * depth, 0.8 * r * depth, depth};

      Jet params_jet[kMaxParams];
      for (int i = 0; i < num_params; ++i) params_jet[i] = Jet(c.params[i], i);
      Jet point_jet[3];
      for (int i = 0; i < 3; ++i) point_jet[i] = Jet(point[i], kMaxParams + i);
      Jet pixel_jet[2];
      double pixel[2];
      if (!colmap_lidar::ProjectPoint(c.model_id, params_jet, point_jet, pixel_jet) ||
          !colmap_lidar::ProjectPoint(c.model_id, c.params, point, pixel)) {
        std::printf("model %d r %g: ProjectPoint failed\n", c.model_id, r);
        ++failures;
        continue;
      }
      for (int k = 0; k < 2; ++k) {
        if (pixel_jet[k].a != pixel[k]) {
          std::printf("model %d r %g: Jet value %.17g != double %.17g\n", c.model_id, r,
                      pixel_jet[k].a, pixel[k]);
          ++failures;
        }
      }
      for (int d = 0; d < kNumDerivs; ++d) {
        if (d >= num_params && d < kMaxParams) continue;
        double params_fd[kMaxParams];
        double point_fd[3];
        for (int i = 0; i < kMaxParams; ++i) params_fd[i] = c.params[i];
        for (int i = 0; i < 3; ++i) point_fd[i] = point[i];
        double* value = d < kMaxParams ? &params_fd[d] : &point_fd[d - kMaxParams];
        const double original = *value;
        const double step = 1e-6 * (1.0 + std::fabs(original));
        double plus[2], minus[2];
        *value = original + step;
        colmap_lidar::ProjectPoint(c.model_id, params_fd, point_fd, plus);
        *value = original - step;
        colmap_lidar::ProjectPoint(c.model_id, params_fd, point_fd, minus);
        for (int k = 0; k < 2; ++k) {
          ++checks;
          const double numeric = (plus[k] - minus[k]) / (2.0 * step);
          const double analytic = pixel_jet[k].v[d];
          if (!std::isfinite(analytic) ||
              std::fabs(analytic - numeric) > 1e-5 * (1.0 + std::fabs(numeric))) {
            std::printf("model %d r %g d/d[%d] pixel[%d]: autodiff %.10g, numeric %.10g\n",
                        c.model_id, r, d, k, analytic, numeric);
            ++failures;
          }
        }
      }
    }
  }
  // Closed-form reprojection Jacobians against autodiff.
  using JetAll = ceres::Jet<double, 10 + kMaxParams>;  // q, t, X, intrinsics
  // Unit quaternions (w, x, y, z), translations and world points.
  const double kQuats[][4] = {{1.0, 0.0, 0.0, 0.0},
                              {0.5895669440180283, 0.5829223938223662,
                               -0.3970109212869718, 0.39369357332894744},
                              {0.2, -0.4, 0.6, 0.66332495807107994}};
  const double kTrans[][3] = {{0.0, 0.0, 0.0}, {-1.07, 1.55, -1.72}, {500000.0, -4400000.0, 200.0}};
  for (const Case& c : kCases) {
    const int num_params = colmap_lidar::NumParams(c.model_id);
    for (int qi = 0; qi < 3; ++qi) {
      for (int ti = 0; ti < 3; ++ti) {
        const double* q = kQuats[qi];
        const double* t = kTrans[ti];
        // A world point 3 m in front of the camera, off the axis.
        const double in_cam[3] = {0.7, -0.4, 3.0};
        double shifted[3] = {in_cam[0] - t[0], in_cam[1] - t[1], in_cam[2] - t[2]};
        const double q_inv[4] = {q[0], -q[1], -q[2], -q[3]};
        double point[3];
        colmap_lidar::RotateByUnitQuaternion(q_inv, shifted, point);
        const double x_px = 612.25, y_px = 401.5, weight = 0.8;

        double residuals[2], jq[8], jt[6], jx[6], jp[2 * kMaxParams];
        const bool ok = EvaluateAnyModel(num_params, c.model_id, c.params, q, t, point, x_px,
                                         y_px, weight, residuals, jq, jt, jx, jp);
        // Without the intrinsics' Jacobian (the fixed-camera Jet path), and
        // any subset of the others (Ceres passes null for constant blocks):
        // bit for bit the values of the call above, which is compared with
        // autodiff below.
        double residuals_fixed[2], jq_fixed[8], jt_fixed[6], jx_fixed[6];
        double residuals_point[2], jx_point[6], residuals_pose[2], jq_pose[8], jt_pose[6];
        const bool ok_fixed =
            EvaluateAnyModel(num_params, c.model_id, c.params, q, t, point, x_px, y_px, weight,
                             residuals_fixed, jq_fixed, jt_fixed, jx_fixed, nullptr) &&
            EvaluateAnyModel(num_params, c.model_id, c.params, q, t, point, x_px, y_px, weight,
                             residuals_point, nullptr, nullptr, jx_point, nullptr) &&
            EvaluateAnyModel(num_params, c.model_id, c.params, q, t, point, x_px, y_px, weight,
                             residuals_pose, jq_pose, jt_pose, nullptr, nullptr);
        for (int k = 0; ok && k < 8; ++k) {
          const bool same =
              ok_fixed && jq_fixed[k] == jq[k] && jq_pose[k] == jq[k] &&
              (k >= 6 || (jt_fixed[k] == jt[k] && jt_pose[k] == jt[k] && jx_fixed[k] == jx[k] &&
                          jx_point[k] == jx[k])) &&
              (k >= 2 || (residuals_fixed[k] == residuals[k] &&
                          residuals_point[k] == residuals[k] && residuals_pose[k] == residuals[k]));
          ++checks;
          if (!same) {
            std::printf("model %d pose %d/%d: value %d differs without the intrinsics' Jacobian "
                        "or for a subset of the Jacobians\n",
                        c.model_id, qi, ti, k);
            ++failures;
          }
        }
        // Autodiff of the same composition.
        JetAll qj[4], tj[3], xj[3], params_jet[kMaxParams];
        for (int i = 0; i < 4; ++i) qj[i] = JetAll(q[i], i);
        for (int i = 0; i < 3; ++i) tj[i] = JetAll(t[i], 4 + i);
        for (int i = 0; i < 3; ++i) xj[i] = JetAll(point[i], 7 + i);
        for (int i = 0; i < kMaxParams; ++i) params_jet[i] = JetAll(c.params[i], 10 + i);
        JetAll cam[3], pixel_jet[2];
        colmap_lidar::RotateByUnitQuaternion(qj, xj, cam);
        for (int i = 0; i < 3; ++i) cam[i] += tj[i];
        if (!ok || !colmap_lidar::ProjectPoint(c.model_id, params_jet, cam, pixel_jet)) {
          std::printf("model %d pose %d/%d: reprojection failed\n", c.model_id, qi, ti);
          ++failures;
          continue;
        }
        for (int r = 0; r < 2; ++r) {
          const double expected_residual =
              weight * (pixel_jet[r].a - (r == 0 ? x_px : y_px));
          ++checks;
          if (std::fabs(residuals[r] - expected_residual) > 1e-9 * (1.0 + std::fabs(expected_residual))) {
            std::printf("model %d pose %d/%d residual[%d]: closed form %.17g, autodiff %.17g\n",
                        c.model_id, qi, ti, r, residuals[r], expected_residual);
            ++failures;
          }
          for (int d = 0; d < 10 + num_params; ++d) {
            const double closed = d < 4    ? jq[4 * r + d]
                                  : d < 7  ? jt[3 * r + d - 4]
                                  : d < 10 ? jx[3 * r + d - 7]
                                           : jp[num_params * r + d - 10];
            const double autodiff = weight * pixel_jet[r].v[d];
            ++checks;
            if (!(std::fabs(closed - autodiff) <= 1e-9 * (1.0 + std::fabs(autodiff)))) {
              std::printf("model %d pose %d/%d d r[%d] / d[%d]: closed form %.17g, autodiff %.17g\n",
                          c.model_id, qi, ti, r, d, closed, autodiff);
              ++failures;
            }
          }
        }
      }
    }
  }
  std::printf("%d derivative checks, %d failures\n", checks, failures);
  return failures == 0 ? 0 : 1;
}
