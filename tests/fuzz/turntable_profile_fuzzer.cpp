// libFuzzer target: a turntable register-map profile through ParseTurntableProfile.
#include <cstdlib>
#include <string>

#include "config/turntable_profile.h"
#include "tests/fuzz/fuzz_util.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  Result<TurntableProfile> p =
      ParseTurntableProfile(std::string(fuzz::AsView(data, size)), "fuzz.toml");
  if (!p && p.error().message.empty()) std::abort();  // refused without saying why
  return 0;
}
