// A ZIP archive of files on disk, made piece by piece while a client reads
// it: the HTTP transport asks for the next bytes, the stream writes the next
// member's header or the next block of its data through libarchive, and
// hands out what that produced. A sample's images are some tens of MB; the
// daemon's memory budget is a few frames, so the archive is never whole in
// memory: at most one block of a member plus libarchive's own header bytes
// are buffered at a time.
//
// Members are stored, not deflated: JPEG and PNG are compressed already, and
// storing costs no CPU on the rig's small computer while a capture runs.
#pragma once

#include <sys/types.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/error.h"
#include "daemon/control.h"

struct archive;

namespace aggscan {

/// Bytes produced on demand for an HTTP answer (see ApiResponse::source).
class BodySource {
 public:
  virtual ~BodySource() = default;
  /// Writes up to `max` bytes to `out`: the count written, 0 at the end, -1
  /// on an error (error() says which), after which the answer is cut short.
  virtual ssize_t Read(char* out, size_t max) = 0;
  virtual const std::string& error() const = 0;
};

class ZipStream final : public BodySource {
 public:
  /// Bytes of a member read from disk per step.
  static constexpr size_t kBlockBytes = size_t{64} * 1024;

  /// Checks that every member is a regular file (its size and time are
  /// taken now) and that the names are unique and relative; kNotFound
  /// naming the first file that is not there, kInvalidArgument for a bad
  /// name. Nothing is read yet.
  static Result<std::unique_ptr<ZipStream>> Open(std::vector<ArchiveMember> members);
  ~ZipStream() override;
  ZipStream(const ZipStream&) = delete;
  ZipStream& operator=(const ZipStream&) = delete;

  ssize_t Read(char* out, size_t max) override;
  const std::string& error() const override { return error_; }

  /// The most bytes held in memory at once so far (what libarchive produced
  /// and the client has not taken yet).
  size_t peak_buffered() const { return peak_; }
  /// Bytes of the members' data written so far.
  uint64_t data_bytes() const { return data_bytes_; }

 private:
  struct Member {
    ArchiveMember m;
    int64_t size = 0;
    int64_t mtime = 0;
  };
  explicit ZipStream(std::vector<Member> members) : members_(std::move(members)) {}
  /// Produces the next piece into pending_: a member's header, a block of its
  /// data, or the central directory at the end. False on an error.
  bool Step();
  bool Fail(std::string what);
  /// The current member's data is all written: closes its file and entry.
  bool EndMember();
  friend ssize_t ZipCollect(struct archive*, void* self, const void* buf, size_t n);

  std::vector<Member> members_;
  struct archive* a_ = nullptr;
  size_t next_ = 0;      // the member to start next
  int fd_ = -1;          // the member being written, -1 between members
  int64_t left_ = 0;     // its bytes still to write
  std::string pending_;  // produced, not yet read
  size_t off_ = 0;
  bool finished_ = false;
  bool failed_ = false;
  std::string error_;
  size_t peak_ = 0;
  uint64_t data_bytes_ = 0;
};

}  // namespace aggscan
