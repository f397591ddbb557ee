#include "cli/user_command.h"

#include <sys/stat.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <iostream>
#include <optional>
#include <sstream>

#include "common/fsutil.h"
#include "daemon/access.h"

namespace aggscan {

namespace {

constexpr size_t kMinPassword = 8;

// One verb's line of the usage (PrintUserUsage prints them all).
void PrintVerbUsage(std::ostream& o, const std::string& verb) {
  if (verb == "add")
    o << "  aggscan user add NAME --role operator|viewer --file FILE   add or replace an API "
         "account (password from the terminal, or stdin's first line)\n";
  if (verb == "remove")
    o << "  aggscan user remove NAME --file FILE                       remove an account\n";
  if (verb == "list")
    o << "  aggscan user list --file FILE                              names and roles\n";
}

int Usage(std::ostream& err, const std::string& why) {
  err << "aggscan user: " << why << "\n";
  PrintUserUsage(err);
  return 2;
}

// One line from the terminal without echo (or from a pipe as it is).
std::optional<std::string> ReadSecret(std::istream& in, std::ostream& err, const char* prompt) {
  const bool tty = &in == &std::cin && ::isatty(STDIN_FILENO);
  termios old{};
  if (tty) {
    err << prompt << std::flush;
    ::tcgetattr(STDIN_FILENO, &old);
    termios quiet = old;
    quiet.c_lflag &= ~static_cast<tcflag_t>(ECHO);
    ::tcsetattr(STDIN_FILENO, TCSANOW, &quiet);
  }
  std::string line;
  const bool ok = static_cast<bool>(std::getline(in, line));
  if (tty) {
    ::tcsetattr(STDIN_FILENO, TCSANOW, &old);
    err << "\n";
  }
  if (!ok) return std::nullopt;
  if (!line.empty() && line.back() == '\r') line.pop_back();
  return line;
}

// The accounts of `path`, or none when it does not exist yet.
Result<std::vector<Account>> ReadExisting(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return std::vector<Account>{};
  Result<std::string> text = ReadFile(path);
  if (!text) return text.error();
  return ParseAccounts(*text, path);
}

Status WriteAccounts(const std::string& path, const std::vector<Account>& accounts) {
  std::ostringstream o;
  o << "# aggscand accounts (daemon.credentials_file): name:role:crypt(3) hash.\n"
    << "# Edit with `aggscan user add|remove`; keep it readable by the service alone.\n";
  for (const Account& a : accounts) o << a.name << ":" << RoleName(a.role) << ":" << a.hash << "\n";
  // Created 0600 from the start: the hashes are never readable by others.
  return WriteFileAtomic(path, o.str(), false, 0600);
}

}  // namespace

void PrintUserUsage(std::ostream& o) {
  PrintVerbUsage(o, "add");
  PrintVerbUsage(o, "remove");
  PrintVerbUsage(o, "list");
}

int RunUserCommand(const std::vector<std::string>& args, std::istream& in, std::ostream& out,
                   std::ostream& err) {
  // Before anything else: `user add NAME --help` must not ask for a password.
  if (std::any_of(args.begin(), args.end(),
                  [](const std::string& a) { return a == "--help" || a == "-h"; })) {
    out << "usage:\n";
    if (args[0] == "add" || args[0] == "remove" || args[0] == "list")
      PrintVerbUsage(out, args[0]);
    else
      PrintUserUsage(out);
    return 0;
  }
  if (args.empty()) return Usage(err, "say add, remove or list");
  const std::string verb = args[0];
  std::string name, file, role_text;
  for (size_t i = 1; i < args.size(); ++i) {
    const std::string& a = args[i];
    auto value = [&](std::string* v) {
      if (i + 1 >= args.size()) return false;
      *v = args[++i];
      return true;
    };
    if (a == "--file") {
      if (!value(&file)) return Usage(err, "--file needs a path");
    } else if (a == "--role") {
      if (!value(&role_text)) return Usage(err, "--role needs operator or viewer");
    } else if (name.empty() && verb != "list" && a.rfind("--", 0) != 0) {
      name = a;
    } else {
      return Usage(err, "unexpected argument \"" + a + "\"");
    }
  }
  if (file.empty())
    return Usage(err, "give the accounts file with --file (daemon.credentials_file)");
  Result<std::vector<Account>> accounts = ReadExisting(file);
  if (!accounts) {
    err << "aggscan user: " << accounts.error().ToString() << "\n";
    return 1;
  }
  if (verb == "list") {
    for (const Account& a : *accounts) out << a.name << " " << RoleName(a.role) << "\n";
    return 0;
  }
  if (verb != "add" && verb != "remove") return Usage(err, "unknown verb \"" + verb + "\"");
  if (!IsValidAccountName(name))
    return Usage(err, "give an account name of 1-32 characters from A-Z a-z 0-9 . _ -");
  auto it = std::find_if(accounts->begin(), accounts->end(),
                         [&](const Account& a) { return a.name == name; });
  if (verb == "remove") {
    if (it == accounts->end()) {
      err << "aggscan user: no account " << name << " in " << file << "\n";
      return 1;
    }
    accounts->erase(it);
  } else {
    const std::optional<Role> role = ParseRole(role_text);
    if (!role) return Usage(err, "--role must be operator or viewer");
    const std::optional<std::string> password = ReadSecret(in, err, "password: ");
    if (!password || password->size() < kMinPassword) {
      err << "aggscan user: the password must have at least " << kMinPassword << " characters\n";
      return 1;
    }
    if (&in == &std::cin && ::isatty(STDIN_FILENO)) {
      const std::optional<std::string> again = ReadSecret(in, err, "again: ");
      if (!again || *again != *password) {
        err << "aggscan user: the passwords differ; nothing changed\n";
        return 1;
      }
    }
    Result<std::string> hash = HashPassword(*password);
    if (!hash) {
      err << "aggscan user: " << hash.error().ToString() << "\n";
      return 1;
    }
    Account a{name, *role, *hash};
    if (it != accounts->end()) {
      *it = a;
    } else {
      accounts->push_back(a);
    }
  }
  if (Status s = WriteAccounts(file, *accounts); !s) {
    err << "aggscan user: " << s.error().ToString() << "\n";
    return 1;
  }
  out << (verb == "add" ? "saved " : "removed ") << name << " in " << file
      << " (a running aggscand rereads it at the next login)\n";
  return 0;
}

}  // namespace aggscan
