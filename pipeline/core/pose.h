// The pose type of the worker's records and of every view handed between
// stages: a rigid transform in millimetres, named target_from_source
// (cam_from_table maps turntable points into the camera). On disk it is the
// row-major homogeneous 4x4 matrix, 16 numbers, under a key ending "_4x4".
//
// geom::Rigid3 (geometry.h) is the same transform for the marker and stitch
// algebra; ToPose / ToRigid3 convert without loss.
#pragma once

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/json_io.h"
#include "pipeline/core/geometry.h"

namespace aggscan {

using Pose = Eigen::Isometry3d;

/// The 16 numbers, row-major.
nlohmann::json PoseToJson(const Pose& T);

/// A pose from 16 row-major numbers; kCorrupt (through `src`, naming `key`)
/// when it is not 16 finite numbers, its last row is not 0 0 0 1 or its 3x3
/// part is not a rotation (to 1e-6: a hand edit or a damaged file).
Result<Pose> PoseFromJson(const nlohmann::json& j, const char* key, const jsonio::Source& src);

/// j[key] read as a pose (kCorrupt naming the key when absent).
Result<Pose> PoseField(const nlohmann::json& j, const char* key, const jsonio::Source& src);

Pose ToPose(const geom::Rigid3& r);
geom::Rigid3 ToRigid3(const Pose& T);

}  // namespace aggscan
