// Ceres bundle adjustment for colmap-lidar: reprojection residuals through the
// COLMAP camera models (camera_models.h), signed point-to-plane residuals and
// pose priors, built from the flat arrays of BaProblemFfi in one loop.
//
// Conventions: poses are cam_from_world, X_cam = R(q) X_world + t, with the
// quaternion stored w, x, y, z (Ceres' and COLMAP's order). Rotation and
// translation are separate parameter blocks (4 and 3 doubles) pointing into the
// caller's `poses` array, so the solution lands there in place.
//
// Every size and index is checked here again even though Rust validates first:
// a failed glog CHECK inside Ceres would abort the whole process.
#include "colmap-lidar/cpp/bundle_adjustment.h"

#include <ceres/ceres.h>
#include <ceres/rotation.h>
#include <glog/logging.h>

#include <chrono>
#include <cmath>
#include <memory>
#include <mutex>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "camera_models.h"
#include "reprojection.h"
#include "colmap-lidar/src/solver/ffi.rs.h"

namespace colmap_lidar {
namespace {

// Residual family indices shared with Rust (src/solver/bridge.rs).
constexpr uint32_t kFamilyReprojection = 0;
constexpr uint32_t kFamilyPosePrior = 1;

// Linear solver codes shared with Rust.
constexpr int kDenseSchur = 0;
constexpr int kSparseSchur = 1;
constexpr int kIterativeSchur = 2;
constexpr int kDenseQr = 3;
constexpr int kDenseNormalCholesky = 4;
constexpr int kSparseNormalCholesky = 5;

[[noreturn]] void Fail(const std::string& what) {
  throw std::invalid_argument("bundle adjustment: " + what);
}

// Reprojection error of a world point seen by a posed camera:
//   X_cam = R(q) X + t
//   r     = w * (pi_model(K, X_cam) - x_observed)          [pixels * w]
// with Jacobians in closed form (cpp/reprojection.h). Evaluation fails
// (returns false) when the model cannot project X_cam, e.g. a point behind
// the camera; Ceres then rejects the step.
template <int kNumParams>
class ReprojectionCost : public ceres::SizedCostFunction<2, 4, 3, 3, kNumParams> {
 public:
  ReprojectionCost(int model_id, double x_px, double y_px, double weight)
      : model_id_(model_id), x_px_(x_px), y_px_(y_px), weight_(weight) {}

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    return EvaluateReprojection<kNumParams>(
        model_id_, parameters[3], parameters[0], parameters[1], parameters[2],
        x_px_, y_px_, weight_, residuals, jacobians ? jacobians[0] : nullptr,
        jacobians ? jacobians[1] : nullptr, jacobians ? jacobians[2] : nullptr,
        jacobians ? jacobians[3] : nullptr);
  }

 private:
  int model_id_;
  double x_px_;
  double y_px_;
  double weight_;
};

// The same residual with constant intrinsics, Jacobians in closed form
// (cpp/reprojection.h): what most residual blocks of every solve are.
template <int kNumParams>
class ReprojectionConstantCameraCost
    : public ceres::SizedCostFunction<2, 4, 3, 3> {
 public:
  ReprojectionConstantCameraCost(int model_id, const double* params,
                                 double x_px, double y_px, double weight)
      : model_id_(model_id), x_px_(x_px), y_px_(y_px), weight_(weight) {
    for (int k = 0; k < kNumParams; ++k) params_[k] = params[k];
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    return EvaluateReprojection<kNumParams>(
        model_id_, params_, parameters[0], parameters[1], parameters[2], x_px_,
        y_px_, weight_, residuals, jacobians ? jacobians[0] : nullptr,
        jacobians ? jacobians[1] : nullptr, jacobians ? jacobians[2] : nullptr);
  }

 private:
  int model_id_;
  double params_[kNumParams];
  double x_px_;
  double y_px_;
  double weight_;
};

// The same residual for a constant pose and constant intrinsics (most
// observations of a local bundle adjustment): only the point varies.
template <int kNumParams>
class ReprojectionConstantPoseCost : public ceres::SizedCostFunction<2, 3> {
 public:
  ReprojectionConstantPoseCost(int model_id, const double* params,
                               const double* cam_from_world_q,
                               const double* cam_from_world_t, double x_px,
                               double y_px, double weight)
      : model_id_(model_id), x_px_(x_px), y_px_(y_px), weight_(weight) {
    for (int k = 0; k < kNumParams; ++k) params_[k] = params[k];
    for (int k = 0; k < 4; ++k) q_[k] = cam_from_world_q[k];
    for (int k = 0; k < 3; ++k) t_[k] = cam_from_world_t[k];
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    return EvaluateReprojection<kNumParams>(
        model_id_, params_, q_, t_, parameters[0], x_px_, y_px_, weight_,
        residuals, nullptr, nullptr, jacobians ? jacobians[0] : nullptr);
  }

