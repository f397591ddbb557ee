// --version of aggscan, aggscand and aggscan-worker, and --help / -h of every
// offline command of aggscan (and of each form of it), through the real
// binaries: exit 0, the usage on stdout, and nothing done, even with a line
// that would otherwise run the command.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "common/fsutil.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

struct Outcome {
  int rc = -1;
  std::string out, err;
};

// Runs BINARY_DIR/rel with `args` in the directory `cwd`, stdin from
// /dev/null (a command that went on to read a password gets none). A command
// that ran instead of printing its usage could run for minutes (validate,
// masks train): it is killed after 60 s and reported as 128 + SIGKILL.
Outcome Exec(const std::string& rel, const std::vector<std::string>& args, const std::string& cwd) {
  static test::TempDir logs;
  static int seq = 0;
  const std::string out_path = logs.path() + "/out" + std::to_string(seq);
  const std::string err_path = logs.path() + "/err" + std::to_string(seq++);
  std::vector<std::string> argv_s = {std::string(AGGSCAN_BINARY_DIR) + "/" + rel};
  argv_s.insert(argv_s.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& a : argv_s) argv.push_back(a.data());
  argv.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid == 0) {
    const int in = ::open("/dev/null", O_RDONLY);
    const int o = ::open(out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    const int e = ::open(err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (in < 0 || o < 0 || e < 0 || ::chdir(cwd.c_str()) != 0) _exit(126);
    ::dup2(in, 0);
    ::dup2(o, 1);
    ::dup2(e, 2);
    ::execv(argv[0], argv.data());
    _exit(127);
  }
  Outcome r;
  int st = 0;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (::waitpid(pid, &st, WNOHANG) == 0) {
    if (std::chrono::steady_clock::now() > deadline) {
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &st, 0);
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  r.rc = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + (WIFSIGNALED(st) ? WTERMSIG(st) : 0);
  const Result<std::string> o = ReadFile(out_path), e = ReadFile(err_path);
  r.out = o ? *o : std::string();
  r.err = e ? *e : std::string();
  return r;
}

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

std::string Join(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& w : v) s += (s.empty() ? "" : " ") + w;
  return s;
}

std::vector<std::string> Entries(const std::string& dir) {
  std::vector<std::string> names;
  for (const auto& e : fs::recursive_directory_iterator(dir)) names.push_back(e.path().string());
  return names;
}

TEST(HelpVersion, VersionEachBinaryPrintsTheSameVersionWithoutAConfig) {
  struct Binary {
    std::string name, rel;
  };
  const std::vector<Binary> binaries = {
      {"aggscan", "cli/aggscan"},
      {"aggscand", "daemon/aggscand"},
      {"aggscan-worker", "pipeline/aggscan-worker"},
  };
  // The project() version, then +g<commit> and -dirty from a git checkout.
  const std::string version_re =
      std::regex_replace(AGGSCAN_PROJECT_VERSION, std::regex(R"(\.)"), R"(\.)") +
      R"((\+g[0-9a-f]{4,40}(-dirty)?)?)";
  std::vector<std::string> versions;
  for (const Binary& b : binaries) {
    test::TempDir cwd;
    const Outcome r = Exec(b.rel, {"--version"}, cwd.path());
    SCOPED_TRACE(b.name + " --version: stdout '" + r.out + "', stderr '" + r.err + "'");
    EXPECT_EQ(r.rc, 0);
    EXPECT_TRUE(std::regex_search(r.out, std::regex("^" + b.name + R"( \d+\.\d+\.\d+)")));
    EXPECT_TRUE(std::regex_match(r.out, std::regex(b.name + " " + version_re + "\n")));
    EXPECT_TRUE(Entries(cwd.path()).empty()) << "--version left files behind";
    const size_t space = r.out.find(' ');
    versions.push_back(space == std::string::npos ? "" : r.out.substr(space + 1));
  }
  EXPECT_EQ(versions[0], versions[1]);
  EXPECT_EQ(versions[0], versions[2]);
}

// --version wins over options that would otherwise need a config or a daemon.
TEST(HelpVersion, VersionWinsOverTheRestOfTheLine) {
  test::TempDir cwd;
  const Outcome d = Exec("daemon/aggscand", {"--config", "missing.toml", "--version"}, cwd.path());
  EXPECT_EQ(d.rc, 0) << d.err;
  EXPECT_EQ(d.out.rfind("aggscand ", 0), 0u) << d.out;
  const Outcome w = Exec("pipeline/aggscan-worker", {"--once", "--version"}, cwd.path());
  EXPECT_EQ(w.rc, 0) << w.err;
  EXPECT_EQ(w.out.rfind("aggscan-worker ", 0), 0u) << w.out;
  const Outcome a = Exec("cli/aggscan", {"--url", "http://127.0.0.1:1", "--version"}, cwd.path());
  EXPECT_EQ(a.rc, 0) << a.err;
  EXPECT_EQ(a.out.rfind("aggscan ", 0), 0u) << a.out;
  EXPECT_TRUE(Entries(cwd.path()).empty());
}

struct HelpCase {
  std::vector<std::string> words;  // the command, as its usage names it
  std::vector<std::string> rest;   // a line that, without --help, would do something or fail
};

// Every offline command and each of its forms. The rest of each line names
// files in the working directory that the command would create (or would
// read, failing) were it run instead of answering --help.
const std::vector<HelpCase> kCases = {
    {{"selftest"}, {"--config", "rig.toml", "--json"}},
    {{"calibrate"}, {}},
    {{"calibrate", "board"}, {"--out", "board.png", "--dpi", "300"}},
    {{"calibrate", "aruco"}, {"--out", "aruco.pgm", "--config", "rig.toml"}},
    {{"calibrate"}, {"sample", "--out", "calibration.json"}},
    {{"reconstruct"}, {"sample", "--surface", "hull"}},
    {{"morph"}, {"rock.ply", "--json"}},
    {{"morph2d"}, {"rock.png"}},
    {{"sim"}, {}},
    {{"sim", "capture"},
     {"--seed", "1", "--views", "2", "--width", "320", "--height", "240", "--out", "sample"}},
    {{"user"}, {}},
    {{"user", "add"}, {"bob", "--role", "viewer", "--file", "users"}},
    {{"user", "remove"}, {"bob", "--file", "users"}},
    {{"user", "list"}, {"--file", "users"}},
    {{"empty-turntable"}, {}},
    {{"empty-turntable"}, {"sample", "--state-dir", "state"}},
    {{"import"}, {"photos", "--id", "rock-1", "--out", "rock-1"}},
    {{"masks"}, {}},
    {{"masks", "dataset"}, {"--out", "set", "sample"}},
    {{"masks", "train"}, {"--dataset", "set", "--out", "model.onnx"}},
    {{"masks", "eval"}, {"--save", "saved", "sample"}},
    {{"validate"}, {"--count", "1", "--views", "4", "--keep", "kept"}},
    {{"report"}, {"rock-1", "--state-dir", "state", "--pdf", "rock.pdf"}},
    {{"report"}, {"--batch", "week-49", "--spec", "en13383-lma10-60", "--html", "b.html"}},
};

void ExpectHelp(const std::string& rel, const std::vector<std::string>& args,
                const std::string& mention) {
  test::TempDir cwd;
  const Outcome r = Exec(rel, args, cwd.path());
  SCOPED_TRACE(rel + " " + Join(args) + ": stdout '" + r.out + "', stderr '" + r.err + "'");
  EXPECT_EQ(r.rc, 0);
  EXPECT_FALSE(r.out.empty());
  EXPECT_NE(Lower(r.out).find("usage"), std::string::npos);
  // That command's usage, not another's (nor only the list of all of them).
  EXPECT_NE(r.out.find(mention), std::string::npos) << "no mention of '" << mention << "'";
  const std::vector<std::string> left = Entries(cwd.path());
  EXPECT_TRUE(left.empty()) << "it ran: " << left.size() << " file(s) left, the first "
                            << (left.empty() ? "" : left[0]);
}

TEST(HelpVersion, HelpEveryOfflineCommandAnswersHelpAndDoesNothing) {
  for (const HelpCase& c : kCases) {
    for (const std::string flag : {"--help", "-h"}) {
      const std::string mention = "aggscan " + Join(c.words);
      std::vector<std::string> args = c.words;
      args.insert(args.end(), c.rest.begin(), c.rest.end());
      // Last: the options before it are as a user had typed them.
      std::vector<std::string> last = args;
      last.push_back(flag);
      ExpectHelp("cli/aggscan", last, mention);
      // Right after the command word: the rest is not judged either.
      std::vector<std::string> first = c.words;
      first.push_back(flag);
      first.insert(first.end(), c.rest.begin(), c.rest.end());
      ExpectHelp("cli/aggscan", first, mention);
    }
  }
}

TEST(HelpVersion, HelpTheProgramsAnswerHelp) {
  for (const std::string flag : {"--help", "-h"}) {
    ExpectHelp("cli/aggscan", {flag}, "aggscan COMMAND");
    ExpectHelp("daemon/aggscand", {flag}, "aggscand");
    ExpectHelp("daemon/aggscand", {"--port", "0", "--state-dir", "state", flag}, "aggscand");
    ExpectHelp("pipeline/aggscan-worker", {flag}, "aggscan-worker");
    ExpectHelp("pipeline/aggscan-worker", {"--state-dir", "state", "--once", flag},
               "aggscan-worker");
  }
}

}  // namespace
}  // namespace aggscan
