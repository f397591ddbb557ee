#include "pipeline/core/stage.h"

#include <algorithm>
#include <mutex>
#include <new>
#include <opencv2/core.hpp>
#include <stdexcept>
#include <thread>
#include <vector>

namespace aggscan {
namespace {

struct Frame {
  std::string name;
  std::thread::id thread;
  bool concurrent = false;
  int done = 0;
  int total = 0;  // 0: this stage reported no progress
};

struct StageState {
  std::mutex mu;
  std::vector<Frame> stack;
  std::string threw_in;  // innermost stage an exception unwound through
  StageObserver observer = nullptr;
};

StageState& State() {
  static StageState* s = new StageState;  // never destroyed: stages may end during exit
  return *s;
}

// The innermost stage: the last frame, or the run of concurrent frames at
// the top of the stack.
std::string Innermost(const StageState& s) {
  if (s.stack.empty()) return {};
  auto first = s.stack.end() - 1;
  if (first->concurrent)
    while (first != s.stack.begin() && (first - 1)->concurrent) --first;
  std::string name;
  for (auto f = first; f != s.stack.end(); ++f) name += (name.empty() ? "" : " & ") + f->name;
  return name;
}

void Notify(StageState& s) {
  if (!s.observer) return;
  int done = 0, total = 0;
  for (auto f = s.stack.rbegin(); f != s.stack.rend(); ++f) {
    if (f->total > 0) {
      done = f->done;
      total = f->total;
      break;
    }
  }
  s.observer(Innermost(s).c_str(), done, total);
}

}  // namespace

void SetStageObserver(StageObserver observer) {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  s.observer = observer;
}

std::string CurrentStage() {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  return Innermost(s);
}

std::string ThreadStage() {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  const auto me = std::this_thread::get_id();
  auto own = std::find_if(s.stack.rbegin(), s.stack.rend(),
                          [&](const Frame& x) { return x.thread == me; });
  if (own != s.stack.rend()) return own->name;
  auto outer =
      std::find_if(s.stack.rbegin(), s.stack.rend(), [](const Frame& x) { return !x.concurrent; });
  return outer != s.stack.rend() ? outer->name : std::string();
}

void StageLog(LogLevel level, const char* category, const std::string& sample_id,
              const std::string& text) {
  const std::string stage = ThreadStage();
  LogLine(level, category, sample_id, stage.empty() ? text : stage + ": " + text);
}

void ReportStageProgress(int done, int total) {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  auto f =
      std::find_if(s.stack.rbegin(), s.stack.rend(), [](const Frame& x) { return !x.concurrent; });
  if (f == s.stack.rend()) return;
  f->done = std::max(0, std::min(done, total));
  f->total = std::max(0, total);
  Notify(s);
}

StageScope::StageScope(std::string name, bool concurrent) : uncaught_(std::uncaught_exceptions()) {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  if (!concurrent) s.threw_in.clear();  // a stage starting means nothing is unwinding
  s.stack.push_back(Frame{std::move(name), std::this_thread::get_id(), concurrent});
  Notify(s);
}

StageScope::~StageScope() {
  StageState& s = State();
  std::lock_guard<std::mutex> lock(s.mu);
  // This thread's innermost frame: with concurrent stages it need not be the
  // last one.
  const auto me = std::this_thread::get_id();
  auto f = std::find_if(s.stack.rbegin(), s.stack.rend(),
                        [&](const Frame& x) { return x.thread == me; });
  if (f == s.stack.rend()) return;
  if (std::uncaught_exceptions() > uncaught_ && s.threw_in.empty()) s.threw_in = f->name;
  s.stack.erase(std::next(f).base());
  Notify(s);
}

Error StageExceptionError(const std::string& stage, const std::exception_ptr& e) {
  std::string where = stage;
  {
    StageState& s = State();
    std::lock_guard<std::mutex> lock(s.mu);
    if (!s.threw_in.empty()) where = s.threw_in;
    s.threw_in.clear();
  }
  const std::string head = "stage \"" + where + "\" failed: ";
  try {
    std::rethrow_exception(e);
  } catch (const cv::Exception& x) {
    // OpenCV asserts on what it cannot use (a 1x1 or 0-byte photo, a mask of
    // another size): the input of this stage, not the code, is the suspect.
    return MakeError(
        ErrorClass::kCorrupt,
        head + "OpenCV refused its data (" + x.func + ": " + x.err +
            "); a photo or mask of this stage is probably corrupt, truncated or of an unusable "
            "size: "
            "check that stage's files, replace or re-capture them, then retry the sample",
        x.what());
  } catch (const std::bad_alloc& x) {
    return MakeError(
        ErrorClass::kInternal,
        head + "out of memory (" + x.what() +
            "); an input file may declare absurd sizes, or the machine has too little free memory: "
            "check the stage's files and the free memory, then retry the sample",
        x.what());
  } catch (const std::length_error& x) {
    return MakeError(
        ErrorClass::kCorrupt,
        head + "a size out of range (" + std::string(x.what()) +
            "); an input file probably declares an absurd count: check the stage's files, replace "
            "or re-capture them, then retry the sample",
        x.what());
  } catch (const std::exception& x) {
    return MakeError(
        ErrorClass::kInternal,
        head + "unexpected library error (" + std::string(x.what()) +
            "); check the stage's input files; if they are sound, report it with the sample, then "
            "retry the sample",
        x.what());
  } catch (...) {
    return MakeError(ErrorClass::kInternal,
                     head + "unknown exception; report it with the sample, then retry the sample");
  }
}

}  // namespace aggscan
