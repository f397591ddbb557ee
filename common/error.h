// Errors that cross module borders: a class an operator can act on, a message
// that says what is wrong and what to do, and the underlying detail (errno text,
// library message) kept separately for logs.
#pragma once

#include <cassert>
#include <string>
#include <utility>
#include <variant>

namespace aggscan {

enum class ErrorClass {
  kInvalidArgument,  // a request or input value is wrong; fix the input
  kInvalidConfig,    // configuration is invalid; fix the config file
  kInvalidState,     // the operation is not allowed in the current state
  kNotFound,         // the named thing does not exist
  kConflict,         // the thing already exists / would be overwritten
  kDeviceMissing,    // device not present (unplugged, wrong path)
  kDisconnected,     // device went away during use
  kTimeout,          // device or peer did not answer in time
  kStalled,          // motion did not progress
  kDeviceFault,      // device reported an alarm / fault
  kDiskFull,         // no space left on the state directory's filesystem
  kIo,               // other filesystem or I/O error
  kCorrupt,          // stored data failed validation
  kCancelled,        // stopped on request (shutdown, abort); resumes when run again
  kInternal,         // a bug; report it
};

/// Short stable name of an error class ("timeout", "disk_full", ...), used in
/// logs, the API and metrics labels.
const char* ErrorClassName(ErrorClass c);

struct [[nodiscard]] Error {
  ErrorClass cls = ErrorClass::kInternal;
  std::string message;  // operator-facing: what is wrong and what to do
  std::string detail;   // underlying errno / library text, may be empty

  /// "message (detail)" or just the message.
  std::string ToString() const;
};

Error MakeError(ErrorClass cls, std::string message, std::string detail = {});
/// Error from errno: ENOSPC/EDQUOT map to kDiskFull, ENOENT to kNotFound, others kIo.
Error ErrnoError(std::string message, int err);

/// A value or an error. Small stand-in for std::expected (C++23).
template <typename T>
class [[nodiscard]] Result {
 public:
  Result(T value) : v_(std::move(value)) {}      // NOLINT(google-explicit-constructor)
  Result(Error error) : v_(std::move(error)) {}  // NOLINT(google-explicit-constructor)
  bool ok() const { return v_.index() == 0; }
  explicit operator bool() const { return ok(); }
  T& value() & {
    assert(ok());
    return std::get<0>(v_);
  }
  const T& value() const& {
    assert(ok());
    return std::get<0>(v_);
  }
  T&& value() && {
    assert(ok());
    return std::get<0>(std::move(v_));
  }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }
  const Error& error() const {
    assert(!ok());
    return std::get<1>(v_);
  }

 private:
  std::variant<T, Error> v_;
};

template <>
class [[nodiscard]] Result<void> {
 public:
  Result() = default;
  Result(Error error) : err_(std::move(error)), ok_(false) {}  // NOLINT
  bool ok() const { return ok_; }
  explicit operator bool() const { return ok_; }
  const Error& error() const {
    assert(!ok_);
    return err_;
  }

 private:
  Error err_;
  bool ok_ = true;
};

using Status = Result<void>;
inline Status OkStatus() { return Status(); }

}  // namespace aggscan
