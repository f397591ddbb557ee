// Checks a state directory after a power cut (run inside the VM of
// power_cut_vm.py, after e2fsck and mount replayed the journal):
//
//   power_cut_check files STATE_DIR EXPECT_FILE   before aggscand starts
//   power_cut_check queue STATE_DIR               after aggscand's start-up recovery
//
// files: every file under a final name is complete (a sidecar implies an
// image that decodes without a libjpeg warning and has the sidecar's size; a
// manifest lists only views whose image and sidecar exist with the listed
// byte size; every JSON parses; every PNG decodes; a temp file is counted,
// never read as a final one); every view, manifest and captured state that
// EXPECT_FILE says the guest reported as stored before the cut is there; the
// queue passes SQLite's integrity check.
//   EXPECT_FILE lines: "view ID SIDE VIEW", "moved ID SIDE VIEW" (a view of a
//   side shot again since: in one of its sideN.interrupted-K directories),
//   "manifest ID SIDE", "captured ID".
// queue: every side with a manifest and every captured sample has a job.
//
// Prints one "problem: ..." line per finding and a summary line; exit status
// 0 when nothing was found, 1 otherwise, 2 on usage errors.
#include <sqlite3.h>
#include <turbojpeg.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <sstream>
#include <string>
#include <vector>

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

int g_problems = 0;
void Problem(const std::string& what) {
  ++g_problems;
  std::printf("problem: %s\n", what.c_str());
  std::fflush(stdout);
}

std::string ReadAll(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

bool IsTemp(const fs::path& p) { return p.filename().string().rfind(".tmp-", 0) == 0; }

// A JPEG is complete when libjpeg-turbo decodes it without even a warning: a
// truncated file only warns ("Premature end of JPEG file").
bool DecodeJpeg(const std::string& bytes, int* w, int* h, std::string* why) {
  tjhandle tj = tjInitDecompress();
  int ss = 0, cs = 0;
  bool ok = tjDecompressHeader3(tj, reinterpret_cast<const unsigned char*>(bytes.data()),
                                bytes.size(), w, h, &ss, &cs) == 0;
  if (ok) {
    std::vector<unsigned char> px(static_cast<size_t>(*w) * *h * 3);
    ok = tjDecompress2(tj, reinterpret_cast<const unsigned char*>(bytes.data()), bytes.size(),
                       px.data(), *w, 0, *h, TJPF_RGB, 0) == 0;
  }
  if (!ok || tjGetErrorCode(tj) == TJERR_WARNING) {
    *why = tjGetErrorStr2(tj);
    ok = false;
  }
  tjDestroy(tj);
  return ok;
}

json ParseJson(const fs::path& p, int* n_json) {
  ++*n_json;
  json j = json::parse(ReadAll(p), nullptr, false);
  if (j.is_discarded())
    Problem("not valid JSON: " + p.string() + " (" + std::to_string(fs::file_size(p)) + " bytes)");
  return j;
}

struct Counts {
  int samples = 0, views = 0, orphan_images = 0, manifests = 0, json = 0, png = 0, temp = 0,
      other = 0;
  int expected = 0;
};

// One side directory (sideN or sideN.interrupted-K).
void CheckSide(const fs::path& dir, Counts& c) {
  std::map<std::string, uintmax_t> complete;  // image name -> size, views with a sidecar
  for (const auto& e : fs::directory_iterator(dir)) {
    const fs::path p = e.path();
    const std::string name = p.filename().string();
    if (IsTemp(p)) {
      ++c.temp;
      continue;
    }
    int v = -1;
    char ext[8] = {0};
    if (std::sscanf(name.c_str(), "view_%d.%4s", &v, ext) != 2) continue;  // manifest: below
    if (std::string(ext) == "json") {
      json car = ParseJson(p, &c.json);
      fs::path img = p;
      img.replace_extension(".jpg");
      if (!fs::exists(img)) {
        Problem("sidecar without its image: " + p.string());
        continue;
      }
      ++c.views;
      int w = 0, h = 0;
      std::string why;
      const std::string bytes = ReadAll(img);
      if (!DecodeJpeg(bytes, &w, &h, &why)) {
        Problem("image of a complete view does not decode: " + img.string() + " (" +
                std::to_string(bytes.size()) + " bytes): " + why);
      } else if (car.is_object() && (car.value("width", -1) != w || car.value("height", -1) != h)) {
        Problem("image " + img.string() + " is " + std::to_string(w) + "x" + std::to_string(h) +
                ", its sidecar says " + std::to_string(car.value("width", -1)) + "x" +
                std::to_string(car.value("height", -1)));
      }
      if (car.is_object() && car.value("view", -1) != v)
        Problem("sidecar " + p.string() + " names another view");
      complete[img.filename().string()] = bytes.size();
    } else if (std::string(ext) == "jpg") {
      fs::path car = p;
      car.replace_extension(".json");
      if (fs::exists(car)) continue;  // checked with its sidecar
      // An image whose sidecar never landed is not a stored view, but under
      // its final name it must still be whole.
      ++c.orphan_images;
      int w = 0, h = 0;
      std::string why;
      const std::string bytes = ReadAll(p);
      if (!DecodeJpeg(bytes, &w, &h, &why)) {
        Problem("image under its final name does not decode: " + p.string() + " (" +
                std::to_string(bytes.size()) + " bytes): " + why);
      }
    }
  }
  const fs::path man = dir / "manifest.json";
  if (!fs::exists(man)) return;
  ++c.manifests;
  json m = ParseJson(man, &c.json);
  if (!m.is_object() || !m.contains("views") || !m["views"].is_array()) {
    Problem("manifest without a views list: " + man.string());
    return;
  }
  for (const auto& v : m["views"]) {
    const std::string img = v.value("image", "");
    const auto it = complete.find(img);
    if (it == complete.end()) {
      Problem("manifest " + man.string() + " lists " + img +
              ", which has no complete image and sidecar");
    } else if (static_cast<int64_t>(it->second) != v.value("bytes", int64_t{-1})) {
      Problem("manifest " + man.string() + " lists " + img + " with " +
              std::to_string(v.value("bytes", -1)) + " bytes, the file has " +
              std::to_string(it->second));
    }
  }
  if (m["views"].size() != complete.size()) {
    Problem("manifest " + man.string() + " lists " + std::to_string(m["views"].size()) +
            " views, the side has " + std::to_string(complete.size()) + " complete ones");
  }
}

// Everything else in a sample: JSON parses, PNG decodes, temp files counted.
void CheckTree(const fs::path& dir, Counts& c) {
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    const fs::path& p = e.path();
    if (IsTemp(p)) {
      ++c.temp;
    } else if (p.extension() == ".json") {
      ParseJson(p, &c.json);
    } else if (p.extension() == ".png") {
      ++c.png;
      std::string bytes = ReadAll(p);
      cv::Mat m = cv::imdecode(cv::Mat(1, static_cast<int>(bytes.size()), CV_8U, bytes.data()),
                               cv::IMREAD_UNCHANGED);
      if (m.empty()) Problem("PNG under its final name does not decode: " + p.string());
    } else {
      ++c.other;
    }
  }
}

