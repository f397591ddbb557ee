// `aggscan selftest --config FILE [--json]`: bring-up without the daemon.
// Opens each device the config names, exercises it briefly (camera: open and
// configure with the config's settings; turntable: open and read its status,
// an alarm counts as a fault; button: start and stop watching it), reports
// each one's state and actionable message, and closes them. Stop aggscand
// first: it holds the devices (a serial port or V4L2 node cannot be shared).
// Without --config, `aggscan selftest` asks the running daemon (cli/client.h).
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

/// `args` are the words after `aggscan` (the word "selftest" among them). Returns 0 when every
/// device is ok, 4 (kClientExitUnhealthy) when one is not, 2 for a bad command line or config.
int RunOfflineSelftest(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

/// True when `args` (the words after `aggscan`) ask for the offline selftest.
bool IsOfflineSelftest(const std::vector<std::string>& args);

}  // namespace aggscan
