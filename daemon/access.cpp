#include "daemon/access.h"

#include <crypt.h>
#include <sys/random.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstring>

#include "common/fsutil.h"
#include "common/log.h"

namespace aggscan {

namespace {

constexpr const char* kCat = "access";

// Names and addresses echoed into the journal: printable ASCII, capped.
std::string Printable(std::string_view s, size_t max_len = 64) {
  std::string out;
  for (unsigned char c : s.substr(0, max_len)) out += (c >= 0x20 && c < 0x7f) ? char(c) : '?';
  if (s.size() > max_len) out += "...";
  return out;
}

std::optional<std::string> Base64Decode(std::string_view in) {
  auto value = [](char c) -> int {
    if (c >= 'A' && c <= 'Z') return c - 'A';
    if (c >= 'a' && c <= 'z') return c - 'a' + 26;
    if (c >= '0' && c <= '9') return c - '0' + 52;
    if (c == '+') return 62;
    if (c == '/') return 63;
    return -1;
  };
  while (!in.empty() && in.back() == '=') in.remove_suffix(1);
  std::string out;
  uint32_t acc = 0;
  int bits = 0;
  for (char c : in) {
    const int v = value(c);
    if (v < 0) return std::nullopt;
    acc = (acc << 6) | static_cast<uint32_t>(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out += static_cast<char>((acc >> bits) & 0xff);
    }
  }
  return out;
}

std::string RandomToken() {
  unsigned char bytes[32];
  size_t got = 0;
  while (got < sizeof bytes) {
    const ssize_t n = ::getrandom(bytes + got, sizeof bytes - got, 0);
    if (n > 0) got += static_cast<size_t>(n);
  }
  static const char* kHex = "0123456789abcdef";
  std::string out;
  for (unsigned char b : bytes) {
    out += kHex[b >> 4];
    out += kHex[b & 15];
  }
  return out;
}

std::string_view Trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
    s.remove_suffix(1);
  return s;
}

}  // namespace

const char* RoleName(Role r) { return r == Role::kOperator ? "operator" : "viewer"; }

std::optional<Role> ParseRole(std::string_view s) {
  if (s == "operator") return Role::kOperator;
  if (s == "viewer") return Role::kViewer;
  return std::nullopt;
}

bool IsValidAccountName(std::string_view name) {
  if (name.empty() || name.size() > 32) return false;
  return std::all_of(name.begin(), name.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '.' ||
           c == '_' || c == '-';
  });
}

Result<std::vector<Account>> ParseAccounts(const std::string& text, const std::string& what) {
  std::vector<Account> out;
  size_t pos = 0;
  for (int line_no = 1; pos <= text.size(); ++line_no) {
    size_t nl = text.find('\n', pos);
    if (nl == std::string::npos) nl = text.size();
    const std::string_view line = Trim(std::string_view(text).substr(pos, nl - pos));
    pos = nl + 1;
    if (line.empty() || line.front() == '#') continue;
    const std::string where = what + " line " + std::to_string(line_no);
    const size_t c1 = line.find(':');
    const size_t c2 = c1 == std::string_view::npos ? c1 : line.find(':', c1 + 1);
    if (c2 == std::string_view::npos) {
      return MakeError(ErrorClass::kInvalidConfig,
                       where +
                           ": expected name:role:hash (add accounts with `aggscan user add NAME "
                           "--role operator|viewer --file " +
                           what + "`)");
    }
    Account a;
    a.name = std::string(line.substr(0, c1));
    const std::string_view role = line.substr(c1 + 1, c2 - c1 - 1);
    a.hash = std::string(line.substr(c2 + 1));
    if (!IsValidAccountName(a.name)) {
      return MakeError(ErrorClass::kInvalidConfig,
                       where + ": account name \"" + Printable(a.name) +
                           "\" is not 1-32 characters from A-Z a-z 0-9 . _ -");
    }
    const std::optional<Role> r = ParseRole(role);
    if (!r) {
      return MakeError(
          ErrorClass::kInvalidConfig,
          where + ": role \"" + Printable(role) + "\" of " + a.name + " is not operator or viewer");
    }
    a.role = *r;
    // crypt(3) settings start with "$id$"; anything else (a password written
    // in clear, say) is refused rather than compared.
    if (a.hash.size() < 4 || a.hash[0] != '$' || a.hash.find('$', 1) == std::string::npos) {
      return MakeError(ErrorClass::kInvalidConfig,
                       where + ": the password of " + a.name +
                           " is not a crypt(3) hash; set it with `aggscan user add " + a.name +
                           " --role " + RoleName(a.role) + " --file " + what + "`");
    }
    for (const Account& other : out) {
      if (other.name == a.name)
        return MakeError(ErrorClass::kInvalidConfig, where + ": account " + a.name + " twice");
    }
    out.push_back(std::move(a));
  }
  return out;
}