 private:
  int model_id_;
  double params_[kNumParams];
  double q_[4];
  double t_[3];
  double x_px_;
  double y_px_;
  double weight_;
};

// A reprojection residual for a pose and a camera, specialised to what is
// constant: the variables it is added with are `params` (filled here).
template <int kNumParams>
ceres::CostFunction* CreateReprojection(int model_id, double* q, double* t,
                                        double* point, double* intrinsics,
                                        bool pose_constant,
                                        bool camera_constant, double x_px,
                                        double y_px, double weight,
                                        std::vector<double*>* params) {
  if (camera_constant && pose_constant) {
    *params = {point};
    return new ReprojectionConstantPoseCost<kNumParams>(
        model_id, intrinsics, q, t, x_px, y_px, weight);
  }
  if (camera_constant) {
    *params = {q, t, point};
    return new ReprojectionConstantCameraCost<kNumParams>(
        model_id, intrinsics, x_px, y_px, weight);
  }
  *params = {q, t, point, intrinsics};
  return new ReprojectionCost<kNumParams>(model_id, x_px, y_px, weight);
}

// The parameter-block size of the intrinsics is a template argument, so
// dispatch on the models' parameter counts (COLMAP: 3, 4, 5, 8 or 12).
ceres::CostFunction* CreateReprojectionError(
    int model_id, int num_params, double* q, double* t, double* point,
    double* intrinsics, bool pose_constant, bool camera_constant, double x_px,
    double y_px, double weight, std::vector<double*>* params) {
  ceres::CostFunction* cost = nullptr;
  const bool known = WithNumParams(num_params, [&](auto n) {
    cost = CreateReprojection<decltype(n)::value>(
        model_id, q, t, point, intrinsics, pose_constant, camera_constant,
        x_px, y_px, weight, params);
  });
  if (!known) {
    Fail("unsupported number of camera parameters " +
         std::to_string(num_params));
  }
  return cost;
}

// Signed point-to-plane distance, scaled to pixel-equivalents:
//   r = w * (n . X - d)
// Linear in X, so smooth everywhere including on the plane (unlike
// w * sqrt((n . X - d)^2), whose derivative is 0/0 there).
//
// For the solver the residual carries a second row that is always 0
// (kRows = 2): Ceres then sees 2-row residual blocks on every point, as the
// reprojections are, and uses its compiled Schur eliminator for 2-row blocks,
// 3-dimensional points and 3-dimensional pose blocks instead of the generic
// dynamic-size one (measured: the final bundle adjustments of the 100-image
// corridor 26 % faster). The objective, its gradient and every step are
// unchanged. Evaluations and Jacobians handed to Rust use kRows = 1.
template <int kRows>
class PointToPlaneCost : public ceres::SizedCostFunction<kRows, 3> {
 public:
  PointToPlaneCost(const double* normal, double offset_m, double weight)
      : n_{normal[0], normal[1], normal[2]}, offset_m_(offset_m), weight_(weight) {}

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const double* x = parameters[0];
    residuals[0] =
        weight_ * (n_[0] * x[0] + n_[1] * x[1] + n_[2] * x[2] - offset_m_);
    for (int k = 1; k < kRows; ++k) residuals[k] = 0.0;
    if (jacobians && jacobians[0]) {
      for (int c = 0; c < 3; ++c) jacobians[0][c] = weight_ * n_[c];
      for (int c = 3; c < 3 * kRows; ++c) jacobians[0][c] = 0.0;
    }
    return true;
  }

 private:
  double n_[3];
  double offset_m_;
  double weight_;
};

ceres::CostFunction* CreatePointToPlaneError(const double* normal,
                                             double offset_m, double weight,
                                             bool for_solver) {
  if (for_solver) {
    return new PointToPlaneCost<2>(normal, offset_m, weight);
  }
  return new PointToPlaneCost<1>(normal, offset_m, weight);
}

// Prior on a pose's camera centre and orientation:
//   C        = -R(q)^T t                                  (centre in world)
//   r[0..3]  = w_p * (C - C_prior)                        [metres * w_p]
//   r[3..6]  = w_r * AngleAxis(q * conj(q_prior))         [radians * w_r]
// where q and q_prior are cam_from_world rotations.
struct PosePriorError {
  PosePriorError(const double* position_in_world, const double* prior_q,
                 double position_weight, double rotation_weight)
      : position{position_in_world[0], position_in_world[1],
                 position_in_world[2]},
        prior_q_conj{prior_q[0], -prior_q[1], -prior_q[2], -prior_q[3]},
        position_weight(position_weight),
        rotation_weight(rotation_weight) {}

