// Runs one fuzz target's LLVMFuzzerTestOneInput on every file of the folders
// given (its committed corpus: the seeds and every input a fuzzing run kept),
// without libFuzzer, in the regular build: a parser change that crashes,
// hangs or throws on an input the fuzzers already know fails the test suite
// at once. Finding new inputs is scripts/run-fuzzers.sh's (clang, libFuzzer,
// sanitizers); this only replays.
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);
// Optional in a target (the image target bounds OpenCV's decoder there).
extern "C" __attribute__((weak)) int LLVMFuzzerInitialize(int* argc, char*** argv);

int main(int argc, char** argv) {
  if (LLVMFuzzerInitialize != nullptr) LLVMFuzzerInitialize(&argc, &argv);
  std::vector<std::filesystem::path> inputs;
  for (int i = 1; i < argc; ++i) {
    std::error_code ec;
    for (const auto& e : std::filesystem::recursive_directory_iterator(argv[i], ec))
      if (e.is_regular_file()) inputs.push_back(e.path());
    if (ec) {
      std::fprintf(stderr, "fuzz replay: cannot read the corpus %s: %s\n", argv[i],
                   ec.message().c_str());
      return 2;
    }
  }
  std::sort(inputs.begin(), inputs.end());
  if (inputs.empty()) {
    std::fprintf(stderr, "fuzz replay: no input in the corpus folders given\n");
    return 2;
  }
  for (const auto& p : inputs) {
    std::ifstream f(p, std::ios::binary);
    const std::string bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
    // Named before it runs: a crash leaves the culprit as the last line.
    std::fprintf(stderr, "fuzz replay: %s (%zu bytes)\n", p.c_str(), bytes.size());
    LLVMFuzzerTestOneInput(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
  }
  std::printf("fuzz replay: %zu inputs, none crashed\n", inputs.size());
  return 0;
}