Result<std::vector<Account>> LoadAccounts(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) {
    const int err = errno;
    return MakeError(ErrorClass::kInvalidConfig,
                     "cannot read the accounts file " + path + ": " + std::strerror(err) +
                         " (daemon.credentials_file; create it with `aggscan user add NAME --role "
                         "operator --file " +
                         path + "`)");
  }
  if ((st.st_mode & 077) != 0) {
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    return MakeError(ErrorClass::kInvalidConfig,
                     "the accounts file " + path + " may be read or written by others (mode " +
                         mode + "): make it the service's alone, `chmod 600 " + path + "`");
  }
  Result<std::string> text = ReadFile(path);
  if (!text) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "cannot read the accounts file " + path + ": " + text.error().ToString() +
                         " (it must be readable by the user aggscand runs as)");
  }
  Result<std::vector<Account>> accounts = ParseAccounts(*text, path);
  if (accounts && accounts->empty()) {
    return MakeError(ErrorClass::kInvalidConfig, "the accounts file " + path +
                                                     " has no account: add one with `aggscan user "
                                                     "add NAME --role operator --file " +
                                                     path + "`");
  }
  return accounts;
}

Result<std::string> HashPassword(const std::string& password) {
  char setting[CRYPT_GENSALT_OUTPUT_SIZE];
  // Null random bytes: libxcrypt takes them from the kernel; 0: its default cost.
  if (crypt_gensalt_rn("$y$", 0, nullptr, 0, setting, sizeof setting) == nullptr) {
    return MakeError(ErrorClass::kInternal, "cannot make a password salt", std::strerror(errno));
  }
  crypt_data data{};
  const char* hash = crypt_rn(password.c_str(), setting, &data, sizeof data);
  if (hash == nullptr || hash[0] == '*')
    return MakeError(ErrorClass::kInternal, "cannot hash the password", std::strerror(errno));
  return std::string(hash);
}

bool PasswordMatches(const std::string& password, const std::string& hash) {
  crypt_data data{};
  const char* out = crypt_rn(password.c_str(), hash.c_str(), &data, sizeof data);
  if (out == nullptr || out[0] == '*') return false;
  // Constant time over the hash's length.
  const size_t n = std::strlen(out);
  if (n != hash.size()) return false;
  unsigned char diff = 0;
  for (size_t i = 0; i < n; ++i) diff |= static_cast<unsigned char>(out[i] ^ hash[i]);
  return diff == 0;
}

Result<std::unique_ptr<AccessControl>> AccessControl::Open(const std::string& path) {
  Result<std::vector<Account>> accounts = LoadAccounts(path);
  if (!accounts) return accounts.error();
  std::unique_ptr<AccessControl> ac(new AccessControl(path));
  ac->accounts_ = std::move(*accounts);
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0) {
    ac->file_mtime_ns_ = static_cast<int64_t>(st.st_mtim.tv_sec) * 1000000000 + st.st_mtim.tv_nsec;
    ac->file_size_ = st.st_size;
  }
  return ac;
}

