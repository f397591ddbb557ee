#include "pipeline/stitch_stage.h"

#include <chrono>

namespace aggscan {

using nlohmann::json;

namespace {

json IsoJson(const Eigen::Isometry3d& T) {
  json a = json::array();
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) a.push_back(T.matrix()(r, c));
  return a;
}

}  // namespace

Result<json> RunStitchStage(const StitchStageInput& in) {
  const auto t0 = std::chrono::steady_clock::now();
  if (in.views.empty()) return MakeError(ErrorClass::kInvalidArgument, "stitch stage: no sides");
  if (in.views.size() == 1) {
    const int side = in.views.begin()->first;
    return json{{"method", "single-side"},
                {"sides", json::array({{{"side", side}, {"table_from_object_4x4", IsoJson(Eigen::Isometry3d::Identity())}}})},
                {"rms_mm", nullptr},
                {"max_mm", nullptr},
                {"stage_seconds", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()}};
  }
  // The marker/feature stitching (issue 3 item 5) is being integrated; until
  // then only one-side samples reconstruct, and a two-side sample says so.
  return MakeError(ErrorClass::kInvalidState,
                   "stitch stage: this build reconstructs one side only; stitching " +
                       std::to_string(in.views.size()) + " sides by the object markers is not in this build yet");
}

}  // namespace aggscan