  template <typename T>
  bool operator()(const T* cam_from_world_q, const T* cam_from_world_t,
                  T* residuals) const {
    const T q_conj[4] = {cam_from_world_q[0], -cam_from_world_q[1],
                         -cam_from_world_q[2], -cam_from_world_q[3]};
    T rotated_t[3];
    ceres::UnitQuaternionRotatePoint(q_conj, cam_from_world_t, rotated_t);
    for (int i = 0; i < 3; ++i) {
      residuals[i] = T(position_weight) * (-rotated_t[i] - T(position[i]));
    }
    const T prior_conj[4] = {T(prior_q_conj[0]), T(prior_q_conj[1]),
                             T(prior_q_conj[2]), T(prior_q_conj[3])};
    T q_error[4];
    ceres::QuaternionProduct(cam_from_world_q, prior_conj, q_error);
    T angle_axis[3];
    ceres::QuaternionToAngleAxis(q_error, angle_axis);
    for (int i = 0; i < 3; ++i) {
      residuals[3 + i] = T(rotation_weight) * angle_axis[i];
    }
    return true;
  }

  static ceres::CostFunction* Create(const double* position_in_world,
                                     const double* prior_q,
                                     double position_weight,
                                     double rotation_weight) {
    return new ceres::AutoDiffCostFunction<PosePriorError, 6, 4, 3>(
        new PosePriorError(position_in_world, prior_q, position_weight,
                           rotation_weight));
  }

  double position[3];
  double prior_q_conj[4];
  double position_weight;
  double rotation_weight;
};

struct ResidualRecord {
  uint32_t family;
  ceres::CostFunction* cost;  // owned by the problem
  ceres::LossFunction* loss;  // owned by BuiltProblem::losses (or null)
  std::vector<double*> params;
};

// The Ceres problem plus what it points to. Members are destroyed in reverse
// order, so `problem` goes before the manifolds and losses it borrows.
struct BuiltProblem {
  std::unique_ptr<ceres::Manifold> quaternion_manifold;
  std::vector<std::unique_ptr<ceres::Manifold>> camera_manifolds;
  std::vector<std::unique_ptr<ceres::LossFunction>> losses;  // per family
  std::vector<ResidualRecord> records;  // observations, planes, priors
  std::unique_ptr<ceres::Problem> problem;
  size_t num_families = 0;
  // Parameter blocks in the problem: points (Schur group 0), poses (group
  // 1) and intrinsics (group 2). Ceres orders the blocks of one group by
  // their addresses, and the poses and the intrinsics live in two separate
  // allocations: in one group, whether a camera came before or after the
  // poses changed from run to run, and with it the last bits of a solve.
  std::vector<double*> point_blocks;
  std::vector<double*> pose_blocks;
  std::vector<double*> camera_blocks;
};

std::unique_ptr<ceres::LossFunction> MakeLoss(int kind, double scale,
                                              size_t family) {
  if (kind != 0 && !(std::isfinite(scale) && scale > 0.0)) {
    Fail("loss scale of family " + std::to_string(family) +
         " must be finite and positive");
  }
  switch (kind) {
    case 0:
      return nullptr;
    case 1:
      return std::make_unique<ceres::HuberLoss>(scale);
    case 2:
      return std::make_unique<ceres::SoftLOneLoss>(scale);
    case 3:
      return std::make_unique<ceres::CauchyLoss>(scale);
    default:
      Fail("unknown loss kind " + std::to_string(kind));
  }
}

void CheckSize(size_t actual, size_t expected, const char* name) {
  if (actual != expected) {
    std::ostringstream msg;
    msg << name << " has " << actual << " values, expected " << expected;
    Fail(msg.str());
  }
}

void CheckIndex(uint32_t index, size_t count, const char* what, size_t row) {
  if (index >= count) {
    std::ostringstream msg;
    msg << what << " index " << index << " in row " << row
        << " is out of range (" << count << ")";
    Fail(msg.str());
  }
}

void CheckFinite(const double* values, size_t count, const char* name) {
  for (size_t i = 0; i < count; ++i) {
    if (!std::isfinite(values[i])) {
      std::ostringstream msg;
      msg << name << "[" << i << "] is not finite";
      Fail(msg.str());
    }
  }
}