void AccessControl::ReloadIfChanged() {
  struct stat st {};
  if (::stat(path_.c_str(), &st) != 0) return;  // LoadAccounts would say why; keep what we have
  const int64_t mtime = static_cast<int64_t>(st.st_mtim.tv_sec) * 1000000000 + st.st_mtim.tv_nsec;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (mtime == file_mtime_ns_ && st.st_size == file_size_) return;
    file_mtime_ns_ = mtime;
    file_size_ = st.st_size;
  }
  Result<std::vector<Account>> accounts = LoadAccounts(path_);
  if (!accounts) {
    AGG_LOGE(kCat, "accounts not reloaded, the ones read before stay: %s",
             accounts.error().ToString().c_str());
    return;
  }
  std::lock_guard<std::mutex> lock(mu_);
  accounts_ = std::move(*accounts);
  AGG_LOGI(kCat, "accounts reloaded from %s: %zu", path_.c_str(), accounts_.size());
}

size_t AccessControl::accounts() const {
  std::lock_guard<std::mutex> lock(mu_);
  return accounts_.size();
}

size_t AccessControl::sessions() const {
  std::lock_guard<std::mutex> lock(mu_);
  return sessions_.size();
}

std::optional<AccessControl::Refusal> AccessControl::Locked(const std::string& peer) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = failures_.find(peer);
  if (it == failures_.end()) return std::nullopt;
  const auto now = Clock::now();
  if (it->second.locked_until <= now) return std::nullopt;
  const auto left = std::chrono::ceil<std::chrono::seconds>(it->second.locked_until - now);
  Refusal r;
  r.status = 429;
  r.retry_after_s = static_cast<int>(left.count());
  r.message = "too many failed logins from " + Printable(peer) + ": try again in " +
              std::to_string(r.retry_after_s) + " s";
  return r;
}

AccessControl::Refusal AccessControl::Failed(const std::string& peer, const std::string& user,
                                             const std::string& why) {
  std::lock_guard<std::mutex> lock(mu_);
  const auto now = Clock::now();
  // Forget addresses quiet for longer than the longest lockout; bounds the map.
  for (auto it = failures_.begin(); it != failures_.end();) {
    it = now - it->second.last > kMaxLockout && it->first != peer ? failures_.erase(it)
                                                                  : std::next(it);
  }
  Failures& f = failures_[peer];
  f.count += 1;
  f.last = now;
  std::string lock_note;
  if (f.count >= kFreeFailures) {
    auto lockout = kFirstLockout;
    for (int i = kFreeFailures; i < f.count && lockout < kMaxLockout; ++i) lockout *= 2;
    lockout = std::min(lockout, kMaxLockout);
    f.locked_until = now + lockout;
    lock_note =
        "; further attempts from there are refused for " + std::to_string(lockout.count()) + " s";
  }
  AGG_LOGW(kCat, "refused %s from %s: %s (failure %d in a row%s)",
           user.empty() ? "a request" : ("user \"" + Printable(user) + "\"").c_str(),
           Printable(peer).c_str(), why.c_str(), f.count, lock_note.c_str());
  Refusal r;
  r.status = 401;
  r.message = why;
  return r;
}

void AccessControl::Succeeded(const std::string& peer) {
  std::lock_guard<std::mutex> lock(mu_);
  failures_.erase(peer);
}

std::optional<Principal> AccessControl::Verify(const std::string& user,
                                               const std::string& password) {
  ReloadIfChanged();
  std::optional<Account> account;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const Account& a : accounts_)
      if (a.name == user) account = a;
  }
  if (!account) {
    // The same work as for a known name: the answer's time does not tell
    // which names exist.
    static const std::string dummy = [] {
      Result<std::string> h = HashPassword("-");
      return h ? *h : std::string("$y$j9T$");
    }();
    (void)PasswordMatches(password, dummy);
    return std::nullopt;
  }
  if (!PasswordMatches(password, account->hash)) return std::nullopt;
  return Principal{account->name, account->role, ""};
}

