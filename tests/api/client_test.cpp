#include "cli/client.h"

#include <gtest/gtest.h>
#include <stdlib.h>

#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "daemon/http_api.h"
#include "tests/api/fake_control.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using testing::FakeControl;
using testing::UnusedPort;

class ClientTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ::unsetenv("AGGSCAN_URL");
    api_ = std::make_unique<HttpApi>(fake_, "127.0.0.1", 0);
    const Status st = api_->Start();
    ASSERT_TRUE(st.ok()) << st.error().ToString();
    url_ = "http://127.0.0.1:" + std::to_string(api_->port());
  }
  void TearDown() override {
    ::unsetenv("AGGSCAN_URL");
    api_->Stop();
  }

  // Runs the command with --url pointing at the test server.
  int Run(std::vector<std::string> args) {
    args.insert(args.begin(), {"--url", url_});
    return RunBare(args);
  }
  int RunBare(const std::vector<std::string>& args) {
    out_.str("");
    err_.str("");
    return RunClientCommand(args, out_, err_);
  }

  FakeControl fake_;
  std::unique_ptr<HttpApi> api_;
  std::string url_;
  std::ostringstream out_, err_;
};

TEST_F(ClientTest, StatusHumanReadable) {
  ASSERT_EQ(Run({"status"}), kClientExitOk) << err_.str();
  const std::string out = out_.str();
  EXPECT_NE(out.find("state: capturing  sample: rock-12  side 1 view 7/30\n"), std::string::npos)
      << out;
  EXPECT_NE(out.find("camera: ok"), std::string::npos) << out;
  EXPECT_NE(out.find("queue: 2"), std::string::npos) << out;
  EXPECT_NE(out.find("uptime: 1h 02m 03s"), std::string::npos) << out;
  EXPECT_TRUE(err_.str().empty());
}

TEST_F(ClientTest, StatusShowsFault) {
  fake_.status = {{"state", "fault"},
                  {"sample_id", nullptr},
                  {"fault", {{"class", "stalled"}, {"message", "turntable stalled at 96 deg"}}}};
  ASSERT_EQ(Run({"status"}), kClientExitOk);
  EXPECT_NE(out_.str().find("state: fault\n"), std::string::npos) << out_.str();
  EXPECT_NE(out_.str().find("fault: stalled: turntable stalled at 96 deg"), std::string::npos)
      << out_.str();
}

TEST_F(ClientTest, JsonOptionPrintsDaemonJson) {
  ASSERT_EQ(Run({"status", "--json"}), kClientExitOk);
  const json j = json::parse(out_.str(), nullptr, false);
  ASSERT_FALSE(j.is_discarded()) << out_.str();
  EXPECT_EQ(j, fake_.status);

  ASSERT_EQ(Run({"--json", "samples"}), kClientExitOk);
  EXPECT_EQ(json::parse(out_.str(), nullptr, false), fake_.samples);
}