int CheckFiles(const fs::path& state, const std::string& expect_path) {
  Counts c;
  const fs::path samples = state / "samples";
  if (fs::exists(samples)) {
    for (const auto& s : fs::directory_iterator(samples)) {
      if (IsTemp(s.path())) {
        ++c.temp;
        continue;
      }
      if (!s.is_directory()) continue;
      ++c.samples;
      for (const auto& e : fs::directory_iterator(s.path())) {
        const std::string name = e.path().filename().string();
        if (IsTemp(e.path())) {
          ++c.temp;
        } else if (e.is_directory() && name.rfind("side", 0) == 0) {
          CheckSide(e.path(), c);
        } else if (e.is_directory()) {
          CheckTree(e.path(), c);
        } else if (e.path().extension() == ".json") {
          json j = ParseJson(e.path(), &c.json);
          if (name == "sample.json" && j.is_object() && !j.contains("state")) {
            Problem("sample record without a state: " + e.path().string());
          }
        } else {
          ++c.other;
        }
      }
    }
  }
  std::ifstream ex(expect_path);
  std::string line;
  while (std::getline(ex, line)) {
    std::istringstream ls(line);
    std::string kind, id;
    int side = 0, view = 0;
    ls >> kind >> id;
    if (kind.empty()) continue;
    ++c.expected;
    const fs::path sd = samples / id;
    if (kind == "view") {
      ls >> side >> view;
      char stem[32];
      std::snprintf(stem, sizeof stem, "view_%03d", view);
      const fs::path base = sd / ("side" + std::to_string(side)) / stem;
      if (!fs::exists(base.string() + ".jpg") || !fs::exists(base.string() + ".json")) {
        Problem("view reported stored before the cut is missing: " + base.string() + ".jpg/.json");
      }
    } else if (kind == "moved") {
      ls >> side >> view;
      char stem[32];
      std::snprintf(stem, sizeof stem, "view_%03d", view);
      const std::string prefix = "side" + std::to_string(side) + ".interrupted-";
      bool found = false;
      if (fs::exists(sd)) {
        for (const auto& e : fs::directory_iterator(sd)) {
          const fs::path base = e.path() / stem;
          found =
              found || (e.path().filename().string().rfind(prefix, 0) == 0 &&
                        fs::exists(base.string() + ".jpg") && fs::exists(base.string() + ".json"));
        }
      }
      if (!found)
        Problem("view reported stored before the cut, then moved aside, is missing: " + id +
                " side " + std::to_string(side) + " " + stem);
    } else if (kind == "manifest") {
      ls >> side;
      if (!fs::exists(sd / ("side" + std::to_string(side)) / "manifest.json")) {
        Problem("manifest reported written before the cut is missing: " + id + " side " +
                std::to_string(side));
      }
    } else if (kind == "captured") {
      json rec = json::parse(ReadAll(sd / "sample.json"), nullptr, false);
      if (!rec.is_object() || rec.value("state", "") != "captured") {
        Problem("sample reported captured before the cut is not: " + id + " state " +
                (rec.is_object() ? rec.value("state", "?") : std::string("unreadable")));
      }
    } else {
      Problem("unknown expectation line: " + line);
    }
  }
  // The queue: SQLite's own check after its WAL recovery.
  const fs::path db = state / "queue.db";
  int jobs = -1;
  if (fs::exists(db)) {
    sqlite3* h = nullptr;
    if (sqlite3_open_v2(db.c_str(), &h, SQLITE_OPEN_READWRITE, nullptr) != SQLITE_OK) {
      Problem(std::string("cannot open the queue: ") + sqlite3_errmsg(h));
    } else {
      sqlite3_busy_timeout(h, 10000);
      sqlite3_stmt* st = nullptr;
      sqlite3_prepare_v2(h, "PRAGMA integrity_check", -1, &st, nullptr);
      std::string res;
      while (sqlite3_step(st) == SQLITE_ROW)
        res += reinterpret_cast<const char*>(sqlite3_column_text(st, 0));
      sqlite3_finalize(st);
      if (res != "ok") Problem("queue integrity_check: " + res + " (" + sqlite3_errmsg(h) + ")");
      if (sqlite3_prepare_v2(h, "SELECT COUNT(*) FROM jobs", -1, &st, nullptr) == SQLITE_OK &&
          sqlite3_step(st) == SQLITE_ROW) {
        jobs = sqlite3_column_int(st, 0);
      }
      sqlite3_finalize(st);
    }
    sqlite3_close(h);
  }
  std::printf(
      "check files: samples=%d views=%d orphan_images=%d manifests=%d json=%d png=%d other=%d "
      "temp=%d "
      "expected=%d jobs=%d problems=%d\n",
      c.samples, c.views, c.orphan_images, c.manifests, c.json, c.png, c.other, c.temp, c.expected,
      jobs, g_problems);
  return g_problems == 0 ? 0 : 1;
}

