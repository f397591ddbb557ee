#include "cli/client.h"

#include <fcntl.h>
#include <httplib.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string_view>

#include "common/error.h"
#include "store/layout.h"
#include "store/library_csv.h"

namespace aggscan {

namespace {

using json = nlohmann::json;

constexpr time_t kConnectTimeoutSec = 3;
// Arm/press wait for the daemon's event loop, which may be busy homing.
constexpr time_t kReadTimeoutSec = 30;
constexpr int kProbeTimeoutMs = 2000;
// `show`: arrays of records longer than this are summarised (--json has all).
constexpr size_t kMaxListedRecords = 6;
constexpr size_t kMaxInlineValues = 12;
constexpr const char* kServiceHint = " — is the service running? (systemctl status aggscand)";

struct Target {
  std::string url;     // as given, for messages
  std::string origin;  // scheme://host[:port] for httplib
  std::string host;    // without brackets, for the connect probe
  int port = 0;
  std::string prefix;  // path prefix (reverse proxy), no trailing '/'
};

std::optional<Target> ParseUrl(const std::string& url, std::string* why) {
  Target t;
  t.url = url;
  const size_t sep = url.find("://");
  if (sep == std::string::npos) {
    *why = "URL must start with http:// or https://";
    return std::nullopt;
  }
  const std::string scheme = url.substr(0, sep);
  if (scheme != "http" && scheme != "https") {
    *why = "unsupported scheme \"" + scheme + "\": use http:// or https://";
    return std::nullopt;
  }
  std::string rest = url.substr(sep + 3);
  const size_t slash = rest.find('/');
  std::string authority = rest.substr(0, slash);
  if (slash != std::string::npos) t.prefix = rest.substr(slash);
  while (!t.prefix.empty() && t.prefix.back() == '/') t.prefix.pop_back();
  if (t.prefix.find_first_of("?# ") != std::string::npos) {
    *why = "URL must not contain a query, fragment or spaces";
    return std::nullopt;
  }
  t.port = scheme == "https" ? 443 : 80;
  std::string port_text;
  if (!authority.empty() && authority[0] == '[') {
    const size_t close = authority.find(']');
    if (close == std::string::npos) {
      *why = "unterminated [ in the host";
      return std::nullopt;
    }
    t.host = authority.substr(1, close - 1);
    if (close + 1 < authority.size()) {
      if (authority[close + 1] != ':') {
        *why = "unexpected text after ]";
        return std::nullopt;
      }
      port_text = authority.substr(close + 2);
    }
  } else {
    const size_t colon = authority.find(':');
    t.host = authority.substr(0, colon);
    if (colon != std::string::npos) port_text = authority.substr(colon + 1);
  }
  if (t.host.empty() || t.host.find_first_of("@ ") != std::string::npos) {
    *why = "missing or invalid host";
    return std::nullopt;
  }
  if (!port_text.empty()) {
    const bool digits =
        port_text.size() <= 5 && std::all_of(port_text.begin(), port_text.end(), [](char c) {
          return std::isdigit(static_cast<unsigned char>(c));
        });
    const int port = digits ? std::atoi(port_text.c_str()) : -1;
    if (port < 1 || port > 65535) {
      *why = "invalid port \"" + port_text + "\"";
      return std::nullopt;
    }
    t.port = port;
  }
  const bool v6 = t.host.find(':') != std::string::npos;
  t.origin = scheme + "://" + (v6 ? "[" + t.host + "]" : t.host) + ":" + std::to_string(t.port);
  return t;
}

std::string LowerFirst(std::string s) {
  if (!s.empty()) s[0] = static_cast<char>(std::tolower(static_cast<unsigned char>(s[0])));
  return s;
}

// cpp-httplib says only "Connection" when connecting fails; connect once more
// by hand to tell "refused" from "timed out" or "no route to host".
std::string ProbeConnect(const std::string& host, int port) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* list = nullptr;
  const int rc = getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &list);
  if (rc != 0) return std::string("cannot resolve host: ") + gai_strerror(rc);
  int err = 0;
  for (addrinfo* ai = list; ai != nullptr; ai = ai->ai_next) {
    const int fd =
        ::socket(ai->ai_family, ai->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, ai->ai_protocol);
    if (fd < 0) {
      err = errno;
      continue;
    }
    err = 0;
    if (::connect(fd, ai->ai_addr, ai->ai_addrlen) != 0) {
      err = errno;
      if (err == EINPROGRESS) {
        pollfd p{fd, POLLOUT, 0};
        const int n = ::poll(&p, 1, kProbeTimeoutMs);
        if (n == 0) {
          err = ETIMEDOUT;
        } else {
          socklen_t len = sizeof err;
          if (n < 0 || ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len) != 0) err = errno;
        }
      }
    }
    ::close(fd);
    if (err == 0) break;
  }
  freeaddrinfo(list);
  if (err == 0) return "connection failed";
  return LowerFirst(std::strerror(err));
}

std::string TransportError(const Target& t, httplib::Error e) {
  std::string why;
  switch (e) {
    case httplib::Error::Connection:
      why = ProbeConnect(t.host, t.port);
      break;
    case httplib::Error::ConnectionTimeout:
      why = "connection timed out";
      break;
    case httplib::Error::Read:
      why = "connection lost or no answer within " + std::to_string(kReadTimeoutSec) + " s";
      break;
    case httplib::Error::Write:
      why = "could not send the request";
      break;
    default:
      why = LowerFirst(httplib::to_string(e));
      break;
  }
  return "cannot reach aggscand at " + t.url + ": " + why + kServiceHint;
}