// Checks sizes, indices and finiteness of everything Ceres will touch.
void CheckProblem(const BaProblemFfi& p, const BaOptionsFfi& o) {
  const size_t num_poses = p.poses.size() / 7;
  CheckSize(p.poses.size(), num_poses * 7, "poses");
  CheckSize(p.pose_constant.size(), num_poses, "pose_constant");
  CheckFinite(p.poses.data(), p.poses.size(), "poses");
  for (size_t i = 0; i < num_poses; ++i) {
    const double* q = &p.poses[7 * i];
    const double norm =
        std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (std::abs(norm - 1.0) > 1e-6) {
      Fail("pose " + std::to_string(i) + " quaternion is not unit");
    }
  }

  const size_t num_cameras = p.camera_model_ids.size();
  CheckSize(p.camera_param_offsets.size(), num_cameras + 1,
            "camera_param_offsets");
  if (p.camera_param_offsets[0] != 0 ||
      p.camera_param_offsets[num_cameras] != p.camera_params.size()) {
    Fail("camera_param_offsets do not span camera_params");
  }
  CheckSize(p.camera_param_constant.size(), p.camera_params.size(),
            "camera_param_constant");
  CheckFinite(p.camera_params.data(), p.camera_params.size(),
              "camera_params");
  for (size_t c = 0; c < num_cameras; ++c) {
    const int expected = NumParams(p.camera_model_ids[c]);
    if (expected < 0) {
      Fail("camera " + std::to_string(c) + " has unknown model id " +
           std::to_string(p.camera_model_ids[c]));
    }
    if (p.camera_param_offsets[c + 1] < p.camera_param_offsets[c] ||
        p.camera_param_offsets[c + 1] - p.camera_param_offsets[c] !=
            static_cast<uint32_t>(expected)) {
      Fail("camera " + std::to_string(c) + " has the wrong parameter count");
    }
  }

  const size_t num_points = p.points.size() / 3;
  CheckSize(p.points.size(), num_points * 3, "points");
  CheckSize(p.point_constant.size(), num_points, "point_constant");
  CheckFinite(p.points.data(), p.points.size(), "points");

  const size_t num_obs = p.obs_pose.size();
  CheckSize(p.obs_camera.size(), num_obs, "obs_camera");
  CheckSize(p.obs_point.size(), num_obs, "obs_point");
  CheckSize(p.obs_pixel.size(), 2 * num_obs, "obs_pixel");
  CheckSize(p.obs_weight.size(), num_obs, "obs_weight");
  CheckFinite(p.obs_pixel.data(), p.obs_pixel.size(), "obs_pixel");
  CheckFinite(p.obs_weight.data(), p.obs_weight.size(), "obs_weight");
  for (size_t i = 0; i < num_obs; ++i) {
    CheckIndex(p.obs_pose[i], num_poses, "observation pose", i);
    CheckIndex(p.obs_camera[i], num_cameras, "observation camera", i);
    CheckIndex(p.obs_point[i], num_points, "observation point", i);
  }

  const size_t num_families = o.loss_kind.size();
  CheckSize(o.loss_scale.size(), num_families, "loss_scale");
  if (num_families < 2) Fail("at least two residual families expected");

  const size_t num_planes = p.plane_point.size();
  CheckSize(p.plane_normal.size(), 3 * num_planes, "plane_normal");
  CheckSize(p.plane_offset.size(), num_planes, "plane_offset");
  CheckSize(p.plane_weight.size(), num_planes, "plane_weight");
  CheckSize(p.plane_family.size(), num_planes, "plane_family");
  CheckFinite(p.plane_normal.data(), p.plane_normal.size(), "plane_normal");
  CheckFinite(p.plane_offset.data(), p.plane_offset.size(), "plane_offset");
  CheckFinite(p.plane_weight.data(), p.plane_weight.size(), "plane_weight");
  for (size_t i = 0; i < num_planes; ++i) {
    CheckIndex(p.plane_point[i], num_points, "plane point", i);
    if (p.plane_family[i] < 2) Fail("plane family index below 2");
    CheckIndex(p.plane_family[i], num_families, "plane family", i);
  }

  const size_t num_priors = p.prior_pose.size();
  CheckSize(p.prior_position.size(), 3 * num_priors, "prior_position");
  CheckSize(p.prior_rotation.size(), 4 * num_priors, "prior_rotation");
  CheckSize(p.prior_position_weight.size(), num_priors,
            "prior_position_weight");
  CheckSize(p.prior_rotation_weight.size(), num_priors,
            "prior_rotation_weight");
  CheckFinite(p.prior_position.data(), p.prior_position.size(),
              "prior_position");
  CheckFinite(p.prior_rotation.data(), p.prior_rotation.size(),
              "prior_rotation");
  CheckFinite(p.prior_position_weight.data(), p.prior_position_weight.size(),
              "prior_position_weight");
  CheckFinite(p.prior_rotation_weight.data(), p.prior_rotation_weight.size(),
              "prior_rotation_weight");
  for (size_t i = 0; i < num_priors; ++i) {
    CheckIndex(p.prior_pose[i], num_poses, "prior pose", i);
  }
}

