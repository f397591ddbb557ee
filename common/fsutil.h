// Durable file creation: write to a temporary name in the same directory,
// fsync the file, rename over the final name, fsync the directory. A reader
// never sees a partially written file under its final name; after power loss
// either the old or the new content is there. Temporary names start with
// ".tmp-" so start-up recovery can find and delete leftovers.
#pragma once

#include <span>
#include <string>
#include <string_view>

#include "common/error.h"

namespace aggscan {

inline constexpr std::string_view kTempPrefix = ".tmp-";

/// Atomically creates or replaces `path` with `data`. With `no_replace`, fails
/// with kConflict if `path` exists (nothing captured is overwritten). `mode`:
/// the new file's permissions (before the umask), from its creation on.
Status WriteFileAtomic(const std::string& path, std::span<const unsigned char> data,
                       bool no_replace = false, unsigned mode = 0644);
Status WriteFileAtomic(const std::string& path, std::string_view data, bool no_replace = false,
                       unsigned mode = 0644);
/// fsync()s a directory so that renames and creations in it are durable.
Status FsyncDir(const std::string& dir);
/// mkdir -p, fsyncing each parent whose entry was created.
Status MakeDirsDurable(const std::string& dir);
/// Durable rename (same filesystem), fsyncs both parent directories.
Status RenameDurable(const std::string& from, const std::string& to);
/// Reads a whole file.
Result<std::string> ReadFile(const std::string& path);
bool PathExists(const std::string& path);
/// `prefix` + the time now (CompactUtcNow) + "-2", "-3", ... where needed so
/// that `dir` + the result does not exist yet: names of things kept side by
/// side (previous calibrations, captures, installed sets) that sort by time.
std::string FreeTimedName(const std::string& dir, const std::string& prefix);
/// The folder of the running executable (/proc/self/exe); empty if unknown.
/// Installed data files are found relative to it (../share/aggscan/).
std::string ExecutableDir();
/// Removes leftover temporary files (".tmp-*") in dir (not recursive); returns how many.
int RemoveTempFiles(const std::string& dir);

}  // namespace aggscan
