#include "store/library_csv.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <initializer_list>

#include "common/clock.h"
#include "common/fsutil.h"
#include "store/layout.h"
#include "store/sample_meta.h"

namespace aggscan::library_csv {

using nlohmann::json;

namespace {

// The value at a path of nested objects, or null.
json At(const json& j, std::initializer_list<const char*> path) {
  const json* p = &j;
  for (const char* k : path) {
    if (!p->is_object() || !p->contains(k)) return json();
    p = &(*p)[k];
  }
  return *p;
}

// A spreadsheet reads "1747490.5" as a number and shows it; "1.74749e+06"
// loses digits. Empty when the figure is absent or not finite.
std::string Num(const json& v, int decimals) {
  if (!v.is_number()) return "";
  const double x = v.get<double>();
  if (!std::isfinite(x)) return "";
  char b[64];
  std::snprintf(b, sizeof b, "%.*f", decimals, x);
  return b;
}

// RFC 4180: a field with a comma, quote or line break is quoted, quotes doubled.
std::string Text(const json& v) {
  if (!v.is_string()) return "";
  std::string s = v.get<std::string>();
  if (s.find_first_of(",\"\r\n") == std::string::npos) return s;
  std::string q = "\"";
  for (char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

}  // namespace

std::vector<std::string> SplitLine(const std::string& line) {
  std::vector<std::string> out(1);
  bool quoted = false;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quoted) {
      if (c == '"' && i + 1 < line.size() && line[i + 1] == '"') {
        out.back() += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        out.back() += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      out.emplace_back();
    } else if (c != '\r' && c != '\n') {
      out.back() += c;
    }
  }
  return out;
}

std::string Header() {
  return "sample_id,created_utc,volume_mm3,surface_area_mm2,a_mm,b_mm,c_mm,fer_3d,ratio_c_b,"
         "ratio_b_a,sphericity,mass_g,specific_gravity,sg_basis,material,operator,lot,"
         "fer_2d_mean,fer_2d_min,fer_2d_max,fer_2d_cov,circularity_mean,views,poses_method,"
         "stitch_method,surface_method,stitch_rms_mm,silhouette_iou_mean,silhouette_iou_min,"
         "total_s,confident,quality_flags,warnings,software_version,config_sha256\n";
}

std::string Row(const json& m, const json& meta) {
  const json d3 = At(m, {"morphology_3d"});
  std::string row = Text(At(m, {"sample_id"})) + "," + Text(At(m, {"created_utc"}));
  for (const auto& [k, dec] :
       std::initializer_list<std::pair<const char*, int>>{{"volume_mm3", 1},
                                                          {"surface_area_mm2", 1},
                                                          {"a_mm", 2},
                                                          {"b_mm", 2},
                                                          {"c_mm", 2},
                                                          {"fer_3d", 4},
                                                          {"ratio_c_b", 4},
                                                          {"ratio_b_a", 4},
                                                          {"sphericity", 4}}) {
    row += "," + Num(At(d3, {k}), dec);
  }
  const json vol = At(d3, {"volume_mm3"});
  const sample_meta::Mass mass =
      sample_meta::MassOf(vol.is_number() ? vol.get<double>() : 0.0, meta);
  row += "," + (mass.grams ? Num(*mass.grams, 1) : std::string());
  row += "," + (mass.grams ? Num(mass.specific_gravity, 3) : std::string());
  row += "," + (mass.grams ? Text(json(mass.basis)) : std::string());
  row += "," + Text(At(meta, {"material", "name"})) + "," + Text(At(meta, {"operator"})) + "," +
         Text(At(meta, {"lot"}));
  const json fer2 = At(m, {"stats_2d", "overall", "fer_2d"});
  row += "," + Num(At(fer2, {"mean"}), 4) + "," + Num(At(fer2, {"min"}), 4) + "," +
         Num(At(fer2, {"max"}), 4) + "," + Num(At(fer2, {"cov"}), 4);
  row += "," + Num(At(m, {"stats_2d", "overall", "circularity", "mean"}), 4);
  const json views = At(m, {"views_2d"});
  row += "," + std::to_string(views.is_array() ? views.size() : 0);
  for (const char* k : {"poses", "stitch", "surface"}) row += "," + Text(At(m, {"methods", k}));
  row += "," + Num(At(m, {"quality", "stitch_rms_mm"}), 3) + "," +
         Num(At(m, {"quality", "silhouette_iou_mean"}), 4) + "," +
         Num(At(m, {"quality", "silhouette_iou_min"}), 4);
  row += "," + Num(At(m, {"timings_s", "total"}), 1);
  const json q = At(m, {"quality"});
  const json flags = At(q, {"flags"});
  const json confident = At(q, {"confident"});
  row +=
      std::string(",") +
      (confident.is_boolean() && confident.get<bool>() && flags.is_array() && flags.empty() ? "yes"
                                                                                            : "no");
  // Codes joined by ';': one field however many.
  std::string codes;
  for (const json& f : flags.is_array() ? flags : json::array()) {
    if (f.is_object() && f.contains("code") && f["code"].is_string())
      codes += (codes.empty() ? "" : ";") + f["code"].get<std::string>();
  }
  row += "," + Text(json(codes));
  std::string warnings;
  const json w = At(m, {"warnings"});
  for (const json& e : w.is_array() ? w : json::array()) {
    if (e.is_string()) warnings += (warnings.empty() ? "" : " | ") + e.get<std::string>();
  }
  row += "," + Text(json(warnings));
  row +=
      "," + Text(At(m, {"software", "version"})) + "," + Text(At(m, {"software", "config_sha256"}));
  return row + "\n";
}

Status Upsert(const std::string& state_dir, const std::string& sample_id, const std::string& row) {
  if (state_dir.empty()) return OkStatus();
  const std::string path = state_dir + "/" + layout::kLibraryCsv;
  const std::string lock_path = path + ".lock";
  const int lock = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (lock < 0) {
    return MakeError(ErrorClass::kIo, "cannot open " + lock_path + ": " + std::strerror(errno));
  }
  struct Unlock {
    int fd;
    ~Unlock() { ::close(fd); }  // closing releases the lock
  } unlock{lock};
  while (::flock(lock, LOCK_EX) != 0) {
    if (errno != EINTR)
      return MakeError(ErrorClass::kIo, "cannot lock " + lock_path + ": " + std::strerror(errno));
  }
  std::string text;
  if (PathExists(path)) {
    auto t = ReadFile(path);
    if (!t) return t.error();
    text = *t;
    if (text.compare(0, Header().size(), Header()) != 0) {
      // Written with other columns (an older release): kept beside under a
      // new name, and a new library begins, so no row is mixed or lost.
      const std::string kept = state_dir + "/library-" + NowUtcString() + ".csv";
      if (Status s = RenameDurable(path, kept); !s) return s;
      text = Header();
    } else if (const size_t at = text.find("\n" + sample_id + ","); at != std::string::npos) {
      // The sample's row replaced in place (reconstructed again, or its
      // description edited); the same row again changes nothing.
      const size_t end = text.find('\n', at + 1);
      const size_t len = (end == std::string::npos ? text.size() : end + 1) - (at + 1);
      if (text.compare(at + 1, len, row) == 0) return OkStatus();
      text.replace(at + 1, len, row);
      return WriteFileAtomic(path, std::string_view(text));
    }
  } else {
    text = Header();
  }
  text += row;
  return WriteFileAtomic(path, std::string_view(text));
}

}  // namespace aggscan::library_csv
