// Stage boundaries of the reconstruction: every stage runs through RunStage,
// which names the stage for whoever watches the worker (the job supervisor
// reads the stage a crashed job was in) and turns whatever the libraries
// throw (cv::Exception, std::bad_alloc, std::length_error, Ceres and Eigen
// through std::exception, anything else) into an Error naming the stage, the
// library's message and what to do. Inside a stage, errors stay values; no
// try/catch is needed around each library call.
#pragma once

#include <exception>
#include <string>
#include <type_traits>
#include <utility>

#include "common/error.h"
#include "common/log.h"

namespace aggscan {

/// Called with the innermost running stage ("" when none) and the progress
/// of the innermost stage that reported one (`done` of `total` units; 0 of 0
/// when none did) each time a stage starts or ends or reports progress. Runs
/// on the stage's thread, so it must be cheap; it must not throw. nullptr:
/// none (the default).
using StageObserver = void (*)(const char* stage, int done, int total);
void SetStageObserver(StageObserver observer);

/// The innermost running stage ("" outside any), e.g. "masks side 1 view 7"
/// (concurrent stages: all of them, see StageScope).
std::string CurrentStage();

/// The stage the calling thread is in: the innermost it opened itself, or, on
/// a thread that opened none (a parallel loop's helper), the innermost that
/// is not one of several concurrent ones; "" outside any.
std::string ThreadStage();

/// LogLine with the calling thread's stage before the text ("[S-1] stitch:
/// ..."): the lines a stage writes itself say which stage wrote them.
void StageLog(LogLevel level, const char* category, const std::string& sample_id,
              const std::string& text);

/// The innermost running stage that is not one of several concurrent ones
/// has done `done` of its `total` units (views,
/// sub-stages). Kept by that stage until it ends, so the stages nested in it
/// show its progress ("masks side 1 view 7" shows 6 of 30 views done).
void ReportStageProgress(int done, int total);

/// Marks a stage for its lifetime (nested stages name the innermost). When an
/// exception unwinds through it, it remembers itself as the stage that threw
/// (RunStage reports that one, not the outermost).
///
/// Stages that run side by side on several threads (the views of a side) are
/// `concurrent`: while more than one runs, the innermost stage is all of them,
/// joined by " & " in the order they started ("masks side 1 view 6 & masks
/// side 1 view 7"), so a crash names every view that was in flight, never a
/// guess. Progress reported inside them goes to the stage around them.
class StageScope {
 public:
  explicit StageScope(std::string name, bool concurrent = false);
  ~StageScope();
  StageScope(const StageScope&) = delete;
  StageScope& operator=(const StageScope&) = delete;

 private:
  int uncaught_;
};

/// The error for the exception `e` caught at the boundary of `stage` (or of
/// the innermost stage it unwound through).
Error StageExceptionError(const std::string& stage, const std::exception_ptr& e);

/// Runs fn() (returning Status or Result<T>) as the stage `name`; an
/// exception from it becomes its error value.
template <typename F>
auto RunStage(const std::string& name, F&& fn) -> decltype(fn()) {
  try {
    StageScope scope(name);
    return std::forward<F>(fn)();
  } catch (...) {
    return StageExceptionError(name, std::current_exception());
  }
}

}  // namespace aggscan