// Text from the daemon, made safe for a terminal.
std::string Clean(std::string_view s) {
  std::string out;
  for (unsigned char c : s) {
    if (c < 0x20 || c == 0x7f) {
      out += c == '\t' ? ' ' : '?';
    } else {
      out += static_cast<char>(c);
    }
  }
  return out;
}

std::string Scalar(const json& v) {
  if (v.is_null()) return "-";
  if (v.is_string()) return Clean(v.get<std::string>());
  return v.dump(-1, ' ', false, json::error_handler_t::replace);
}

std::string FieldText(const json& obj, const char* key) {
  if (!obj.is_object()) return "-";
  const auto it = obj.find(key);
  if (it == obj.end()) return "-";
  if (it->is_array()) {
    std::string s;
    for (const auto& e : *it) s += (s.empty() ? "" : ",") + Scalar(e);
    return s.empty() ? "-" : s;
  }
  if (it->is_object()) return std::to_string(it->size());
  return Scalar(*it);
}

bool HasNumber(const json& obj, const char* key) {
  return obj.is_object() && obj.contains(key) && obj[key].is_number();
}

bool HasText(const json& obj, const char* key) {
  return obj.is_object() && obj.contains(key) && obj[key].is_string() &&
         !obj[key].get<std::string>().empty();
}

std::string Duration(double seconds) {
  long s = seconds > 0 ? static_cast<long>(seconds) : 0;
  char buf[64];
  if (s >= 3600) {
    std::snprintf(buf, sizeof buf, "%ldh %02ldm %02lds", s / 3600, s / 60 % 60, s % 60);
  } else if (s >= 60) {
    std::snprintf(buf, sizeof buf, "%ldm %02lds", s / 60, s % 60);
  } else {
    std::snprintf(buf, sizeof buf, "%lds", s);
  }
  return buf;
}

// "state: capturing  sample: rock-12  side 1 view 7/30"
std::string StatusHeadline(const json& st) {
  std::string line = "state: " + FieldText(st, "state");
  if (HasText(st, "sample_id")) line += "  sample: " + Clean(st["sample_id"].get<std::string>());
  if (HasNumber(st, "side") && st["side"].get<double>() > 0) {
    line += "  side " + Scalar(st["side"]);
    if (HasNumber(st, "view")) {
      line += " view " + Scalar(st["view"]);
      if (HasNumber(st, "views_per_side")) line += "/" + Scalar(st["views_per_side"]);
    }
  }
  return line;
}

void PrintStatus(const json& st, std::ostream& out) {
  out << StatusHeadline(st) << "\n";
  if (!st.is_object()) return;
  if (st.contains("fault") && st["fault"].is_object()) {
    out << "fault: " << FieldText(st["fault"], "class") << ": " << FieldText(st["fault"], "message")
        << "\n";
  }
  if (HasText(st, "status_line"))
    out << "status: " << Clean(st["status_line"].get<std::string>()) << "\n";
  if (st.contains("devices") && st["devices"].is_object() && !st["devices"].empty()) {
    out << "devices:\n";
    for (const auto& [name, dev] : st["devices"].items()) {
      std::string text;
      if (dev.is_object()) {
        if (dev.contains("healthy") && dev["healthy"].is_boolean()) {
          text = dev["healthy"].get<bool>() ? "ok" : "UNHEALTHY";
          if (!dev["healthy"].get<bool>() && HasText(dev, "state"))
            text += " " + Clean(dev["state"].get<std::string>());
        } else {
          text = dev.contains("state") ? FieldText(dev, "state") : FieldText(dev, "status");
        }
        if (HasText(dev, "backend")) text += " [" + Clean(dev["backend"].get<std::string>()) + "]";
        if (HasText(dev, "message") && dev["message"].get<std::string>() != "ok")
          text += " (" + Clean(dev["message"].get<std::string>()) + ")";
      } else {
        text = Scalar(dev);
      }
      out << "  " << Clean(name) << ": " << text << "\n";
    }
  }
  if (HasNumber(st, "queue_depth"))
    out << "queue: " << Scalar(st["queue_depth"]) << " job(s) waiting\n";
  if (st.contains("worker") && st["worker"].is_object()) {
    const json& w = st["worker"];
    const bool ok = w.contains("healthy") && w["healthy"].is_boolean() && w["healthy"].get<bool>();
    out << "worker: " << (ok ? "" : "UNHEALTHY ") << FieldText(w, "state");
    if (HasText(w, "message") && w["message"].get<std::string>() != FieldText(w, "state"))
      out << " (" << Clean(w["message"].get<std::string>()) << ")";
    if (ok && HasNumber(w, "stage_s") && HasText(w, "stage"))
      out << ", " << Duration(w["stage_s"].get<double>()) << " in this stage";
    out << "\n";
  }
  if (st.contains("failed_jobs") && st["failed_jobs"].is_array() && !st["failed_jobs"].empty()) {
    const json& failed = st["failed_jobs"];
    size_t total = failed.size();
    if (HasNumber(st, "failed_jobs_total") &&
        st["failed_jobs_total"].get<double>() > static_cast<double>(total))
      total = static_cast<size_t>(st["failed_jobs_total"].get<double>());
    out << "failed jobs: " << total
        << " (the worker gave up on them; fix the cause, then `aggscan retry ID`):\n";
    for (const json& j : failed) {
      if (!j.is_object()) continue;
      const bool sample_stage = HasNumber(j, "side") && j["side"].get<double>() == 0;
      out << "  " << FieldText(j, "sample_id") << " "
          << (sample_stage ? std::string("sample stage") : "side " + FieldText(j, "side")) << ", "
          << FieldText(j, "attempts") << " attempt(s): " << FieldText(j, "error") << "\n";
    }
    if (failed.size() < total) out << "  ... and " << total - failed.size() << " older\n";
  }
  if (st.contains("calibration") && st["calibration"].is_object()) {
    const json& c = st["calibration"];
    out << "calibration: " << FieldText(c, "state");
    if (HasText(c, "message")) out << " (" << Clean(c["message"].get<std::string>()) << ")";
    out << "\n";
  }
  if (HasNumber(st, "uptime_s"))
    out << "uptime: " << Duration(st["uptime_s"].get<double>()) << "\n";
}

