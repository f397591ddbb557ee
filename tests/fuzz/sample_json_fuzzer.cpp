// libFuzzer target: the JSON files of a sample directory as the store reads
// them (store/sample_store.*): the input is the sample record, a view's
// sidecar and the state directory's rig calibration, separated by
// kSeparator. Every reader of the daemon and the CLI runs on them: LoadRecord,
// Describe, List, CapturedWork, PrepareArm, Recover and a resume.
#include <cstdlib>
#include <string>

#include "common/rig_calibration.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/fuzz/fuzz_util.h"

namespace {

constexpr std::string_view kSeparator = "\n----\n";
constexpr const char* kId = "rock-1";

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  const auto parts = fuzz::SplitInput(fuzz::AsView(data, size), kSeparator, 3);
  const std::string state = fuzz::ScratchDir() + "/state";
  fuzz::ResetDir(state);
  const std::string dir = layout::SampleDir(state, kId);
  fuzz::WriteFile(dir + "/" + layout::kSampleRecord, parts[0]);
  fuzz::WriteFile(dir + "/side1/" + layout::ViewImageName(0), "\xff\xd8\xff\xd9");
  if (parts.size() > 1) fuzz::WriteFile(dir + "/side1/" + layout::ViewSidecarName(0), parts[1]);
  if (parts.size() > 2) fuzz::WriteFile(CalibrationPath(state), parts[2]);
  fuzz::WriteFile(dir + "/side2.interrupted-1/" + layout::ViewImageName(0), "\xff\xd8\xff\xd9");

  SampleStore store(state);
  (void)store.LoadRecord(kId);
  if (auto d = store.Describe(kId)) (void)d->dump();
  if (auto l = store.List()) (void)l->dump();
  (void)store.CapturedWork();
  (void)LoadCalibration(CalibrationPath(state));
  const SamplePlan plan;
  if (store.PrepareArm(kId, plan)) (void)store.CreateOrResume(kId, plan, "[daemon]\n");
  if (auto r = store.Recover(); !r) {
    if (r.error().message.empty()) std::abort();
  }
  // What the daemon reads after a recovery.
  (void)store.LoadRecord(kId);
  (void)store.CapturedWork();
  return 0;
}
