#include "common/fsutil.h"

#include <dirent.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <filesystem>
#include <random>

#include "common/clock.h"

namespace aggscan {
namespace {

// Closes an fd on scope exit.
class UniqueFd {
 public:
  explicit UniqueFd(int fd) : fd_(fd) {}
  ~UniqueFd() {
    if (fd_ >= 0) ::close(fd_);
  }
  UniqueFd(const UniqueFd&) = delete;
  UniqueFd& operator=(const UniqueFd&) = delete;
  int get() const { return fd_; }
  int release() {
    int f = fd_;
    fd_ = -1;
    return f;
  }

 private:
  int fd_;
};

std::string DirName(const std::string& path) {
  auto p = std::filesystem::path(path).parent_path().string();
  return p.empty() ? "." : p;
}

std::string TempName(const std::string& path) {
  static thread_local std::mt19937_64 rng{std::random_device{}()};
  auto fs = std::filesystem::path(path);
  char suffix[17];
  std::snprintf(suffix, sizeof suffix, "%016llx", static_cast<unsigned long long>(rng()));
  return (fs.parent_path() / (std::string(kTempPrefix) + fs.filename().string() + "." + suffix))
      .string();
}

}  // namespace

Status FsyncDir(const std::string& dir) {
  UniqueFd fd(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (fd.get() < 0) return ErrnoError("cannot open directory " + dir, errno);
  if (::fsync(fd.get()) != 0) return ErrnoError("cannot fsync directory " + dir, errno);
  return OkStatus();
}

Status WriteFileAtomic(const std::string& path, std::span<const unsigned char> data,
                       bool no_replace, unsigned mode) {
  const std::string tmp = TempName(path);
  {
    UniqueFd fd(::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, mode));
    if (fd.get() < 0) return ErrnoError("cannot create " + tmp, errno);
    size_t off = 0;
    while (off < data.size()) {
      ssize_t n = ::write(fd.get(), data.data() + off, data.size() - off);
      if (n < 0) {
        if (errno == EINTR) continue;
        int e = errno;
        ::unlink(tmp.c_str());
        return ErrnoError("cannot write " + path, e);
      }
      off += static_cast<size_t>(n);
    }
    if (::fsync(fd.get()) != 0) {
      int e = errno;
      ::unlink(tmp.c_str());
      return ErrnoError("cannot fsync " + path, e);
    }
  }
  if (no_replace) {
    // link() fails with EEXIST instead of replacing: the existing file is kept.
    if (::link(tmp.c_str(), path.c_str()) != 0) {
      int e = errno;
      ::unlink(tmp.c_str());
      if (e == EEXIST) {
        return MakeError(ErrorClass::kConflict, path + " already exists; refusing to overwrite it");
      }
      return ErrnoError("cannot create " + path, e);
    }
    ::unlink(tmp.c_str());
  } else if (::rename(tmp.c_str(), path.c_str()) != 0) {
    int e = errno;
    ::unlink(tmp.c_str());
    return ErrnoError("cannot rename into " + path, e);
  }
  return FsyncDir(DirName(path));
}

Status WriteFileAtomic(const std::string& path, std::string_view data, bool no_replace,
                       unsigned mode) {
  return WriteFileAtomic(path,
                         std::span<const unsigned char>(
                             reinterpret_cast<const unsigned char*>(data.data()), data.size()),
                         no_replace, mode);
}

Status MakeDirsDurable(const std::string& dir) {
  std::filesystem::path p(dir);
  std::filesystem::path cur;
  for (const auto& part : p) {
    cur /= part;
    if (cur.string().empty()) continue;
    if (::mkdir(cur.c_str(), 0755) == 0) {
      Status s = FsyncDir(DirName(cur.string()));
      if (!s) return s;
    } else if (errno != EEXIST) {
      return ErrnoError("cannot create directory " + cur.string(), errno);
    }
  }
  struct stat st {};
  if (::stat(dir.c_str(), &st) != 0 || !S_ISDIR(st.st_mode)) {
    return MakeError(ErrorClass::kIo, dir + " exists but is not a directory");
  }
  return OkStatus();
}

Status RenameDurable(const std::string& from, const std::string& to) {
  if (::rename(from.c_str(), to.c_str()) != 0)
    return ErrnoError("cannot rename " + from + " to " + to, errno);
  Status s = FsyncDir(DirName(to));
  if (!s) return s;
  if (DirName(from) != DirName(to)) return FsyncDir(DirName(from));
  return OkStatus();
}

Result<std::string> ReadFile(const std::string& path) {
  UniqueFd fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
  if (fd.get() < 0) return ErrnoError("cannot open " + path, errno);
  std::string out;
  char buf[65536];
  for (;;) {
    ssize_t n = ::read(fd.get(), buf, sizeof buf);
    if (n < 0) {
      if (errno == EINTR) continue;
      return ErrnoError("cannot read " + path, errno);
    }
    if (n == 0) break;
    out.append(buf, static_cast<size_t>(n));
  }
  return out;
}

bool PathExists(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0;
}

std::string FreeTimedName(const std::string& dir, const std::string& prefix) {
  const std::string stamp = prefix + CompactUtcNow();
  std::string name = stamp;
  for (int k = 2; PathExists(dir + name); ++k) name = stamp + "-" + std::to_string(k);
  return name;
}

int RemoveTempFiles(const std::string& dir) {
  int removed = 0;
  DIR* d = ::opendir(dir.c_str());
  if (!d) return 0;
  while (dirent* e = ::readdir(d)) {
    std::string_view name(e->d_name);
    if (name.substr(0, kTempPrefix.size()) == kTempPrefix) {
      if (::unlinkat(::dirfd(d), e->d_name, 0) == 0) ++removed;
    }
  }
  ::closedir(d);
  if (removed > 0) (void)FsyncDir(dir);
  return removed;
}

std::string ExecutableDir() {
  char buf[4096];
  const ssize_t n = ::readlink("/proc/self/exe", buf, sizeof buf - 1);
  if (n <= 0) return "";
  buf[n] = '\0';
  return std::filesystem::path(buf).parent_path().string();
}

}  // namespace aggscan