// `selftest`: one block per device from GET /api/v1/health; returns the
// number of unhealthy devices.
int PrintHealth(const json& h, std::ostream& out) {
  int bad = 0, total = 0;
  if (h.is_object() && h.contains("devices") && h["devices"].is_object()) {
    for (const auto& [name, dev] : h["devices"].items()) {
      ++total;
      const bool ok = dev.is_object() && dev.value("healthy", false);
      if (!ok) ++bad;
      std::string line = Clean(name) + ": " + (ok ? "ok" : "FAIL " + FieldText(dev, "state"));
      if (HasText(dev, "backend")) {
        line += " [" + Clean(dev["backend"].get<std::string>());
        if (HasText(dev, "id")) line += " " + Clean(dev["id"].get<std::string>());
        line += "]";
      }
      out << line << "\n";
      if (!ok) {
        out << "    " << FieldText(dev, "message") << "\n";
        std::string retry = "    failed attempts: " + FieldText(dev, "retries");
        if (HasNumber(dev, "next_retry_in_s")) {
          char b[32];
          std::snprintf(b, sizeof b, "%.1f", dev["next_retry_in_s"].get<double>());
          retry += std::string(", next retry in ") + b + " s";
        }
        retry +=
            ", last ok: " + (HasText(dev, "last_ok_utc") ? FieldText(dev, "last_ok_utc") : "never");
        out << retry << "\n";
      }
    }
  }
  if (total == 0) {
    out << "no device health in the answer\n";
    return 1;
  }
  out << (bad == 0 ? "all " + std::to_string(total) + " devices ok"
                   : std::to_string(bad) + " of " + std::to_string(total) + " devices unhealthy")
      << "\n";
  return bad;
}

// A number as people read it: fixed decimals, no exponent; "-" when absent.
std::string Fixed(const json& obj, const char* key, int decimals, double scale = 1.0) {
  if (!obj.is_object()) return "-";
  const auto it = obj.find(key);
  if (it == obj.end() || !it->is_number()) return "-";
  char t[64];
  std::snprintf(t, sizeof t, "%.*f", decimals, it->get<double>() * scale);
  return t;
}

// Where a sample stands, in one word: its capture state until it is
// captured, then its reconstruction's (queued, reconstructing, done, failed).
std::string SampleState(const json& s) {
  std::string state = FieldText(s, "state");
  if (state == "captured" && s.contains("reconstruction") && s["reconstruction"].is_object() &&
      HasText(s["reconstruction"], "state"))
    return FieldText(s["reconstruction"], "state");
  return state;
}

void PrintSamples(const json& answer, std::ostream& out) {
  const json* list = &answer;
  if (answer.is_object() && answer.contains("samples")) list = &answer["samples"];
  if (!list->is_array() || list->empty()) {
    out << "no samples\n";
    return;
  }
  const std::vector<const char*> header = {"ID",    "STATE",   "CREATED (UTC)", "LOT",
                                           "VIEWS", "V cm3",   "b mm",          "FER",
                                           "SPH",   "MASS kg", "QUALITY"};
  std::vector<std::vector<std::string>> rows;
  std::vector<size_t> width;
  width.reserve(header.size());
  for (const char* h : header) width.push_back(std::strlen(h));
  for (const auto& s : *list) {
    const json r = s.is_object() ? s.value("result", json()) : json();
    const json meta = s.is_object() ? s.value("meta", json::object()) : json();
    std::string quality = "-";
    if (r.is_object()) {
      const json flags = r.value("quality_flags", json::array());
      quality = r.value("confident", false) && flags.empty()
                    ? "confident"
                    : "NOT CONFIDENT (" + std::to_string(flags.size()) + " flag(s))";
    }
    std::vector<std::string> row = {
        FieldText(s, "id"),
        SampleState(s),
        FieldText(s, "created_utc"),
        meta.is_object() && HasText(meta, "lot") ? FieldText(meta, "lot") : "-",
        FieldText(s, "views"),
        Fixed(r, "volume_mm3", 1, 1e-3),
        Fixed(r, "b_mm", 1),
        Fixed(r, "fer_3d", 2),
        Fixed(r, "sphericity", 3),
        Fixed(r, "mass_g", 3, 1e-3),
        quality};
    for (size_t i = 0; i < row.size(); ++i) width[i] = std::max(width[i], row[i].size());
    rows.push_back(std::move(row));
  }
  auto print_row = [&](const std::vector<std::string>& cells) {
    std::string line;
    for (size_t i = 0; i < cells.size(); ++i) {
      line += cells[i];
      if (i + 1 < cells.size()) line += std::string(width[i] - cells[i].size() + 2, ' ');
    }
    out << line << "\n";
  };
  print_row(std::vector<std::string>(header.begin(), header.end()));
  for (const auto& r : rows) print_row(r);
}