TEST_F(ClientTest, ActionsCallTheDaemon) {
  EXPECT_EQ(Run({"arm", "rock-12"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("armed sample rock-12"), std::string::npos) << out_.str();
  EXPECT_EQ(Run({"press"}), kClientExitOk);
  EXPECT_NE(out_.str().find("state: homing"), std::string::npos) << out_.str();
  EXPECT_EQ(Run({"abort"}), kClientExitOk);
  EXPECT_EQ(Run({"reset"}), kClientExitOk);
  EXPECT_EQ(Run({"arm-calibration"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("armed calibration capture calibration-20260101T100000Z"),
            std::string::npos)
      << out_.str();
  EXPECT_EQ(fake_.Calls(),
            (std::vector<std::string>{"arm:rock-12", "press:api", "abort", "reset", "calibrate"}));
}

TEST_F(ClientTest, SamplesTable) {
  ASSERT_EQ(Run({"samples"}), kClientExitOk);
  std::istringstream lines(out_.str());
  std::string header, row1, row2;
  std::getline(lines, header);
  std::getline(lines, row1);
  std::getline(lines, row2);
  EXPECT_EQ(header.rfind("ID", 0), 0u) << out_.str();
  EXPECT_NE(header.find("STATE"), std::string::npos);
  EXPECT_EQ(row1.rfind("rock-11", 0), 0u) << out_.str();
  EXPECT_NE(row1.find("done"), std::string::npos);
  EXPECT_NE(row2.find("capturing"), std::string::npos);
  // Columns line up: the state column starts at the same offset in every line.
  EXPECT_EQ(header.find("STATE"), row1.find("done"));

  fake_.samples = json::array();
  ASSERT_EQ(Run({"samples"}), kClientExitOk);
  EXPECT_EQ(out_.str(), "no samples\n");
}

TEST_F(ClientTest, ShowSample) {
  ASSERT_EQ(Run({"show", "rock-11"}), kClientExitOk) << err_.str();
  const std::string out = out_.str();
  EXPECT_EQ(out.rfind("sample: rock-11  state: done\n", 0), 0u) << out;
  EXPECT_NE(out.find("views: 30 entries"), std::string::npos) << out;
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"get:rock-11"});
}

TEST_F(ClientTest, ShowSaysWhenAResultIsNotConfidentAndWhy) {
  fake_.sample_result = {{"volume_mm3", 715900.0},
                         {"a_mm", 83.7},
                         {"b_mm", 122.0},
                         {"c_mm", 142.8},
                         {"confident", false},
                         {"quality_flags",
                          {{{"code", "stitch_unconfirmed"},
                            {"reason", "side 2's stitch onto side 1 is not confirmed"}}}}};
  ASSERT_EQ(Run({"show", "rock-11"}), kClientExitOk) << err_.str();
  std::string out = out_.str();
  EXPECT_NE(out.find("  volume       715900.0 mm3 (715.90 cm3)\n"), std::string::npos) << out;
  EXPECT_NE(out.find("  a / b / c    83.7 / 122.0 / 142.8 mm\n"), std::string::npos) << out;
  EXPECT_NE(out.find("quality: NOT CONFIDENT (1 flag(s))"), std::string::npos) << out;
  EXPECT_NE(out.find("  stitch_unconfirmed: side 2's stitch onto side 1 is not confirmed\n"),
            std::string::npos)
      << out;
  fake_.sample_result = {
      {"volume_mm3", 1000.0}, {"confident", true}, {"quality_flags", json::array()}};
  out_.str("");
  ASSERT_EQ(Run({"show", "rock-11"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("quality: confident\n"), std::string::npos) << out_.str();
}

// Every figure the QA engineer reads, in plain decimals, the mass with its
// specific gravity and basis, the 2D summary, the description and every
// warning; a missing specific gravity says how to give one.
TEST_F(ClientTest, ShowPrintsEveryFigureMassAndWarning) {
  fake_.sample_result = {
      {"volume_mm3", 1747490.5},
      {"surface_area_mm2", 73512.25},
      {"a_mm", 101.25},
      {"b_mm", 152.5},
      {"c_mm", 201.75},
      {"fer_3d", 1.9926},
      {"ratio_c_b", 1.3230},
      {"ratio_b_a", 1.5062},
      {"sphericity", 0.8123},
      {"mass_g", 4630.85},
      {"specific_gravity", 2.65},
      {"mass_basis", "bulk-ssd"},
      {"views_2d",
       {{"fer_2d", {{"mean", 1.41}, {"min", 1.02}, {"max", 1.88}, {"cov", 0.185}, {"n", 60}}}}},
      {"warnings", {"side 2 view 7 left out of the model: blurred"}},
      {"software", {{"version", "0.1.0+gabc"}, {"config_sha256", "0123456789abcdef"}}},
      {"confident", true},
      {"quality_flags", json::array()}};
  fake_.sample_meta = {
      {"operator", "M. Rossi"},
      {"lot", "L-7"},
      {"material", {{"name", "granite"}, {"specific_gravity", 2.65}, {"basis", "bulk-ssd"}}}};
  ASSERT_EQ(Run({"show", "rock-11"}), kClientExitOk) << err_.str();
  const std::string out = out_.str();
  for (const char* want :
       {"operator: M. Rossi\n", "lot: L-7\n",
        "material: granite, specific gravity 2.650 (bulk-ssd)\n",
        "  volume       1747490.5 mm3 (1747.49 cm3)\n", "  area         73512.2 mm2\n",
        "  a / b / c    101.2 / 152.5 / 201.8 mm\n",
        "  FER (c/a)    1.993   c/b 1.323   b/a 1.506\n", "  sphericity   0.812\n",
        "  mass         4630.9 g (specific gravity 2.650, bulk-ssd)\n",
        "  2D FER        mean 1.410 (1.020 to 1.880, CoV 18.5 %, 60 views)\n",
        "quality: confident\n", "warnings:\n  - side 2 view 7 left out of the model: blurred\n",
        "computed by: aggscan 0.1.0+gabc, config sha256 0123456789ab\n"}) {
    EXPECT_NE(out.find(want), std::string::npos) << want << "\n---\n" << out;
  }
  EXPECT_EQ(out.find("e+0"), std::string::npos) << out;
  fake_.sample_result.erase("mass_g");
  fake_.sample_result["mass_none"] = "no specific gravity: give the sample's material";
  ASSERT_EQ(Run({"show", "rock-11"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("  mass         - (no specific gravity: give the sample's material)\n"),
            std::string::npos)
      << out_.str();
}

// A captured sample shows where its reconstruction is, with its key figures.
TEST_F(ClientTest, SamplesShowReconstructionStateAndFigures) {
  fake_.samples =
      json::array({{{"id", "rock-1"},
                    {"state", "captured"},
                    {"created_utc", "2026-01-01T10:00:00.000Z"},
                    {"views", 60},
                    {"meta", {{"lot", "L-7"}}},
                    {"reconstruction", {{"state", "done"}}},
                    {"result",
                     {{"volume_mm3", 1747490.5},
                      {"b_mm", 152.5},
                      {"fer_3d", 1.9926},
                      {"sphericity", 0.8123},
                      {"mass_g", 4630.85},
                      {"confident", true},
                      {"quality_flags", json::array()}}}},
                   {{"id", "rock-2"},
                    {"state", "captured"},
                    {"created_utc", "2026-01-01T10:05:00.000Z"},
                    {"views", 60},
                    {"reconstruction", {{"state", "reconstructing"}}}},
                   {{"id", "rock-3"},
                    {"state", "captured"},
                    {"created_utc", "2026-01-01T10:10:00.000Z"},
                    {"views", 60},
                    {"reconstruction", {{"state", "failed"}, {"error", "bad image"}}}}});
  ASSERT_EQ(Run({"samples"}), kClientExitOk) << err_.str();
  std::istringstream lines(out_.str());
  std::string header, r1, r2, r3;
  std::getline(lines, header);
  std::getline(lines, r1);
  std::getline(lines, r2);
  std::getline(lines, r3);
  EXPECT_EQ(r1.substr(header.find("STATE"), 4), "done") << out_.str();
  EXPECT_EQ(r2.substr(header.find("STATE"), 14), "reconstructing") << out_.str();
  EXPECT_EQ(r3.substr(header.find("STATE"), 6), "failed") << out_.str();
  EXPECT_EQ(r1.substr(header.find("LOT"), 3), "L-7") << out_.str();
  EXPECT_EQ(r1.substr(header.find("V cm3"), 6), "1747.5") << out_.str();
  EXPECT_EQ(r1.substr(header.find("MASS kg"), 5), "4.631") << out_.str();
  EXPECT_EQ(r1.substr(header.find("QUALITY"), 9), "confident") << out_.str();
  EXPECT_EQ(r2.substr(header.find("V cm3"), 1), "-") << out_.str();
}

// meta edits the description through PATCH, clears a field with null, and
// refuses what it cannot send.
TEST_F(ClientTest, MetaPatchesTheDescription) {
  ASSERT_EQ(Run({"meta", "rock-11", "--lot", "L-12", "--sg", "2.7", "--sg-basis", "oven-dry",
                 "--clear", "notes"}),
            kClientExitOk)
      << err_.str();
  ASSERT_EQ(fake_.Calls(), std::vector<std::string>{"meta:rock-11:api"});
  EXPECT_EQ(fake_.last_meta_doc,
            (json{{"lot", "L-12"},
                  {"notes", nullptr},
                  {"material", {{"specific_gravity", 2.7}, {"basis", "oven-dry"}}}}));
  EXPECT_EQ(Run({"meta", "rock-11"}), kClientExitUsage);
  EXPECT_NE(err_.str().find("needs something to change"), std::string::npos) << err_.str();
  EXPECT_EQ(Run({"meta", "rock-11", "--sg", "heavy"}), kClientExitUsage);
  EXPECT_NE(err_.str().find("--sg expects a number"), std::string::npos) << err_.str();
  EXPECT_EQ(Run({"meta", "rock-11", "--clear", "volume"}), kClientExitUsage);
  EXPECT_EQ(Run({"arm", "rock-12", "--clear", "lot"}), kClientExitUsage);
  EXPECT_EQ(Run({"status", "--lot", "x"}), kClientExitUsage);
  // The daemon's refusal reaches the user with its message.
  fake_.fail =
      MakeError(ErrorClass::kInvalidArgument, "\"material.specific_gravity\" needs its basis");
  EXPECT_EQ(Run({"meta", "rock-11", "--sg", "2.7"}), kClientExitDaemonError);
  EXPECT_NE(err_.str().find("needs its basis"), std::string::npos) << err_.str();
}

// batch set sends its criteria with PUT, show lists the members as samples
// does, list and delete say what they did; misuse is a usage error.
TEST_F(ClientTest, BatchCommands) {
  ASSERT_EQ(Run({"batch", "set", "week-49", "--lot", "L-7", "--from", "2026-12-01", "--to",
                 "2026-12-05", "--samples", "rock-1,rock-2", "--notes", "north face"}),
            kClientExitOk)
      << err_.str();
  EXPECT_EQ(fake_.batches["week-49"]["lot"], "L-7");
  EXPECT_EQ(fake_.batches["week-49"]["samples"], (json{"rock-1", "rock-2"}));
  EXPECT_EQ(fake_.batches["week-49"]["notes"], "north face");
  fake_.batches["week-49"]["members"] = json::array(
      {{{"id", "rock-1"}, {"state", "captured"}, {"reconstruction", {{"state", "done"}}}}});
  fake_.batches["week-49"]["missing"] = json::array({"rock-2"});
  ASSERT_EQ(Run({"batch", "show", "week-49"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("1 sample(s):\n"), std::string::npos) << out_.str();
  EXPECT_NE(out_.str().find("\nrock-1  "), std::string::npos) << out_.str();
  EXPECT_NE(out_.str().find("listed but not on this rig: rock-2"), std::string::npos) << out_.str();
  ASSERT_EQ(Run({"batch", "list"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("week-49: "), std::string::npos) << out_.str();
  ASSERT_EQ(Run({"batch", "delete", "week-49"}), kClientExitOk) << err_.str();
  EXPECT_FALSE(fake_.batches.contains("week-49"));
  EXPECT_EQ(Run({"batch", "show", "week-49"}), kClientExitDaemonError);
  EXPECT_EQ(Run({"batch"}), kClientExitUsage);
  EXPECT_EQ(Run({"batch", "set", "b"}), kClientExitUsage);
  EXPECT_NE(err_.str().find("needs its samples"), std::string::npos) << err_.str();
  EXPECT_EQ(Run({"batch", "show", "../b"}), kClientExitUsage);
  EXPECT_EQ(Run({"batch", "list", "--lot", "L"}), kClientExitUsage);
  EXPECT_EQ(Run({"samples", "--from", "2026-01-01"}), kClientExitUsage);
}

// reference import: every line checked before anything is sent, then one
// description edit per rock with its volume in mm3; a refused rock is named.
TEST_F(ClientTest, ReferenceImportPatchesEachRock) {
  test::TempDir t;
  const std::string csv = t.path() + "/volumes.csv";
  std::ofstream(csv) << "sample_id,volume_cm3,method\r\nrock-1,155.7,water displacement\r\n"
                        "\"rock-2\", 1747.5 ,\"displacement, ASTM D6473\"\n\n";
  ASSERT_EQ(Run({"reference", "import", csv}), kClientExitOk) << err_.str();
  EXPECT_EQ(out_.str(), "2 reference volume(s) imported\n");
  ASSERT_EQ(fake_.Calls(), (std::vector<std::string>{"meta:rock-1:api", "meta:rock-2:api"}));
  EXPECT_EQ(fake_.last_meta_doc["reference"], (json{{"volume_mm3", 1747500.0},
                                                    {"method", "displacement, ASTM D6473"},
                                                    {"source", "volumes.csv"}}));
  // A bad line anywhere: nothing is sent.
  for (const std::string& bad :
       {std::string("sample,volume_cm3\nrock-1,1\n"),
        std::string("sample_id,volume_cm3\nrock-1,-3\n"),
        std::string("sample_id,volume_cm3\nrock-1,12 cm3\n"),
        std::string("sample_id,volume_cm3\n../x,1\n"), std::string("sample_id,volume_cm3\n")}) {
    std::ofstream(csv) << bad;
    const size_t before = fake_.CallCount();
    EXPECT_EQ(Run({"reference", "import", csv}), kClientExitUsage) << bad;
    EXPECT_EQ(fake_.CallCount(), before) << bad;
  }
  EXPECT_EQ(Run({"reference", "import", t.path() + "/none.csv"}), kClientExitUsage);
  EXPECT_EQ(Run({"reference", "export", csv}), kClientExitUsage);
  // A rock the daemon refuses is named, the others imported.
  std::ofstream(csv) << "sample_id,volume_mm3\nrock-1,155700\n";
  fake_.fail = MakeError(ErrorClass::kNotFound, "no sample \"rock-1\"");
  EXPECT_EQ(Run({"reference", "import", csv}), kClientExitDaemonError);
  EXPECT_NE(err_.str().find("rock-1: no sample"), std::string::npos) << err_.str();
}

TEST_F(ClientTest, StatusListsFailedJobsWithWhatToDo) {
  fake_.status["failed_jobs"] =
      json::array({{{"sample_id", "rock-9"},
                    {"side", 1},
                    {"attempts", 3},
                    {"error", "stage \"masks side 1 view 4\" failed: OpenCV refused its data"},
                    {"updated_utc", "2026-01-01T10:00:00.000Z"}},
                   {{"sample_id", "rock-8"},
                    {"side", 0},
                    {"attempts", 3},
                    {"error", "crashed with SIGABRT (Aborted)"}}});
  fake_.status["failed_jobs_total"] = 5;
  ASSERT_EQ(Run({"status"}), kClientExitOk) << err_.str();
  const std::string out = out_.str();
  EXPECT_NE(
      out.find(
          "failed jobs: 5 (the worker gave up on them; fix the cause, then `aggscan retry ID`)"),
      std::string::npos)
      << out;
  EXPECT_NE(out.find("  rock-9 side 1, 3 attempt(s): stage \"masks side 1 view 4\" failed: OpenCV "
                     "refused its data\n"),
            std::string::npos)
      << out;
  EXPECT_NE(out.find("  rock-8 sample stage, 3 attempt(s): crashed with SIGABRT (Aborted)\n"),
            std::string::npos)
      << out;
  EXPECT_NE(out.find("  ... and 3 older\n"), std::string::npos) << out;
}

TEST_F(ClientTest, RetryPostsToTheSample) {
  ASSERT_EQ(Run({"retry", "rock-9"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("sample rock-9: 1 failed job(s) back in the worker's queue"),
            std::string::npos)
      << out_.str();
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"retry:rock-9"});
  EXPECT_EQ(Run({"retry"}), kClientExitUsage);
  EXPECT_NE(err_.str().find("retry needs a sample id"), std::string::npos) << err_.str();
  fake_.fail = MakeError(ErrorClass::kNotFound, "sample rock-9 has no failed job to retry");
  EXPECT_EQ(Run({"retry", "rock-9"}), kClientExitDaemonError);
  EXPECT_NE(err_.str().find("retry failed: sample rock-9 has no failed job to retry [not_found]"),
            std::string::npos)
      << err_.str();
}

TEST_F(ClientTest, DaemonErrorExits1WithItsMessage) {
  fake_.fail =
      MakeError(ErrorClass::kInvalidState, "cannot arm while capturing rock-12; abort first");
  EXPECT_EQ(Run({"arm", "rock-13"}), kClientExitDaemonError);
  EXPECT_NE(err_.str().find("cannot arm while capturing rock-12; abort first"), std::string::npos)
      << err_.str();
  EXPECT_TRUE(out_.str().empty());

  // --json: the error document goes to stdout for scripts, still exit 1.
  EXPECT_EQ(Run({"--json", "show", "rock-13"}), kClientExitDaemonError);
  const json j = json::parse(out_.str(), nullptr, false);
  ASSERT_TRUE(j.is_object()) << out_.str();
  EXPECT_EQ(j["error"]["class"], "invalid_state");
}

TEST_F(ClientTest, UsageErrorsExit2) {
  const std::vector<std::vector<std::string>> cases = {
      {},
      {"frobnicate"},
      {"arm"},
      {"show"},
      {"arm", "a", "b"},
      {"status", "extra"},
      {"arm", "../etc"},
      {"show", "a/b"},
      {"arm", std::string(65, 'x')},
      {"--bogus", "status"},
      {"status", "--url"},
      {"--url", "ftp://127.0.0.1:8470", "status"},
      {"--url", "127.0.0.1:8470", "status"},
      {"--url", "http://127.0.0.1:99999", "status"},
  };
  for (const auto& args : cases) {
    std::string joined;
    for (const auto& a : args) joined += a + " ";
    EXPECT_EQ(RunBare(args), kClientExitUsage) << joined;
    EXPECT_FALSE(err_.str().empty()) << joined;
  }
  EXPECT_EQ(fake_.CallCount(), 0u);
}

TEST_F(ClientTest, HelpExits0) {
  EXPECT_EQ(RunBare({"--help"}), kClientExitOk);
  EXPECT_NE(out_.str().find("aggscan [--url URL] [--json] status"), std::string::npos);
}

TEST_F(ClientTest, UnreachableDaemonExits3) {
  const std::string dead = "http://127.0.0.1:" + std::to_string(UnusedPort());
  EXPECT_EQ(RunBare({"--url", dead, "status"}), kClientExitUnreachable);
  EXPECT_EQ(err_.str(),
            "aggscan: cannot reach aggscand at " + dead +
                ": connection refused — is the service running? (systemctl status aggscand)\n");
  EXPECT_EQ(RunBare({"--url=" + dead, "--json", "press"}), kClientExitUnreachable);
  EXPECT_TRUE(out_.str().empty());
}

TEST_F(ClientTest, StatusNamesTheStateOfAnUnhealthyDevice) {
  fake_.status["devices"] = {{"turntable",
                              {{"healthy", false},
                               {"state", "timeout"},
                               {"message", "turntable: no answer from Modbus unit 1"}}}};
  ASSERT_EQ(Run({"status"}), kClientExitOk) << err_.str();
  EXPECT_NE(
      out_.str().find("turntable: UNHEALTHY timeout (turntable: no answer from Modbus unit 1)"),
      std::string::npos)
      << out_.str();
}

TEST_F(ClientTest, SelftestWithoutDaemonSaysHowToStartIt) {
  const std::string dead = "http://127.0.0.1:" + std::to_string(UnusedPort());
  EXPECT_EQ(RunBare({"--url", dead, "selftest"}), kClientExitUnreachable);
  EXPECT_NE(err_.str().find("cannot reach aggscand at " + dead + ": connection refused"),
            std::string::npos)
      << err_.str();
  EXPECT_NE(err_.str().find("start it (systemctl start aggscand"), std::string::npos) << err_.str();
  EXPECT_TRUE(out_.str().empty());
}

TEST_F(ClientTest, EnvironmentUrlHonouredAndFlagWins) {
  ::setenv("AGGSCAN_URL", url_.c_str(), 1);
  EXPECT_EQ(RunBare({"status"}), kClientExitOk) << err_.str();
  const std::string dead = "http://127.0.0.1:" + std::to_string(UnusedPort());
  ::setenv("AGGSCAN_URL", dead.c_str(), 1);
  EXPECT_EQ(RunBare({"status"}), kClientExitUnreachable);
  EXPECT_NE(err_.str().find(dead), std::string::npos);
  EXPECT_EQ(RunBare({"--url", url_, "status"}), kClientExitOk);
}

TEST_F(ClientTest, UrlWithTrailingSlashWorks) {
  EXPECT_EQ(RunBare({"--url", url_ + "/", "status"}), kClientExitOk) << err_.str();
}

TEST(ClientCommands, IsClientCommandAndUsage) {
  for (const char* w : {"status", "arm", "press", "abort", "reset", "samples", "show"}) {
    EXPECT_TRUE(IsClientCommand(w)) << w;
  }
  for (const char* w : {"", "run", "--json", "statuses", "Status"})
    EXPECT_FALSE(IsClientCommand(w)) << w;
  std::ostringstream usage;
  PrintClientUsage(usage);
  for (const char* w :
       {"status", "arm ID", "press", "abort", "reset", "samples", "show ID", "--url", "--json"}) {
    EXPECT_NE(usage.str().find(w), std::string::npos) << w;
  }
}

TEST_F(ClientTest, SelftestExitCodeFollowsDeviceHealth) {
  ASSERT_EQ(Run({"selftest"}), kClientExitOk) << err_.str();
  EXPECT_NE(out_.str().find("camera: ok"), std::string::npos) << out_.str();
  EXPECT_NE(out_.str().find("all 1 devices ok"), std::string::npos) << out_.str();
  fake_.health = {
      {"status", "unhealthy"},
      {"devices",
       {{"camera", {{"state", "ok"}, {"healthy", true}, {"message", "ok"}}},
        {"turntable",
         {{"state", "device_missing"},
          {"healthy", false},
          {"backend", "modbus-rtu"},
          {"message", "turntable: serial device /dev/ttyUSB0 not found — check the adapter"},
          {"retries", 3},
          {"next_retry_in_s", 4.0},
          {"last_ok_utc", nullptr}}}}}};
  out_.str("");
  ASSERT_EQ(Run({"selftest"}), kClientExitUnhealthy) << err_.str();
  const std::string o = out_.str();
  EXPECT_NE(o.find("turntable: FAIL device_missing [modbus-rtu]"), std::string::npos) << o;
  EXPECT_NE(o.find("/dev/ttyUSB0 not found"), std::string::npos) << o;
  EXPECT_NE(o.find("failed attempts: 3, next retry in 4.0 s, last ok: never"), std::string::npos)
      << o;
  EXPECT_NE(o.find("1 of 2 devices unhealthy"), std::string::npos) << o;
  out_.str("");
  ASSERT_EQ(Run({"--json", "selftest"}), kClientExitUnhealthy) << err_.str();
  EXPECT_EQ(json::parse(out_.str())["devices"]["turntable"]["state"], "device_missing");
}

}  // namespace
}  // namespace aggscan
