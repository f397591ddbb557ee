// The `aggscan` subcommands that talk to a running aggscand over its HTTP API
// (daemon/http_api.h):
//
//   aggscan [--url URL] [--json] status | selftest | arm ID | press | abort | reset | samples |
//   show ID
//
// The daemon URL comes from --url, else $AGGSCAN_URL, else kDefaultDaemonUrl.
// --json prints the daemon's JSON answer unchanged (errors too) for scripts.
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

inline constexpr const char* kDefaultDaemonUrl = "http://127.0.0.1:8470";

/// Exit codes of RunClientCommand.
inline constexpr int kClientExitOk = 0;
inline constexpr int kClientExitDaemonError = 1;  // the daemon answered with an error
inline constexpr int kClientExitUsage = 2;        // bad command line
inline constexpr int kClientExitUnreachable = 3;  // no answer from the daemon
inline constexpr int kClientExitUnhealthy =
    4;  // selftest: the daemon answered, a device is unhealthy

/// True for the subcommands RunClientCommand handles ("status", "arm", ...).
bool IsClientCommand(const std::string& word);

/// The usage lines of the client subcommands and their options.
void PrintClientUsage(std::ostream& out);

/// Runs one client subcommand. `args` are the words after `aggscan`; the
/// options --url URL / --url=URL / --json may appear anywhere among them.
/// Results go to `out`, diagnostics to `err`. Returns one of kClientExit*.
int RunClientCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

}  // namespace aggscan