// Indented "key: value" listing of a JSON document, for `show`.
void PrintTree(const json& j, int indent, std::ostream& out) {
  const std::string pad(static_cast<size_t>(indent), ' ');
  if (!j.is_object()) {
    out << pad << Scalar(j) << "\n";
    return;
  }
  for (const auto& [key, v] : j.items()) {
    const std::string k = pad + Clean(key) + ":";
    if (v.is_object()) {
      if (v.empty()) {
        out << k << " -\n";
      } else {
        out << k << "\n";
        PrintTree(v, indent + 2, out);
      }
    } else if (v.is_array()) {
      const bool scalars =
          std::none_of(v.begin(), v.end(), [](const json& e) { return e.is_structured(); });
      if (v.empty()) {
        out << k << " -\n";
      } else if (scalars && v.size() <= kMaxInlineValues) {
        std::string s;
        for (const auto& e : v) s += (s.empty() ? "" : ", ") + Scalar(e);
        out << k << " " << s << "\n";
      } else if (v.size() > kMaxListedRecords || scalars) {
        out << k << " " << v.size() << " entries (--json shows them)\n";
      } else {
        out << k << "\n";
        for (size_t i = 0; i < v.size(); ++i) {
          out << pad << "  [" << i + 1 << "]\n";
          PrintTree(v[i], indent + 4, out);
        }
      }
    } else {
      out << k << " " << Scalar(v) << "\n";
    }
  }
}

void PrintSample(const json& s, std::ostream& out) {
  out << "sample: " << FieldText(s, "id") << "  state: " << SampleState(s) << "\n";
  if (!s.is_object()) return;
  if (const json meta = s.value("meta", json::object()); meta.is_object() && !meta.empty()) {
    for (const char* k : {"operator", "lot", "notes"}) {
      if (HasText(meta, k)) out << k << ": " << FieldText(meta, k) << "\n";
    }
    if (meta.contains("material") && meta["material"].is_object()) {
      const json& m = meta["material"];
      out << "material: " << (HasText(m, "name") ? FieldText(m, "name") : "(unnamed)");
      if (m.contains("specific_gravity") && m["specific_gravity"].is_number())
        out << ", specific gravity " << Fixed(m, "specific_gravity", 3) << " ("
            << FieldText(m, "basis") << ")";
      if (m.value("source", "") == "config") out << " [config default]";
      out << "\n";
    }
  }
  if (s.contains("result") && s["result"].is_object()) {
    const json& r = s["result"];
    out << "result:\n"
        << "  volume       " << Fixed(r, "volume_mm3", 1) << " mm3 ("
        << Fixed(r, "volume_mm3", 2, 1e-3) << " cm3)\n"
        << "  area         " << Fixed(r, "surface_area_mm2", 1) << " mm2\n"
        << "  a / b / c    " << Fixed(r, "a_mm", 1) << " / " << Fixed(r, "b_mm", 1) << " / "
        << Fixed(r, "c_mm", 1) << " mm\n"
        << "  FER (c/a)    " << Fixed(r, "fer_3d", 3) << "   c/b " << Fixed(r, "ratio_c_b", 3)
        << "   b/a " << Fixed(r, "ratio_b_a", 3) << "\n"
        << "  sphericity   " << Fixed(r, "sphericity", 3) << "\n";
    if (r.contains("mass_g")) {
      out << "  mass         " << Fixed(r, "mass_g", 1) << " g (specific gravity "
          << Fixed(r, "specific_gravity", 3) << ", " << FieldText(r, "mass_basis") << ")\n";
    } else {
      out << "  mass         - (" << (HasText(r, "mass_none") ? FieldText(r, "mass_none") : "none")
          << ")\n";
    }
    if (r.contains("views_2d") && r["views_2d"].is_object()) {
      const json& d2 = r["views_2d"];
      for (const char* k : {"fer_2d", "circularity"}) {
        if (!d2.contains(k) || !d2[k].is_object()) continue;
        const json& st = d2[k];
        out << "  2D " << (std::string(k) == "fer_2d" ? "FER       " : "circularity") << " mean "
            << Fixed(st, "mean", 3) << " (" << Fixed(st, "min", 3) << " to " << Fixed(st, "max", 3)
            << ", CoV " << Fixed(st, "cov", 1, 100.0) << " %, " << Fixed(st, "n", 0) << " views)\n";
      }
    }
    const json flags = r.value("quality_flags", json::array());
    if (r.value("confident", false) && flags.empty()) {
      out << "quality: confident\n";
    } else {
      out << "quality: NOT CONFIDENT (" << flags.size()
          << " flag(s)): do not use these figures without checking\n";
      for (const json& f : flags) {
        if (f.is_object())
          out << "  " << FieldText(f, "code") << ": " << FieldText(f, "reason") << "\n";
      }
    }
    if (r.contains("warnings") && r["warnings"].is_array()) {
      out << "warnings:\n";
      for (const json& w : r["warnings"]) {
        out << "  - " << (w.is_string() ? Clean(w.get<std::string>()) : Scalar(w)) << "\n";
      }
    }
    if (r.contains("software") && r["software"].is_object())
      out << "computed by: aggscan " << FieldText(r["software"], "version") << ", config sha256 "
          << FieldText(r["software"], "config_sha256").substr(0, 12) << "\n";
  }
  json rest = s;
  rest.erase("id");
  rest.erase("state");
  rest.erase("result");
  rest.erase("meta");
  PrintTree(rest, 0, out);
}

// A CSV line's fields, blanks around each trimmed (a spreadsheet's export).
std::vector<std::string> CsvFields(const std::string& line) {
  std::vector<std::string> out = library_csv::SplitLine(line);
  for (std::string& f : out) {
    const size_t b = f.find_first_not_of(" \t");
    const size_t e = f.find_last_not_of(" \t");
    f = b == std::string::npos ? std::string() : f.substr(b, e - b + 1);
  }
  return out;
}