std::string AccessControl::SessionToken(const std::string* authorization,
                                        const std::string* cookie) {
  if (authorization != nullptr && authorization->rfind("Bearer ", 0) == 0)
    return std::string(Trim(std::string_view(*authorization).substr(7)));
  if (cookie != nullptr) {
    const std::string key = std::string(kCookie) + "=";
    for (size_t pos = 0; pos < cookie->size();) {
      size_t end = cookie->find(';', pos);
      if (end == std::string::npos) end = cookie->size();
      const std::string_view pair = Trim(std::string_view(*cookie).substr(pos, end - pos));
      if (pair.rfind(key, 0) == 0) return std::string(pair.substr(key.size()));
      pos = end + 1;
    }
  }
  return "";
}

std::variant<Principal, AccessControl::Refusal> AccessControl::Check(
    const std::string* authorization, const std::string* cookie, const std::string& peer) {
  if (std::optional<Refusal> locked = Locked(peer)) return *locked;
  if (authorization != nullptr && authorization->rfind("Basic ", 0) == 0) {
    const std::optional<std::string> pair =
        Base64Decode(Trim(std::string_view(*authorization).substr(6)));
    const size_t colon = pair ? pair->find(':') : std::string::npos;
    if (colon == std::string::npos) {
      return Refusal{401, "malformed Basic credentials: send base64 of name:password", 0};
    }
    const std::string user = pair->substr(0, colon);
    std::optional<Principal> who = Verify(user, pair->substr(colon + 1));
    if (!who) return Failed(peer, user, "wrong account name or password");
    Succeeded(peer);
    who->via = "basic";
    return *who;
  }
  if (authorization != nullptr && authorization->rfind("Bearer ", 0) != 0) {
    return Refusal{401, "unsupported Authorization scheme: use Bearer <session token> or Basic", 0};
  }
  const std::string token = SessionToken(authorization, cookie);
  if (token.empty()) {
    Refusal r;
    r.status = 401;
    r.message =
        "this rig's API needs credentials: log in (POST /api/v1/session {\"user\", "
        "\"password\"}) and send Authorization: Bearer <token>, or send Basic credentials "
        "(curl -u NAME, or AGGSCAN_USER and AGGSCAN_PASSWORD for the aggscan CLI)";
    return r;
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = sessions_.find(token);
    if (it != sessions_.end() && it->second.expires > Clock::now()) {
      Principal who = it->second.who;
      who.via = authorization != nullptr ? "bearer" : "cookie";
      return who;
    }
    if (it != sessions_.end()) sessions_.erase(it);
  }
  // Not counted as a failure: a 256-bit token cannot be guessed, and a
  // console still holding the token of an earlier run (aggscand restarted)
  // must not lock its own tablet out while it reconnects.
  return Refusal{401,
                 "the session token is not valid (expired, logged out, or aggscand restarted): "
                 "log in again",
                 0};
}

std::variant<AccessControl::Session, AccessControl::Refusal> AccessControl::Login(
    const std::string& user, const std::string& password, const std::string& peer) {
  if (std::optional<Refusal> locked = Locked(peer)) return *locked;
  std::optional<Principal> who = Verify(user, password);
  if (!who) return Failed(peer, user, "wrong account name or password");
  Succeeded(peer);
  Session s;
  s.token = RandomToken();
  s.who = *who;
  s.who.via = "bearer";
  s.expires = std::chrono::system_clock::now() + kSessionLifetime;
  std::lock_guard<std::mutex> lock(mu_);
  const auto now = Clock::now();
  for (auto it = sessions_.begin(); it != sessions_.end();)
    it = it->second.expires <= now ? sessions_.erase(it) : std::next(it);
  if (sessions_.size() >= kMaxSessions) {
    auto oldest = std::min_element(
        sessions_.begin(), sessions_.end(),
        [](const auto& a, const auto& b) { return a.second.order < b.second.order; });
    sessions_.erase(oldest);
  }
  sessions_[s.token] = Live{s.who, now + kSessionLifetime, s.expires, next_order_++};
  AGG_LOGI(kCat, "%s (%s) logged in from %s", s.who.user.c_str(), RoleName(s.who.role),
           Printable(peer).c_str());
  return s;
}

void AccessControl::Logout(const std::string& token) {
  std::lock_guard<std::mutex> lock(mu_);
  sessions_.erase(token);
}

}  // namespace aggscan