// Builds the problem in one loop over the residual tables. Parameter blocks
// enter the problem only through residuals, so a pose, camera or point without
// residuals is never touched (and never marked constant, which Ceres would
// reject for an unknown block). `for_solver`: the problem is solved, not
// evaluated for Rust (see PointToPlaneError).
std::unique_ptr<BuiltProblem> BuildProblem(BaProblemFfi& p,
                                           const BaOptionsFfi& o,
                                           bool for_solver) {
  CheckProblem(p, o);
  auto built = std::make_unique<BuiltProblem>();
  built->num_families = o.loss_kind.size();
  for (size_t f = 0; f < built->num_families; ++f) {
    built->losses.push_back(MakeLoss(o.loss_kind[f], o.loss_scale[f], f));
  }
  built->quaternion_manifold = std::make_unique<ceres::QuaternionManifold>();

  ceres::Problem::Options problem_options;
  problem_options.cost_function_ownership = ceres::TAKE_OWNERSHIP;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  built->problem = std::make_unique<ceres::Problem>(problem_options);
  ceres::Problem& problem = *built->problem;

  const size_t num_poses = p.pose_constant.size();
  const size_t num_cameras = p.camera_model_ids.size();
  const size_t num_points = p.point_constant.size();
  std::vector<bool> pose_used(num_poses, false);
  std::vector<bool> camera_used(num_cameras, false);
  std::vector<bool> point_used(num_points, false);

  auto add = [&](uint32_t family, ceres::CostFunction* cost,
                 std::vector<double*> params) {
    ceres::LossFunction* loss = built->losses[family].get();
    problem.AddResidualBlock(cost, loss, params);
    built->records.push_back(ResidualRecord{family, cost, loss, std::move(params)});
  };

  // Cameras whose every intrinsic parameter is constant.
  std::vector<bool> camera_constant(num_cameras, true);
  for (size_t c = 0; c < num_cameras; ++c) {
    for (uint32_t k = p.camera_param_offsets[c];
         k < p.camera_param_offsets[c + 1]; ++k) {
      if (p.camera_param_constant[k] == 0) camera_constant[c] = false;
    }
  }
  for (size_t i = 0; i < p.obs_pose.size(); ++i) {
    const uint32_t pose = p.obs_pose[i];
    const uint32_t cam = p.obs_camera[i];
    const uint32_t point = p.obs_point[i];
    const uint32_t begin = p.camera_param_offsets[cam];
    const int num_params =
        static_cast<int>(p.camera_param_offsets[cam + 1] - begin);
    // Constant poses and intrinsics are held inside the cost function (far
    // cheaper derivatives) and stay out of the problem.
    std::vector<double*> params;
    ceres::CostFunction* cost = CreateReprojectionError(
        p.camera_model_ids[cam], num_params, &p.poses[7 * pose],
        &p.poses[7 * pose + 4], &p.points[3 * point], &p.camera_params[begin],
        p.pose_constant[pose] != 0, camera_constant[cam], p.obs_pixel[2 * i],
        p.obs_pixel[2 * i + 1], p.obs_weight[i], &params);
    const size_t num_blocks = params.size();
    add(kFamilyReprojection, cost, std::move(params));
    point_used[point] = true;
    if (num_blocks >= 3) pose_used[pose] = true;
    if (num_blocks == 4) camera_used[cam] = true;
  }
  for (size_t i = 0; i < p.plane_point.size(); ++i) {
    const uint32_t point = p.plane_point[i];
    add(p.plane_family[i],
        CreatePointToPlaneError(&p.plane_normal[3 * i], p.plane_offset[i],
                                p.plane_weight[i], for_solver),
        {&p.points[3 * point]});
    point_used[point] = true;
  }
  for (size_t i = 0; i < p.prior_pose.size(); ++i) {
    const uint32_t pose = p.prior_pose[i];
    add(kFamilyPosePrior,
        PosePriorError::Create(&p.prior_position[3 * i],
                               &p.prior_rotation[4 * i],
                               p.prior_position_weight[i],
                               p.prior_rotation_weight[i]),
        {&p.poses[7 * pose], &p.poses[7 * pose + 4]});
    pose_used[pose] = true;
  }

  for (size_t i = 0; i < num_poses; ++i) {
    if (!pose_used[i]) continue;
    double* q = &p.poses[7 * i];
    double* t = &p.poses[7 * i + 4];
    built->pose_blocks.push_back(q);
    built->pose_blocks.push_back(t);
    problem.SetManifold(q, built->quaternion_manifold.get());
    if (p.pose_constant[i] != 0) {
      problem.SetParameterBlockConstant(q);
      problem.SetParameterBlockConstant(t);
    }
  }
  for (size_t c = 0; c < num_cameras; ++c) {
    if (!camera_used[c]) continue;
    const uint32_t begin = p.camera_param_offsets[c];
    const int size = static_cast<int>(p.camera_param_offsets[c + 1] - begin);
    std::vector<int> constant;
    for (int k = 0; k < size; ++k) {
      if (p.camera_param_constant[begin + k] != 0) constant.push_back(k);
    }
    double* params = &p.camera_params[begin];
    built->camera_blocks.push_back(params);
    if (static_cast<int>(constant.size()) == size) {
      problem.SetParameterBlockConstant(params);
    } else if (!constant.empty()) {
      built->camera_manifolds.push_back(
          std::make_unique<ceres::SubsetManifold>(size, constant));
      problem.SetManifold(params, built->camera_manifolds.back().get());
    }
  }
  for (size_t i = 0; i < num_points; ++i) {
    if (!point_used[i]) continue;
    built->point_blocks.push_back(&p.points[3 * i]);
    if (p.point_constant[i] != 0) {
      problem.SetParameterBlockConstant(&p.points[3 * i]);
    }
  }
  return built;
}

