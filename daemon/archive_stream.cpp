#include "daemon/archive_stream.h"

#include <archive.h>
#include <archive_entry.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <set>

namespace aggscan {

// libarchive's write callback: what it produced goes to the pending bytes
// the client reads next.
ssize_t ZipCollect(struct archive*, void* self, const void* buf, size_t n) {
  auto* z = static_cast<ZipStream*>(self);
  z->pending_.append(static_cast<const char*>(buf), n);
  z->peak_ = std::max(z->peak_, z->pending_.size() - z->off_);
  return static_cast<ssize_t>(n);
}

Result<std::unique_ptr<ZipStream>> ZipStream::Open(std::vector<ArchiveMember> members) {
  std::vector<Member> checked;
  std::set<std::string> names;
  for (ArchiveMember& m : members) {
    if (m.name.empty() || m.name.front() == '/' || m.name.find("..") != std::string::npos ||
        !names.insert(m.name).second) {
      return MakeError(ErrorClass::kInvalidArgument, "archive member name \"" + m.name +
                                                         "\" is empty, absolute, repeated or "
                                                         "climbs out with \"..\"");
    }
    struct stat st {};
    if (::stat(m.path.c_str(), &st) != 0 || !S_ISREG(st.st_mode)) {
      return MakeError(ErrorClass::kNotFound, "no file " + m.path + " for the archive",
                       std::strerror(errno));
    }
    checked.push_back(Member{std::move(m), static_cast<int64_t>(st.st_size),
                             static_cast<int64_t>(st.st_mtim.tv_sec)});
  }
  std::unique_ptr<ZipStream> z(new ZipStream(std::move(checked)));
  z->a_ = archive_write_new();
  if (z->a_ == nullptr) return MakeError(ErrorClass::kInternal, "libarchive: out of memory");
  // Block size 0: every write goes to the callback at once, no 10 KB blocks
  // padded and held back.
  if (archive_write_set_format_zip(z->a_) != ARCHIVE_OK ||
      archive_write_set_options(z->a_, "zip:compression=store") != ARCHIVE_OK ||
      archive_write_set_bytes_per_block(z->a_, 0) != ARCHIVE_OK ||
      archive_write_open2(z->a_, z.get(), nullptr, &ZipCollect, nullptr, nullptr) != ARCHIVE_OK) {
    return MakeError(ErrorClass::kInternal, std::string("libarchive cannot make a ZIP stream: ") +
                                                archive_error_string(z->a_));
  }
  return z;
}

ZipStream::~ZipStream() {
  if (fd_ >= 0) ::close(fd_);
  if (a_ != nullptr) archive_write_free(a_);
}

bool ZipStream::Fail(std::string what) {
  failed_ = true;
  error_ = std::move(what);
  return false;
}

bool ZipStream::EndMember() {
  ::close(fd_);
  fd_ = -1;
  if (archive_write_finish_entry(a_) != ARCHIVE_OK)
    return Fail(std::string("libarchive: ") + archive_error_string(a_));
  return true;
}

bool ZipStream::Step() {
  if (fd_ >= 0) {
    // The next block of the current member.
    std::string block(static_cast<size_t>(std::min<int64_t>(left_, kBlockBytes)), '\0');
    const Member& m = members_[next_ - 1];
    size_t got = 0;
    while (got < block.size()) {
      const ssize_t n = ::read(fd_, block.data() + got, block.size() - got);
      if (n < 0 && errno == EINTR) continue;
      if (n < 0) return Fail("cannot read " + m.m.path + ": " + std::strerror(errno));
      if (n == 0) return Fail(m.m.path + " became shorter while it was archived");
      got += static_cast<size_t>(n);
    }
    if (archive_write_data(a_, block.data(), block.size()) != static_cast<ssize_t>(block.size()))
      return Fail(std::string("libarchive: ") + archive_error_string(a_));
    data_bytes_ += block.size();
    left_ -= static_cast<int64_t>(block.size());
    return left_ > 0 || EndMember();
  }
  if (next_ < members_.size()) {
    const Member& m = members_[next_++];
    fd_ = ::open(m.m.path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd_ < 0) return Fail("cannot open " + m.m.path + ": " + std::strerror(errno));
    struct stat st {};
    if (::fstat(fd_, &st) != 0 || static_cast<int64_t>(st.st_size) != m.size)
      return Fail(m.m.path + " changed while the archive was made");
    archive_entry* e = archive_entry_new();
    archive_entry_set_pathname(e, m.m.name.c_str());
    archive_entry_set_filetype(e, AE_IFREG);
    archive_entry_set_perm(e, 0644);
    archive_entry_set_size(e, m.size);
    archive_entry_set_mtime(e, m.mtime, 0);
    const int rc = archive_write_header(a_, e);
    archive_entry_free(e);
    if (rc != ARCHIVE_OK) return Fail(std::string("libarchive: ") + archive_error_string(a_));
    left_ = m.size;
    return left_ > 0 || EndMember();
  }
  // Every member written: the central directory.
  if (archive_write_close(a_) != ARCHIVE_OK)
    return Fail(std::string("libarchive: ") + archive_error_string(a_));
  finished_ = true;
  return true;
}

ssize_t ZipStream::Read(char* out, size_t max) {
  while (off_ >= pending_.size()) {
    pending_.clear();
    off_ = 0;
    if (failed_) return -1;
    if (finished_) return 0;
    if (!Step()) return -1;
  }
  const size_t n = std::min(max, pending_.size() - off_);
  std::memcpy(out, pending_.data() + off_, n);
  off_ += n;
  return static_cast<ssize_t>(n);
}

}  // namespace aggscan
