// Who may use the API when it is reachable from the network: accounts in a
// file only the service can read (name, role, crypt(3) hash of the password,
// yescrypt by default), sessions made by logging in, and a lockout of
// addresses that keep failing.
//
//   accounts file:   # comment
//                    alice:operator:$y$j9T$...
//                    qa:viewer:$y$j9T$...
//
// A request proves who it is with `Authorization: Bearer <session token>`
// (the console, after POST /api/v1/session), `Authorization: Basic` (the CLI,
// curl -u), or the session cookie. The cookie alone only reads: a request that
// changes the rig's state must carry the Authorization header, which a link
// or a form on another site cannot send. `viewer` may only read, `operator`
// may also capture.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <variant>
#include <vector>

#include "common/error.h"

namespace aggscan {

enum class Role { kViewer, kOperator };
const char* RoleName(Role r);
std::optional<Role> ParseRole(std::string_view s);

struct Account {
  std::string name;
  Role role = Role::kViewer;
  std::string hash;  // crypt(3) setting and hash, "$y$..." (yescrypt)
};

/// Parses an accounts file's text; `what` names it in errors (kInvalidConfig,
/// with the line number and what to do).
Result<std::vector<Account>> ParseAccounts(const std::string& text, const std::string& what);
/// Reads and parses an accounts file; refused when group or others may read
/// or write it (chmod 600) or when it has no account.
Result<std::vector<Account>> LoadAccounts(const std::string& path);
/// A crypt(3) hash of `password` with a fresh yescrypt salt.
Result<std::string> HashPassword(const std::string& password);
/// Whether `password` matches the crypt(3) `hash`.
bool PasswordMatches(const std::string& password, const std::string& hash);
/// A valid account name: 1-32 of A-Z a-z 0-9 . _ -
bool IsValidAccountName(std::string_view name);

/// The one who made a request, once checked.
struct Principal {
  std::string user;
  Role role = Role::kViewer;
  /// "bearer", "basic" or "cookie": the cookie alone may not change state.
  std::string via;
};

class AccessControl {
 public:
  using Clock = std::chrono::steady_clock;
  /// Consecutive failures from one address before it is locked out.
  static constexpr int kFreeFailures = 5;
  /// The first lockout; each further failure doubles it, up to kMaxLockout.
  static constexpr std::chrono::seconds kFirstLockout{2};
  static constexpr std::chrono::seconds kMaxLockout{15 * 60};
  /// A session lasts this long from its login (an operator's shift).
  static constexpr std::chrono::hours kSessionLifetime{12};
  /// Sessions kept at most; the oldest goes first.
  static constexpr size_t kMaxSessions = 256;
  static constexpr const char* kCookie = "aggscan_session";

  /// `path`: the accounts file, read now (LoadAccounts) and again whenever it
  /// changes (a new account needs no restart).
  static Result<std::unique_ptr<AccessControl>> Open(const std::string& path);

  struct Refusal {
    int status = 401;  // 401 no or bad credentials, 429 locked out
    std::string message;
    int retry_after_s = 0;  // 429 only
  };
  struct Session {
    std::string token;
    Principal who;
    std::chrono::system_clock::time_point expires;
  };

  /// Checks a request's credentials: `authorization` and `cookie` are its
  /// headers (null when absent), `peer` the client's address.
  std::variant<Principal, Refusal> Check(const std::string* authorization,
                                         const std::string* cookie, const std::string& peer);
  /// Logs in with a name and password: a new session, or a refusal.
  std::variant<Session, Refusal> Login(const std::string& user, const std::string& password,
                                       const std::string& peer);
  /// Ends the session of `token` (no-op when unknown).
  void Logout(const std::string& token);
  /// The session token a request carries (Bearer header, else cookie), or "".
  static std::string SessionToken(const std::string* authorization, const std::string* cookie);

  size_t accounts() const;
  size_t sessions() const;

 private:
  explicit AccessControl(std::string path) : path_(std::move(path)) {}
  /// Rereads the file when its size or modification time changed; on an
  /// error the accounts read before stay (and the error is logged).
  void ReloadIfChanged();
  /// A locked-out peer's refusal, if it is locked out now.
  std::optional<Refusal> Locked(const std::string& peer);
  Refusal Failed(const std::string& peer, const std::string& user, const std::string& why);
  void Succeeded(const std::string& peer);
  std::optional<Principal> Verify(const std::string& user, const std::string& password);

  struct Failures {
    int count = 0;
    Clock::time_point locked_until{};
    Clock::time_point last{};
  };
  struct Live {
    Principal who;
    Clock::time_point expires;
    std::chrono::system_clock::time_point expires_utc;
    uint64_t order = 0;
  };

  const std::string path_;
  mutable std::mutex mu_;
  std::vector<Account> accounts_;
  int64_t file_mtime_ns_ = -1;
  int64_t file_size_ = -1;
  std::unordered_map<std::string, Live> sessions_;  // token -> session
  uint64_t next_order_ = 0;
  std::map<std::string, Failures> failures_;  // peer address -> its failures
};

}  // namespace aggscan