// Evaluates every residual block directly through its cost function (so a
// failing block gives NaN residuals instead of failing the whole evaluation)
// and sums 0.5 * rho(|r|^2) per family, as Ceres defines the cost.
void EvaluateRecords(const BuiltProblem& built, std::vector<double>* residuals,
                     std::vector<double>* family_cost,
                     std::vector<uint32_t>* family_blocks,
                     uint32_t* num_failed) {
  family_cost->assign(built.num_families, 0.0);
  family_blocks->assign(built.num_families, 0);
  *num_failed = 0;
  if (residuals != nullptr) residuals->clear();
  double r[6];
  for (const ResidualRecord& record : built.records) {
    const int n = record.cost->num_residuals();
    const bool ok = record.cost->Evaluate(record.params.data(), r, nullptr);
    ++(*family_blocks)[record.family];
    if (!ok) {
      ++(*num_failed);
      for (int k = 0; k < n; ++k) r[k] = std::nan("");
    } else {
      double sq = 0.0;
      for (int k = 0; k < n; ++k) sq += r[k] * r[k];
      double rho[3] = {sq, 1.0, 0.0};
      if (record.loss != nullptr) record.loss->Evaluate(sq, rho);
      (*family_cost)[record.family] += 0.5 * rho[0];
    }
    if (residuals != nullptr) residuals->insert(residuals->end(), r, r + n);
  }
}

template <typename T>
rust::Vec<T> ToRustVec(const std::vector<T>& values) {
  rust::Vec<T> out;
  out.reserve(values.size());
  for (const T& v : values) out.push_back(v);
  return out;
}

int LinearSolverCode(ceres::LinearSolverType type) {
  switch (type) {
    case ceres::DENSE_SCHUR:
      return kDenseSchur;
    case ceres::SPARSE_SCHUR:
      return kSparseSchur;
    case ceres::ITERATIVE_SCHUR:
      return kIterativeSchur;
    case ceres::DENSE_QR:
      return kDenseQr;
    case ceres::DENSE_NORMAL_CHOLESKY:
      return kDenseNormalCholesky;
    case ceres::SPARSE_NORMAL_CHOLESKY:
      return kSparseNormalCholesky;
    default:
      return -1;
  }
}

ceres::SparseLinearAlgebraLibraryType AvailableSparseLibrary() {
  for (auto type : {ceres::SUITE_SPARSE, ceres::EIGEN_SPARSE,
                    ceres::CX_SPARSE}) {
    if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(type)) return type;
  }
  Fail("no sparse linear algebra library in this Ceres build");
}

ceres::Solver::Options MakeSolverOptions(const BaOptionsFfi& o,
                                         const BuiltProblem& built) {
  ceres::Solver::Options options;
  options.max_num_iterations = o.max_iterations;
  options.function_tolerance = o.function_tolerance;
  options.gradient_tolerance = o.gradient_tolerance;
  options.parameter_tolerance = o.parameter_tolerance;
  if (o.max_time_s > 0.0) options.max_solver_time_in_seconds = o.max_time_s;
  // An invalid step is one whose linear solve failed numerically or whose
  // model predicts no decrease (round-off near a minimum); each shrinks the
  // trust region, faster at each in a row. Ceres' default of 5 in a row ends
  // the solve in FAILURE, which throws away every step it had accepted; 20
  // lets the region shrink until a step is valid or it reaches its minimum
  // radius, which ends the solve as converged at the last accepted state.
  // (A trial step that puts a point behind a camera is not invalid: the cost
  // functions return false, and Ceres rejects it as a step of infinite cost.)
  options.max_num_consecutive_invalid_steps = 20;
  options.num_threads = o.num_threads;
  options.minimizer_progress_to_stdout = o.logging;
  options.logging_type =
      o.logging ? ceres::PER_MINIMIZER_ITERATION : ceres::SILENT;

  bool schur = false;
  switch (o.linear_solver) {
    case kDenseSchur:
      options.linear_solver_type = ceres::DENSE_SCHUR;
      schur = true;
      break;
    case kSparseSchur:
      options.linear_solver_type = ceres::SPARSE_SCHUR;
      options.sparse_linear_algebra_library_type = AvailableSparseLibrary();
      schur = true;
      break;
    case kIterativeSchur:
      options.linear_solver_type = ceres::ITERATIVE_SCHUR;
      options.preconditioner_type = ceres::SCHUR_JACOBI;
      schur = true;
      break;
    case kDenseQr:
      options.linear_solver_type = ceres::DENSE_QR;
      break;
    case kDenseNormalCholesky:
      options.linear_solver_type = ceres::DENSE_NORMAL_CHOLESKY;
      break;
    case kSparseNormalCholesky:
      options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
      options.sparse_linear_algebra_library_type = AvailableSparseLibrary();
      break;
    default:
      Fail("unknown linear solver code " + std::to_string(o.linear_solver));
  }

  // Schur elimination: points (group 0) first, then poses, then cameras
  // (see BuiltProblem). The ordering must list every parameter block of the
  // problem, constant ones included (Ceres drops those itself).
  if (schur && !built.point_blocks.empty()) {
    auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
    for (double* block : built.point_blocks) {
      ordering->AddElementToGroup(block, 0);
    }
    for (double* block : built.pose_blocks) {
      ordering->AddElementToGroup(block, 1);
    }
    for (double* block : built.camera_blocks) {
      ordering->AddElementToGroup(block, 2);
    }
    options.linear_solver_ordering = ordering;
  }
  return options;
}