// Reference volumes measured another way (water displacement, ASTM D6473
// style): a header naming sample_id and volume_cm3, volume_ml or volume_mm3
// (and optionally method), one rock a line. Every line is checked before
// anything is sent: (sample id, "reference" object) pairs, or what is wrong
// where.
Result<std::vector<std::pair<std::string, json>>> ReadReferenceCsv(const std::string& path) {
  std::ifstream f(path);
  if (!f) return MakeError(ErrorClass::kNotFound, "cannot read " + path);
  std::string line;
  if (!std::getline(f, line)) return MakeError(ErrorClass::kInvalidArgument, path + " is empty");
  const std::vector<std::string> header = CsvFields(line);
  auto col = [&](const char* name) {
    const auto it = std::find(header.begin(), header.end(), name);
    return it == header.end() ? -1 : static_cast<int>(it - header.begin());
  };
  const int id_col = col("sample_id");
  int vol_col = col("volume_cm3");
  double scale = 1000.0;  // to mm3
  if (vol_col < 0) vol_col = col("volume_ml");
  if (vol_col < 0) {
    vol_col = col("volume_mm3");
    scale = 1.0;
  }
  const int method_col = col("method");
  if (id_col < 0 || vol_col < 0) {
    return MakeError(ErrorClass::kInvalidArgument,
                     path +
                         ": the first line must name the columns: sample_id and volume_cm3 "
                         "(or volume_ml, volume_mm3), optionally method");
  }
  std::vector<std::pair<std::string, json>> rows;
  for (int n = 2; std::getline(f, line); ++n) {
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    const std::vector<std::string> v = CsvFields(line);
    const std::string where = path + " line " + std::to_string(n);
    if (static_cast<int>(v.size()) <= std::max(id_col, vol_col))
      return MakeError(ErrorClass::kInvalidArgument, where + ": too few columns");
    if (!layout::IsValidSampleId(v[id_col]))
      return MakeError(ErrorClass::kInvalidArgument,
                       where + ": \"" + Clean(v[id_col]) + "\" is not a sample id");
    char* end = nullptr;
    const double x = std::strtod(v[vol_col].c_str(), &end);
    if (v[vol_col].empty() || *end != '\0' || !std::isfinite(x) || x <= 0)
      return MakeError(ErrorClass::kInvalidArgument,
                       where + ": volume \"" + Clean(v[vol_col]) +
                           "\" is not a positive number (a decimal point, no unit)");
    json ref = {{"volume_mm3", x * scale}, {"source", std::filesystem::path(path).filename()}};
    if (method_col >= 0 && method_col < static_cast<int>(v.size()) && !v[method_col].empty())
      ref["method"] = v[method_col];
    rows.emplace_back(v[id_col], ref);
  }
  if (rows.empty()) return MakeError(ErrorClass::kInvalidArgument, path + " has no rock");
  return rows;
}

int Usage(std::ostream& err, const std::string& problem) {
  err << "aggscan: " << problem << "\n";
  PrintClientUsage(err);
  return kClientExitUsage;
}

struct Command {
  std::string name;
  std::string method;  // "GET", "POST", "PATCH", "PUT" or "DELETE"
  std::string path;    // under /api/v1
  std::string body;    // POST body
};

}  // namespace

bool IsClientCommand(const std::string& word) {
  static const char* const kCommands[] = {
      "status", "selftest", "arm",  "arm-calibration", "press",    "abort", "reset", "samples",
      "show",   "retry",    "meta", "batch",           "reference"};
  return std::any_of(std::begin(kCommands), std::end(kCommands),
                     [&](const char* c) { return word == c; });
}

void PrintClientUsage(std::ostream& out) {
  out << "daemon commands (talk to a running aggscand):\n"
         "  aggscan [--url URL] [--json] status     state, current sample, fault, devices\n"
         "  aggscan [--url URL] [--json] selftest   each device's health and what to check\n"
         "                                         (exit 0 all ok, 4 a device is unhealthy)\n"
         "  aggscan [--url URL] [--json] arm ID     arm a new sample (or resume one) named ID\n"
         "      [--operator NAME] [--lot LOT] [--notes TEXT]   kept in the sample's record\n"
         "      [--material NAME] [--sg G --sg-basis bulk-ssd|oven-dry]   the stone and its\n"
         "                                         specific gravity (mass); default [material]\n"
         "  aggscan [--url URL] [--json] arm-calibration   arm a capture of the calibration\n"
         "                                         board lying on the disc (no rock); press\n"
         "                                         START and the worker solves the rig "
         "calibration\n"
         "  aggscan [--url URL] [--json] press      same as pressing the start button\n"
         "  aggscan [--url URL] [--json] abort      abort the running capture\n"
         "  aggscan [--url URL] [--json] reset      clear a fault and return to idle\n"
         "  aggscan [--url URL] [--json] samples    list the samples\n"
         "  aggscan [--url URL] [--json] show ID    one sample: sides, views, jobs\n"
         "  aggscan [--url URL] [--json] meta ID [--operator NAME] [--lot LOT] [--notes TEXT]\n"
         "      [--material NAME] [--sg G] [--sg-basis bulk-ssd|oven-dry] [--clear FIELD]...\n"
         "                                         edit a sample's description (sample.json only;\n"
         "                                         photos and results untouched; kept in its\n"
         "                                         meta_history); --clear "
         "operator|lot|notes|material\n"
         "  aggscan [--url URL] [--json] batch list | show NAME | delete NAME\n"
         "  aggscan [--url URL] [--json] batch set NAME [--lot LOT] [--from DATE] [--to DATE]\n"
         "      [--samples ID,ID,...] [--notes TEXT]   a named set of samples for reports: those\n"
         "                                         of the lot created in the dates (YYYY-MM-DD,\n"
         "                                         UTC, both ends included), and those listed\n"
         "  aggscan [--url URL] reference import FILE.csv   reference volumes measured another\n"
         "      way (water displacement): columns sample_id, volume_cm3 (or volume_ml,\n"
         "      volume_mm3), optionally method; kept in each sample's description for the\n"
         "      batch report's Figure 6\n"
         "  aggscan [--url URL] [--json] retry ID   put the sample's failed jobs back in the\n"
         "                                         worker's queue (after fixing the cause that\n"
         "                                         `aggscan status` names)\n"
         "options:\n"
         "  --url URL   daemon address (default $AGGSCAN_URL, else "
      << kDefaultDaemonUrl
      << ")\n"
         "  --json      print the daemon's JSON answer unchanged\n"
         "environment: AGGSCAN_USER and AGGSCAN_PASSWORD send an account's credentials (a rig\n"
         "  with daemon.credentials_file); AGGSCAN_CA_CERT trusts that certificate for https://\n"
         "exit codes: 0 ok, 1 the daemon reported an error, 2 usage error, 3 daemon unreachable,\n"
         "            4 selftest: a device is unhealthy\n";
}

int RunClientCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::optional<std::string> url_flag;
  bool json_out = false;
  std::vector<std::string> words;
  // arm's and meta's description of the sample, stored in its sample.json.
  json arm_meta = json::object();
  json batch_def = json::object();  // batch set's criteria
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a == "--json") {
      json_out = true;
    } else if (a == "--from" || a == "--to") {
      if (i + 1 >= args.size()) return Usage(err, a + " needs a date, e.g. 2026-12-01");
      batch_def[a.substr(2)] = args[++i];
    } else if (a == "--samples") {
      if (i + 1 >= args.size()) return Usage(err, "--samples needs ids, e.g. rock-1,rock-2");
      json ids = json::array();
      std::stringstream list(args[++i]);
      for (std::string part; std::getline(list, part, ',');) {
        if (!part.empty()) ids.push_back(part);
      }
      batch_def["samples"] = ids;
    } else if (a == "--operator" || a == "--lot" || a == "--notes") {
      if (i + 1 >= args.size()) return Usage(err, a + " needs a value");
      arm_meta[a.substr(2)] = args[++i];
    } else if (a == "--material" || a == "--sg-basis") {
      if (i + 1 >= args.size()) return Usage(err, a + " needs a value");
      arm_meta["material"][a == "--material" ? "name" : "basis"] = args[++i];
    } else if (a == "--sg") {
      if (i + 1 >= args.size()) return Usage(err, "--sg needs a value, e.g. --sg 2.65");
      const std::string& v = args[++i];
      char* end = nullptr;
      const double sg = std::strtod(v.c_str(), &end);
      if (v.empty() || end != v.c_str() + v.size() || !std::isfinite(sg))
        return Usage(err,
                     "--sg expects a number (the stone's specific gravity, e.g. 2.65), got \"" +
                         Clean(v) + "\"");
      arm_meta["material"]["specific_gravity"] = sg;
    } else if (a == "--clear") {
      if (i + 1 >= args.size())
        return Usage(err, "--clear needs a field: operator, lot, notes or material");
      const std::string& f = args[++i];
      if (f != "operator" && f != "lot" && f != "notes" && f != "material")
        return Usage(err,
                     "--clear takes operator, lot, notes or material, not \"" + Clean(f) + "\"");
      arm_meta[f] = nullptr;
    } else if (a == "--url") {
      if (i + 1 >= args.size())
        return Usage(err, "--url needs a value, e.g. --url http://127.0.0.1:8470");
      url_flag = args[++i];
    } else if (a.rfind("--url=", 0) == 0) {
      url_flag = a.substr(6);
    } else if (a == "-h" || a == "--help") {
      PrintClientUsage(out);
      return kClientExitOk;
    } else if (a.size() > 1 && a[0] == '-') {
      return Usage(err, "unknown option " + a);
    } else {
      words.push_back(a);
    }
  }
  if (words.empty()) return Usage(err, "missing command");
  const std::string& name = words[0];
  if (!IsClientCommand(name)) return Usage(err, "unknown command \"" + name + "\"");
  if (name == "batch") {
    // batch set takes the lot and notes as criteria, not as a description.
    const std::string verb = words.size() > 1 ? words[1] : "";
    if (verb == "set") {
      for (const char* k : {"lot", "notes"}) {
        if (arm_meta.contains(k)) {
          batch_def[k] = arm_meta[k];
          arm_meta.erase(k);
        }
      }
    }
    if (!arm_meta.empty())
      return Usage(err, "batch takes --lot, --from, --to, --samples and --notes (with set)");
    if (verb != "list" && verb != "show" && verb != "set" && verb != "delete")
      return Usage(err, "batch needs list, show NAME, set NAME or delete NAME");
    if (!batch_def.empty() && verb != "set")
      return Usage(err, "--lot, --from, --to, --samples belong to batch set");
    const size_t want_words = verb == "list" ? 2 : 3;
    if (words.size() < want_words) return Usage(err, "batch " + verb + " needs a batch name");
    if (words.size() > want_words)
      return Usage(err, "unexpected argument \"" + words[want_words] + "\" after batch " + verb);
    if (verb == "set" && batch_def.empty())
      return Usage(err,
                   "batch set needs its samples: --lot LOT, --from DATE --to DATE or --samples "
                   "ID,ID,...");
  } else if (!batch_def.empty()) {
    return Usage(err, "--from, --to and --samples belong to batch set");
  }
  std::vector<std::pair<std::string, json>> references;
  if (name == "reference") {
    if (words.size() != 3 || words[1] != "import")
      return Usage(err, "reference needs: reference import FILE.csv");
    Result<std::vector<std::pair<std::string, json>>> rows = ReadReferenceCsv(words[2]);
    if (!rows) return Usage(err, rows.error().message);
    references = std::move(*rows);
  }
  if (name != "arm" && name != "meta" && name != "batch" && !arm_meta.empty())
    return Usage(
        err, "--operator, --lot, --notes, --material, --sg and --sg-basis belong to arm and meta");
  if (name == "arm" &&
      std::any_of(arm_meta.begin(), arm_meta.end(), [](const json& v) { return v.is_null(); }))
    return Usage(err, "--clear belongs to meta (a new sample has nothing to clear)");
  if (name == "meta" && arm_meta.empty())
    return Usage(
        err, "meta needs something to change, e.g. --lot L-12 or --sg 2.65 --sg-basis bulk-ssd");
  const bool needs_id = name == "arm" || name == "show" || name == "retry" || name == "meta";
  const size_t want = needs_id ? 2 : 1;
  const bool own_words = name == "batch" || name == "reference";
  if (!own_words && words.size() < want) return Usage(err, name + " needs a sample id");
  if (!own_words && words.size() > want)
    return Usage(err, "unexpected argument \"" + words[want] + "\" after " + name);
  std::string id;
  const std::string batch_verb = name == "batch" ? words[1] : "";
  const std::string batch_name = name == "batch" && words.size() > 2 ? words[2] : "";
  if (!batch_name.empty() && !layout::IsValidSampleId(batch_name)) {
    return Usage(err, "invalid batch name \"" + Clean(batch_name) +
                          "\": use 1-64 characters from A-Z a-z 0-9 . _ -, not starting with '.' "
                          "or '-'");
  }
  if (needs_id) {
    id = words[1];
    // Checked here too: the id becomes part of the request path.
    if (!layout::IsValidSampleId(id)) {
      return Usage(
          err, "invalid sample id \"" + Clean(id) +
                   "\": use 1-64 characters from A-Z a-z 0-9 . _ -, not starting with '.' or '-'");
    }
  }

  std::string url = kDefaultDaemonUrl;
  if (url_flag) {
    url = *url_flag;
  } else if (const char* env = std::getenv("AGGSCAN_URL"); env != nullptr && *env != '\0') {
    url = env;
  }
  std::string why;
  const std::optional<Target> target = ParseUrl(url, &why);
  if (!target) return Usage(err, "invalid daemon URL \"" + Clean(url) + "\": " + why);

  Command cmd{name, "GET", "/status", {}};
  if (name == "arm") {
    json body = arm_meta;
    body["id"] = id;
    cmd = {name, "POST", "/samples", body.dump()};
  }
  if (name == "arm-calibration") cmd = {name, "POST", "/calibration", "{}"};
  if (name == "press") cmd = {name, "POST", "/button", "{}"};
  if (name == "abort") cmd = {name, "POST", "/abort", "{}"};
  if (name == "reset") cmd = {name, "POST", "/reset", "{}"};
  if (name == "samples") cmd = {name, "GET", "/samples", {}};
  if (name == "selftest") cmd = {name, "GET", "/health", {}};
  if (name == "show") cmd = {name, "GET", "/samples/" + id, {}};
  if (name == "retry") cmd = {name, "POST", "/samples/" + id + "/retry", "{}"};
  if (name == "meta") cmd = {name, "PATCH", "/samples/" + id + "/meta", arm_meta.dump()};
  if (batch_verb == "list") cmd = {name, "GET", "/batches", {}};
  if (batch_verb == "show") cmd = {name, "GET", "/batches/" + batch_name, {}};
  if (batch_verb == "set") cmd = {name, "PUT", "/batches/" + batch_name, batch_def.dump()};
  if (batch_verb == "delete") cmd = {name, "DELETE", "/batches/" + batch_name, {}};

  httplib::Client client(target->origin);
  if (const char* ca = std::getenv("AGGSCAN_CA_CERT"); ca != nullptr && *ca != '\0')
    client.set_ca_cert_path(ca);  // the rig's own (self-signed) certificate, say
  if (const char* user = std::getenv("AGGSCAN_USER"); user != nullptr && *user != '\0') {
    const char* password = std::getenv("AGGSCAN_PASSWORD");
    if (password == nullptr) {
      return Usage(err,
                   "AGGSCAN_USER is set but AGGSCAN_PASSWORD is not: set both to send "
                   "credentials to a rig that requires them");
    }
    client.set_basic_auth(user, password);
  }
  client.set_connection_timeout(kConnectTimeoutSec, 0);
  client.set_read_timeout(kReadTimeoutSec, 0);
  client.set_write_timeout(kConnectTimeoutSec, 0);
  client.set_tcp_nodelay(true);  // a POST's headers and body are separate writes
  if (name == "reference") {
    // One edit per rock: each kept in its sample's meta_history.
    int done = 0;
    std::vector<std::string> failed;
    for (const auto& [sid, ref] : references) {
      const json body = {{"reference", ref}};
      httplib::Result r = client.Patch(target->prefix + "/api/v1/samples/" + sid + "/meta",
                                       body.dump(), "application/json");
      if (!r) {
        err << "aggscan: " << TransportError(*target, r.error()) << "\n";
        return kClientExitUnreachable;
      }
      if (r->status >= 200 && r->status < 300) {
        ++done;
      } else {
        const json e = json::parse(r->body, nullptr, false);
        std::string why = "HTTP " + std::to_string(r->status);
        if (e.is_object() && e.contains("error") && e["error"].is_object() &&
            HasText(e["error"], "message"))
          why = Clean(e["error"]["message"].get<std::string>());
        failed.push_back(sid + ": " + why);
      }
    }
    out << done << " reference volume(s) imported";
    if (!failed.empty()) out << ", " << failed.size() << " refused";
    out << "\n";
    for (const std::string& f : failed) err << "aggscan: reference import: " << f << "\n";
    return failed.empty() ? kClientExitOk : kClientExitDaemonError;
  }
  const std::string path = target->prefix + "/api/v1" + cmd.path;
  httplib::Result res = cmd.method == "GET"      ? client.Get(path)
                        : cmd.method == "PATCH"  ? client.Patch(path, cmd.body, "application/json")
                        : cmd.method == "PUT"    ? client.Put(path, cmd.body, "application/json")
                        : cmd.method == "DELETE" ? client.Delete(path)
                                                 : client.Post(path, cmd.body, "application/json");
  if (!res) {
    err << "aggscan: " << TransportError(*target, res.error()) << "\n";
    if (name == "selftest") {
      err << "aggscan: selftest asks the running daemon; start it (systemctl start aggscand, or "
             "aggscand --config FILE) or point at it with --url URL / $AGGSCAN_URL\n";
    }
    return kClientExitUnreachable;
  }

  const json answer = json::parse(res->body, nullptr, /*allow_exceptions=*/false);
  const bool ok = res->status >= 200 && res->status < 300;
  if (answer.is_discarded()) {
    err << "aggscan: unexpected answer from " << target->url << " (HTTP " << res->status
        << ", not JSON) — is that address really aggscand?\n";
    return kClientExitDaemonError;
  }
  if (json_out) {
    out << res->body;
    if (res->body.empty() || res->body.back() != '\n') out << "\n";
  }
  // The health endpoint answers 503 with the full report when a device is
  // unhealthy: that is a result, not a failed request.
  if (name == "selftest" && answer.is_object() && answer.contains("devices")) {
    const bool healthy = ok && answer.value("status", "") == "ok";
    if (!json_out) PrintHealth(answer, out);
    return healthy ? kClientExitOk : kClientExitUnhealthy;
  }
  if (!ok) {
    std::string message = "HTTP " + std::to_string(res->status);
    std::string cls;
    if (answer.is_object() && answer.contains("error") && answer["error"].is_object()) {
      const json& e = answer["error"];
      if (HasText(e, "message")) message = Clean(e["message"].get<std::string>());
      if (HasText(e, "class")) cls = Clean(e["class"].get<std::string>());
    }
    err << "aggscan: " << name << " failed: " << message << (cls.empty() ? "" : " [" + cls + "]")
        << "\n";
    return kClientExitDaemonError;
  }
  if (json_out) return kClientExitOk;

  if (name == "status") {
    PrintStatus(answer, out);
  } else if (name == "samples") {
    PrintSamples(answer, out);
  } else if (name == "show") {
    PrintSample(answer, out);
  } else if (name == "batch") {
    if (batch_verb == "list") {
      const json list =
          (answer.is_object() ? answer.value("batches", json::array()) : json::array());
      if (list.empty()) out << "no batches\n";
      for (const json& b : list) {
        out << FieldText(b, "name") << ": " << FieldText(b, "members") << " sample(s)";
        if (HasText(b, "lot")) out << ", lot " << FieldText(b, "lot");
        if (HasText(b, "from") || HasText(b, "to"))
          out << ", created " << (HasText(b, "from") ? FieldText(b, "from") : "...") << " to "
              << (HasText(b, "to") ? FieldText(b, "to") : "...");
        if (b.contains("samples") && b["samples"].is_array() && !b["samples"].empty())
          out << ", " << b["samples"].size() << " listed";
        out << "\n";
      }
    } else if (batch_verb == "delete") {
      out << "batch " << batch_name << " deleted (its samples are untouched)\n";
    } else {
      out << "batch: " << FieldText(answer, "name") << "\n";
      if (HasText(answer, "lot")) out << "lot: " << FieldText(answer, "lot") << "\n";
      if (HasText(answer, "from") || HasText(answer, "to"))
        out << "created: " << (HasText(answer, "from") ? FieldText(answer, "from") : "...")
            << " to " << (HasText(answer, "to") ? FieldText(answer, "to") : "...") << "\n";
      if (HasText(answer, "notes")) out << "notes: " << FieldText(answer, "notes") << "\n";
      const json members =
          (answer.is_object() ? answer.value("members", json::array()) : json::array());
      out << members.size() << " sample(s):\n";
      if (!members.empty()) PrintSamples(members, out);
      for (const json& m :
           (answer.is_object() ? answer.value("missing", json::array()) : json::array())) {
        out << "listed but not on this rig: " << (m.is_string() ? Clean(m.get<std::string>()) : "?")
            << "\n";
      }
    }
  } else if (name == "meta") {
    const json changed = answer.is_object() ? answer.value("changed", json::object()) : json();
    if (!changed.is_object() || changed.empty()) {
      out << "sample " << id << ": nothing changed\n";
    } else {
      out << "sample " << id << ": description changed (" << changed.size() << " field(s))\n";
      if (answer.contains("meta")) PrintTree(answer["meta"], 2, out);
    }
  } else if (name == "retry") {
    out << "sample " << id << ": " << FieldText(answer, "requeued")
        << " failed job(s) back in the worker's queue; follow them with `aggscan show " << id
        << "`\n";
  } else {
    if (name == "arm") out << "armed sample " << id << "\n";
    if (name == "arm-calibration")
      out << "armed calibration capture " << FieldText(answer, "sample_id")
          << ": lay the board flat on the disc (no rock), then press START\n";
    if (name == "press") out << "button pressed\n";
    if (name == "abort") out << "capture aborted\n";
    if (name == "reset") out << "reset done\n";
    // Actions answer with the resulting status where the daemon provides it.
    if (answer.is_object() && answer.contains("state")) out << StatusHeadline(answer) << "\n";
  }
  return kClientExitOk;
}

}  // namespace aggscan