int CheckQueue(const fs::path& state) {
  std::set<std::pair<std::string, int>> jobs;
  sqlite3* h = nullptr;
  if (sqlite3_open_v2((state / "queue.db").c_str(), &h, SQLITE_OPEN_READONLY, nullptr) !=
      SQLITE_OK) {
    Problem(std::string("cannot open the queue: ") + sqlite3_errmsg(h));
    sqlite3_close(h);
    return 1;
  }
  sqlite3_busy_timeout(h, 10000);
  sqlite3_stmt* st = nullptr;
  sqlite3_prepare_v2(h, "SELECT sample_id, side FROM jobs", -1, &st, nullptr);
  while (sqlite3_step(st) == SQLITE_ROW) {
    jobs.emplace(reinterpret_cast<const char*>(sqlite3_column_text(st, 0)),
                 sqlite3_column_int(st, 1));
  }
  sqlite3_finalize(st);
  sqlite3_close(h);
  int needed = 0;
  for (const auto& s : fs::directory_iterator(state / "samples")) {
    if (!s.is_directory() || IsTemp(s.path())) continue;
    const std::string id = s.path().filename().string();
    json rec = json::parse(ReadAll(s.path() / "sample.json"), nullptr, false);
    const int sides = rec.is_object() && rec.contains("plan") ? rec["plan"].value("sides", 0) : 0;
    for (int side = 1; side <= sides; ++side) {
      if (!fs::exists(s.path() / ("side" + std::to_string(side)) / "manifest.json")) continue;
      ++needed;
      if (!jobs.count({id, side}))
        Problem("side " + std::to_string(side) + " of " + id + " has a manifest but no job");
    }
    if (rec.is_object() && rec.value("state", "") == "captured") {
      ++needed;
      if (!jobs.count({id, 0})) Problem("sample " + id + " is captured but has no sample job");
    }
  }
  std::printf("check queue: jobs=%zu needed=%d problems=%d\n", jobs.size(), needed, g_problems);
  return g_problems == 0 ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  const std::string mode = argc > 1 ? argv[1] : "";
  try {
    if (mode == "files" && argc == 4) return CheckFiles(argv[2], argv[3]);
    if (mode == "queue" && argc == 3) return CheckQueue(argv[2]);
  } catch (const std::exception& e) {
    Problem(std::string("checker stopped: ") + e.what());
    return 1;
  }
  std::fprintf(stderr, "usage: %s files STATE_DIR EXPECT_FILE | queue STATE_DIR\n", argv[0]);
  return 2;
}
