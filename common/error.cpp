#include "common/error.h"

#include <cerrno>
#include <cstring>

namespace aggscan {

const char* ErrorClassName(ErrorClass c) {
  switch (c) {
    case ErrorClass::kInvalidArgument:
      return "invalid_argument";
    case ErrorClass::kInvalidConfig:
      return "invalid_config";
    case ErrorClass::kInvalidState:
      return "invalid_state";
    case ErrorClass::kNotFound:
      return "not_found";
    case ErrorClass::kConflict:
      return "conflict";
    case ErrorClass::kDeviceMissing:
      return "device_missing";
    case ErrorClass::kDisconnected:
      return "disconnected";
    case ErrorClass::kTimeout:
      return "timeout";
    case ErrorClass::kStalled:
      return "stalled";
    case ErrorClass::kDeviceFault:
      return "device_fault";
    case ErrorClass::kDiskFull:
      return "disk_full";
    case ErrorClass::kIo:
      return "io";
    case ErrorClass::kCorrupt:
      return "corrupt";
    case ErrorClass::kCancelled:
      return "cancelled";
    case ErrorClass::kInternal:
      return "internal";
  }
  return "internal";
}

std::string Error::ToString() const {
  if (detail.empty()) return message;
  return message + " (" + detail + ")";
}

Error MakeError(ErrorClass cls, std::string message, std::string detail) {
  return Error{cls, std::move(message), std::move(detail)};
}

Error ErrnoError(std::string message, int err) {
  ErrorClass cls = ErrorClass::kIo;
  if (err == ENOSPC || err == EDQUOT) {
    cls = ErrorClass::kDiskFull;
    message += ": disk full, free space on the state directory's filesystem";
  } else if (err == ENOENT) {
    cls = ErrorClass::kNotFound;
  }
  return Error{cls, std::move(message), std::strerror(err)};
}

}  // namespace aggscan
