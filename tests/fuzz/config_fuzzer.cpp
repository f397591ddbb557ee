// libFuzzer target: a config file through LoadConfigString (TOML, profile,
// validation). A config that loads must print (ConfigToToml) as TOML that
// loads again to the same config, as --print-config promises.
#include <cstdlib>
#include <string>
#include <vector>

#include "config/config.h"
#include "tests/fuzz/fuzz_util.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  std::vector<ConfigProblem> problems;
  Result<Config> c =
      LoadConfigString(std::string(fuzz::AsView(data, size)), "fuzz.toml", &problems);
  if (!c) {
    if (problems.empty()) std::abort();  // refused without saying why
    return 0;
  }
  const std::string printed = ConfigToToml(*c);
  std::vector<ConfigProblem> again;
  Result<Config> c2 = LoadConfigString(printed, "printed.toml", &again);
  if (!c2 || ConfigToToml(*c2) != printed) std::abort();  // --print-config does not round-trip
  return 0;
}