void SetLogLevel(bool logging) {
  // Ceres writes through glog: to stderr only, and nothing below FATAL unless
  // asked for (the summary carries Ceres' message anyway).
  static std::once_flag init;
  std::call_once(init, [] {
    FLAGS_logtostderr = true;
    if (!google::IsGoogleLoggingInitialized()) {
      google::InitGoogleLogging("colmap-lidar");
    }
  });
  FLAGS_minloglevel = logging ? google::GLOG_INFO : google::GLOG_FATAL;
}

BaSummaryFfi SolveImpl(BaProblemFfi& p, const BaOptionsFfi& o) {
  if (o.max_iterations < 0 || o.num_threads < 1) {
    Fail("max_iterations must be >= 0 and num_threads >= 1");
  }
  SetLogLevel(o.logging);
  using Clock = std::chrono::steady_clock;
  const auto seconds_since = [](Clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
  };
  BaSummaryFfi out;
  out.preprocessor_time_s = 0.0;
  out.residual_time_s = 0.0;
  out.jacobian_time_s = 0.0;
  out.linear_solver_time_s = 0.0;
  Clock::time_point t = Clock::now();
  std::unique_ptr<BuiltProblem> built = BuildProblem(p, o, true);
  out.build_time_s = seconds_since(t);

  std::vector<double> initial_cost;
  std::vector<double> final_cost;
  std::vector<uint32_t> blocks;
  uint32_t failed = 0;
  t = Clock::now();
  EvaluateRecords(*built, nullptr, &initial_cost, &blocks, &failed);
  out.family_cost_time_s = seconds_since(t);
  out.family_num_blocks = ToRustVec(blocks);
  out.family_initial_cost = ToRustVec(initial_cost);

  if (built->records.empty()) {
    out.initial_cost = 0.0;
    out.final_cost = 0.0;
    out.num_iterations = 0;
    out.termination = 0;
    out.usable = true;
    out.time_s = 0.0;
    out.message = "no residuals: nothing to solve";
    out.linear_solver_used = -1;
    out.family_final_cost = ToRustVec(initial_cost);
    return out;
  }

  ceres::Solver::Options options = MakeSolverOptions(o, *built);
  std::string options_error;
  if (!options.IsValid(&options_error)) {
    Fail("invalid solver options: " + options_error);
  }
  ceres::Solver::Summary summary;
  ceres::Solve(options, built->problem.get(), &summary);

  t = Clock::now();
  EvaluateRecords(*built, nullptr, &final_cost, &blocks, &failed);
  out.family_cost_time_s += seconds_since(t);
  out.preprocessor_time_s = summary.preprocessor_time_in_seconds;
  out.residual_time_s = summary.residual_evaluation_time_in_seconds;
  out.jacobian_time_s = summary.jacobian_evaluation_time_in_seconds;
  out.linear_solver_time_s = summary.linear_solver_time_in_seconds;
  out.schur_structure = summary.schur_structure_used;
  out.family_final_cost = ToRustVec(final_cost);
  out.initial_cost = summary.initial_cost;
  out.final_cost = summary.final_cost;
  out.num_iterations =
      summary.num_successful_steps + summary.num_unsuccessful_steps;
  switch (summary.termination_type) {
    case ceres::CONVERGENCE:
      out.termination = 0;
      break;
    case ceres::NO_CONVERGENCE:
      out.termination = 1;
      break;
    case ceres::FAILURE:
      out.termination = 2;
      break;
    case ceres::USER_SUCCESS:
      out.termination = 3;
      break;
    case ceres::USER_FAILURE:
      out.termination = 4;
      break;
  }
  out.usable = summary.IsSolutionUsable() && std::isfinite(summary.final_cost);
  out.time_s = summary.total_time_in_seconds;
  out.message = summary.message;
  out.linear_solver_used = LinearSolverCode(summary.linear_solver_type_used);
  return out;
}

