// libFuzzer target: the JSON files the worker reads back from a sample
// directory (pipeline/side_job.*): the input is side 1's manifest, view 0's
// sidecar and an existing side 2 result (results/side2_morph2d.json),
// separated by kSeparator. Side 1's three views are small valid JPEGs
// (synthetic_view.h). ProcessSide reads the manifest and the sidecar,
// ProcessSample the side results; the poses stage's checks of a side result
// (SideHasEnoughWholeViews, CheckSideMasks) run on side 2's.
#include <cstdlib>
#include <nlohmann/json.hpp>
#include <string>

#include "common/log.h"
#include "pipeline/worker/side_job.h"
#include "store/layout.h"
#include "tests/fuzz/fuzz_util.h"
#include "tests/fuzz/synthetic_view.h"

namespace {

constexpr std::string_view kSeparator = "\n----\n";
std::string g_view_jpeg;

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  aggscan::SetLogLevel(
      aggscan::LogLevel::kError);  // a warning per input would bury the fuzzer's output
  const auto jpeg = aggscan::fuzz::SyntheticViewJpeg(64, 48, 1);
  g_view_jpeg.assign(jpeg.begin(), jpeg.end());
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  using nlohmann::json;
  const auto parts = fuzz::SplitInput(fuzz::AsView(data, size), kSeparator, 3);
  const std::string sample = fuzz::ScratchDir() + "/samples/rock-1";
  fuzz::ResetDir(sample);
  for (int v = 0; v < 3; ++v)
    fuzz::WriteFile(sample + "/side1/" + layout::ViewImageName(v), g_view_jpeg);
  fuzz::WriteFile(sample + "/side1/" + layout::kManifest, parts[0]);
  if (parts.size() > 1) fuzz::WriteFile(sample + "/side1/" + layout::ViewSidecarName(0), parts[1]);
  fuzz::ResetDir(sample + "/side2");
  if (parts.size() > 2) fuzz::WriteFile(SideResultPath(sample, 2), parts[2]);

  WorkerOptions opts;
  opts.reuse_masks = false;
  Status s = ProcessSide(sample, 1, opts);
  if (!s && s.error().message.empty()) std::abort();  // a failure must say what is wrong
  s = ProcessSample(sample, opts);
  if (!s && s.error().message.empty()) std::abort();
  if (parts.size() > 2) {
    json side2 = json::parse(parts[2], nullptr, false);
    auto r = records::SideResult::FromJson(side2, {"side result", "side2", ""});
    if (!r && r.error().message.empty()) std::abort();
    if (r) {
      (void)SideHasEnoughWholeViews(*r);
      (void)CheckSideMasks(&r->views);
      // What was read writes back and reads again as the same record.
      auto again = records::SideResult::FromJson(r->ToJson(), {"side result", "side2", ""});
      if (!again || again->ToJson() != r->ToJson()) std::abort();
    }
  }
  return 0;
}
