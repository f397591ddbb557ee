#include "pipeline/core/pose.h"

#include <cmath>

namespace aggscan {

using nlohmann::json;

json PoseToJson(const Pose& T) {
  json a = json::array();
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) a.push_back(T.matrix()(r, c));
  return a;
}

Result<Pose> PoseFromJson(const json& j, const char* key, const jsonio::Source& src) {
  const std::string name = std::string("\"") + key + "\"";
  if (!j.is_array() || j.size() != 16)
    return src.Bad(name + " is not a 4x4 matrix (16 numbers, row-major)");
  Eigen::Matrix4d m;
  for (int i = 0; i < 16; ++i) {
    const json& e = j[static_cast<size_t>(i)];
    if (!e.is_number() || !std::isfinite(e.get<double>()))
      return src.Bad(name + " is not a 4x4 matrix (16 numbers, row-major)");
    m(i / 4, i % 4) = e.get<double>();
  }
  if ((m.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff() > 1e-9)
    return src.Bad(name + " is not a rigid transform (its last row is not 0 0 0 1)");
  const Eigen::Matrix3d R = m.topLeftCorner<3, 3>();
  if ((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > 1e-6 ||
      R.determinant() < 0)
    return src.Bad(name + " is not a rigid transform (its 3x3 part is not a rotation)");
  Pose T = Pose::Identity();
  T.linear() = R;
  T.translation() = m.topRightCorner<3, 1>();
  return T;
}

Result<Pose> PoseField(const json& j, const char* key, const jsonio::Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(std::string("\"") + key + "\" is missing");
  return PoseFromJson(j[key], key, src);
}

Pose ToPose(const geom::Rigid3& r) {
  Pose T = Pose::Identity();
  T.linear() = r.R;
  T.translation() = r.t;
  return T;
}

geom::Rigid3 ToRigid3(const Pose& T) { return {T.linear(), T.translation()}; }

}  // namespace aggscan