BaEvaluationFfi EvaluateImpl(BaProblemFfi& p, const BaOptionsFfi& o) {
  std::unique_ptr<BuiltProblem> built = BuildProblem(p, o, false);
  std::vector<double> residuals;
  std::vector<double> cost;
  std::vector<uint32_t> blocks;
  uint32_t failed = 0;
  EvaluateRecords(*built, &residuals, &cost, &blocks, &failed);
  BaEvaluationFfi out;
  out.residuals = ToRustVec(residuals);
  out.family_num_blocks = ToRustVec(blocks);
  out.family_cost = ToRustVec(cost);
  out.num_failed_blocks = failed;
  return out;
}

// Block kinds of the Jacobian's columns, shared with Rust (src/solver/ffi.rs).
constexpr uint32_t kBlockPoint = 0;
constexpr uint32_t kBlockPoseRotation = 1;
constexpr uint32_t kBlockPoseTranslation = 2;
constexpr uint32_t kBlockCamera = 3;

// The Jacobian of every residual with respect to the variable parameter
// blocks (tangent space; points first, then each pose's rotation and
// translation, then intrinsics), with the robust losses' corrections applied
// as the solver sees them, and the corrected residuals.
BaJacobianFfi JacobianImpl(BaProblemFfi& p, const BaOptionsFfi& o) {
  SetLogLevel(o.logging);
  std::unique_ptr<BuiltProblem> built = BuildProblem(p, o, false);
  ceres::Problem& problem = *built->problem;
  BaJacobianFfi out;
  out.num_rows = 0;
  out.num_cols = 0;
  ceres::Problem::EvaluateOptions eval;
  eval.apply_loss_function = true;
  eval.num_threads = 1;
  auto add = [&](double* block, uint32_t kind, size_t index) {
    if (!problem.HasParameterBlock(block) ||
        problem.IsParameterBlockConstant(block)) {
      return;
    }
    eval.parameter_blocks.push_back(block);
    out.block_kind.push_back(kind);
    out.block_index.push_back(static_cast<uint32_t>(index));
    out.block_size.push_back(
        static_cast<uint32_t>(problem.ParameterBlockTangentSize(block)));
  };
  for (size_t i = 0; i < p.point_constant.size(); ++i) {
    add(&p.points[3 * i], kBlockPoint, i);
  }
  for (size_t i = 0; i < p.pose_constant.size(); ++i) {
    add(&p.poses[7 * i], kBlockPoseRotation, i);
    add(&p.poses[7 * i + 4], kBlockPoseTranslation, i);
  }
  for (size_t c = 0; c < p.camera_model_ids.size(); ++c) {
    add(&p.camera_params[p.camera_param_offsets[c]], kBlockCamera, c);
  }
  if (eval.parameter_blocks.empty() || built->records.empty()) return out;
  double cost = 0.0;
  std::vector<double> residuals;
  ceres::CRSMatrix jacobian;
  if (!problem.Evaluate(eval, &cost, &residuals, nullptr, &jacobian)) {
    Fail("the Jacobian could not be evaluated (a point behind a camera?)");
  }
  out.num_rows = static_cast<uint64_t>(jacobian.num_rows);
  out.num_cols = static_cast<uint64_t>(jacobian.num_cols);
  out.row_starts.reserve(jacobian.rows.size());
  for (int r : jacobian.rows) out.row_starts.push_back(static_cast<uint64_t>(r));
  out.cols.reserve(jacobian.cols.size());
  for (int c : jacobian.cols) out.cols.push_back(static_cast<uint32_t>(c));
  out.values = ToRustVec(jacobian.values);
  out.residuals = ToRustVec(residuals);
  return out;
}

// Turns anything thrown into a std::exception, which cxx passes to Rust.
template <typename F>
auto Guard(F&& body) -> decltype(body()) {
  try {
    return body();
  } catch (const std::exception&) {
    throw;
  } catch (...) {
    throw std::runtime_error("bundle adjustment: unknown C++ exception");
  }
}

}  // namespace

BaSummaryFfi solve_bundle_adjustment(BaProblemFfi& problem,
                                     const BaOptionsFfi& options) {
  return Guard([&] { return SolveImpl(problem, options); });
}

BaEvaluationFfi evaluate_bundle_adjustment(BaProblemFfi& problem,
                                           const BaOptionsFfi& options) {
  return Guard([&] { return EvaluateImpl(problem, options); });
}

BaJacobianFfi jacobian_bundle_adjustment(BaProblemFfi& problem,
                                         const BaOptionsFfi& options) {
  return Guard([&] { return JacobianImpl(problem, options); });
}

bool sparse_linear_algebra_available() {
  for (auto type : {ceres::SUITE_SPARSE, ceres::EIGEN_SPARSE,
                    ceres::CX_SPARSE}) {
    if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(type)) return true;
  }
  return false;
}

}  // namespace colmap_lidar
