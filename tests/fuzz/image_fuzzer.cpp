// libFuzzer target: a stored view as the worker meets it. The input is the
// view's file (side1/view_000.jpg of a one-view sample, whatever its real
// format): ProcessSide decodes it, computes its mask and its 2D figures
// (pipeline/side_job.*), then `aggscan morph2d` reads the same file
// (pipeline/morph2d_cli.*). A library exception escaping either is a crash.
//
// Input size is bounded twice: by -max_len (bytes, set by the run script)
// and by OpenCV's own decoder limits, lowered here to 1 megapixel so that a
// small header claiming a huge picture costs a bounded decode, not the
// fuzzer's memory limit. OpenCV reads those limits once, when the library is
// loaded, so they are set and the process re-executed before any input.
#include <unistd.h>

#include <cstdlib>
#include <sstream>
#include <string>

#include "cli/morph2d_command.h"
#include "common/log.h"
#include "pipeline/worker/side_job.h"
#include "store/layout.h"
#include "tests/fuzz/fuzz_util.h"

namespace {

constexpr const char* kMaxPixels = "1048576";

}  // namespace

extern "C" int LLVMFuzzerInitialize(int* argc, char*** argv) {
  const char* set = std::getenv("OPENCV_IO_MAX_IMAGE_PIXELS");
  if (!set || std::string(set) != kMaxPixels) {
    ::setenv("OPENCV_IO_MAX_IMAGE_PIXELS", kMaxPixels, 1);
    ::setenv("OPENCV_IO_MAX_IMAGE_WIDTH", "65536", 1);
    ::setenv("OPENCV_IO_MAX_IMAGE_HEIGHT", "65536", 1);
    ::execv("/proc/self/exe", *argv);
    std::abort();  // cannot re-execute: running unbounded would only find the memory limit
  }
  (void)argc;
  aggscan::SetLogLevel(
      aggscan::LogLevel::kError);  // a warning per input would bury the fuzzer's output
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  const std::string sample = fuzz::ScratchDir() + "/samples/rock-1";
  fuzz::ResetDir(sample);
  const std::string image = sample + "/side1/" + layout::ViewImageName(0);
  fuzz::WriteFile(image, fuzz::AsView(data, size));
  fuzz::WriteFile(
      sample + "/side1/" + layout::kManifest,
      R"({"sample_id": "rock-1", "side": 1, "views": [{"view": 0, "image": "view_000.jpg"}]})");
  WorkerOptions opts;
  opts.reuse_masks = false;
  Status s = ProcessSide(sample, 1, opts);
  if (!s && s.error().message.empty()) std::abort();  // a failure must say what is wrong
  std::ostringstream out, err;
  (void)RunMorph2dCommand(image, true, out, err);
  return 0;
}
