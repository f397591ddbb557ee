#include "cli/report_command.h"

#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <ostream>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "common/version.h"
#include "config/config.h"
#include "pipeline/core/subprocess.h"
#include "pipeline/worker/reconstruct.h"
#include "store/batches.h"
#include "store/layout.h"
#include "store/sample_files.h"
#include "store/sample_meta.h"
#include "store/sample_store.h"

namespace aggscan {

using nlohmann::json;

namespace {

constexpr const char* kScript = "aggscan_report.py";
// A report needs python3 with matplotlib (and WeasyPrint for a PDF):
// Debian's, whatever python3 comes first on PATH.
constexpr const char* kPython = "/usr/bin/python3";
constexpr const char* kDefaultStateDir = "/var/lib/aggscan";
// The script's exit codes (scripts/report/aggscan_report.py).
constexpr int kScriptBadInput = 2;
constexpr int kScriptMissingLibrary = 3;

std::string ReportDir() {
  if (const char* e = std::getenv("AGGSCAN_REPORT_DIR"); e && *e) return e;
  std::string installed = ExecutableDir() + "/../share/aggscan/report";
  if (PathExists(installed + "/" + kScript)) return installed;
  return std::string(AGGSCAN_SOURCE_DIR) + "/scripts/report";
}

// The specifications shipped (scripts/report/specs/*.toml), by name.
std::vector<std::string> KnownSpecs() {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(ReportDir() + "/specs", ec)) {
    const std::string n = e.path().filename().string();
    if (n.size() > 5 && n.compare(n.size() - 5, 5, ".toml") == 0)
      names.push_back(n.substr(0, n.size() - 5));
  }
  std::sort(names.begin(), names.end());
  return names;
}

// Two views of each side, a quarter turn apart where there are (the
// rock's outline from two directions).
json Photos(const std::string& dir, const json& rec) {
  json out = json::array();
  for (const json& sd : rec.value("sides", json::array())) {
    const int side = sd.value("side", 0);
    const std::string side_dir = dir + "/" + layout::SideDirName(side);
    Result<SideManifest> man = ReadSideManifest(side_dir);
    if (!man || man->views.empty()) continue;
    const size_t n = man->views.size();
    std::vector<size_t> picks = {0};
    if (n / 4 > 0) picks.push_back(n / 4);
    for (size_t k : picks) {
      const SideManifest::Entry& v = man->views[k];
      const std::string mask = layout::ResultsPath(dir, layout::ViewMaskName(side, v.view));
      out.push_back({{"side", side},
                     {"view", v.view},
                     {"image", side_dir + "/" + v.image},
                     {"mask", PathExists(mask) ? json(mask) : json()}});
    }
  }
  return out;
}

// What the report script needs of one sample: its record, its typed
// morphology (refused with the field named when it does not read), the
// mass from its description, its photos and mesh.
Result<json> SampleEntry(const std::string& dir) {
  const std::string id = layout::SampleIdOfDir(dir);
  Result<json> rec = jsonio::ReadFile(dir + "/" + layout::kSampleRecord, "sample record");
  if (!rec) return rec.error();
  const json meta = rec->value("meta", json::object());
  json e = {{"id", id},
            {"dir", dir},
            {"created_utc", rec->value("created_utc", "")},
            {"state", rec->value("state", "")},
            {"meta", meta.is_object() ? meta : json::object()}};
  Result<records::Morphology> m = ReadMorphologyRecord(dir);
  if (m) {
    json mj = m->ToJson();
    e["morphology"] = mj;
    const sample_meta::Mass mass = sample_meta::MassOf(m->volume_mm3, e["meta"]);
    if (mass.grams) {
      e["mass_g"] = *mass.grams;
    } else {
      e["mass_none"] = mass.why_none;
    }
  } else if (m.error().cls == ErrorClass::kNotFound) {
    e["why_no_result"] = "it has not been reconstructed (no results/morphology.json)";
  } else {
    return m.error();
  }
  const json ref = e["meta"].value("reference", json());
  if (ref.is_object() && ref.contains("volume_mm3") && ref["volume_mm3"].is_number())
    e["reference_volume_mm3"] = ref["volume_mm3"];
  e["photos"] = Photos(dir, *rec);
  const std::string mesh = layout::ResultsPath(dir, layout::kMeshPly);
  if (PathExists(mesh)) e["mesh"] = mesh;
  return e;
}

}  // namespace

void PrintReportUsage(std::ostream& o) {
  o << "  aggscan report SAMPLE_ID|SAMPLE_DIR [--state-dir DIR | --config FILE] [--html FILE]\n"
       "                 [--pdf FILE]\n"
       "      one rock's report: description, photos with the mask outline, the model from\n"
       "      three directions, the study's Table 1 row and Figures 7 and 8, quality with\n"
       "      pass/warn, methods, timings, software (default: ID-report.html and .pdf here)\n"
       "  aggscan report --batch NAME [--spec NAME|FILE] [--state-dir DIR | --config FILE]\n"
       "                 [--html FILE] [--pdf FILE]\n"
       "      a batch's report (`aggscan batch set`): Table 1, gradation by mass with W15-W100\n"
       "      and D15-D85 (checked against --spec: a shipped specification or a TOML file as\n"
       "      scripts/report/specs/template.toml), ASTM D4791 shares, Figures 6 (with imported\n"
       "      reference volumes), 7 and 8, the 3D/2D FER factor; needs every rock's mass\n"
       "      The state directory: --state-dir, else daemon.state_dir of --config, else\n"
       "      $AGGSCAN_STATE_DIR, else "
    << kDefaultStateDir << "\n";
}

int RunReportCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::string target, batch, spec, state_dir, config_path, html, pdf;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    auto val = [&](std::string* dst) {
      if (i + 1 >= args.size()) return false;
      *dst = args[++i];
      return true;
    };
    bool ok = true;
    if (a == "-h" || a == "--help") {
      out << "usage:\n";
      PrintReportUsage(out);
      return 0;
    }
    if (a == "--batch") {
      ok = val(&batch);
    } else if (a == "--spec") {
      ok = val(&spec);
    } else if (a == "--state-dir") {
      ok = val(&state_dir);
    } else if (a == "--config") {
      ok = val(&config_path);
    } else if (a == "--html") {
      ok = val(&html);
    } else if (a == "--pdf") {
      ok = val(&pdf);
    } else if (a.rfind("--", 0) == 0) {
      err << "aggscan report: unknown option '" << a << "'\n";
      return 2;
    } else if (target.empty()) {
      target = a;
    } else {
      err << "aggscan report: unexpected argument '" << a << "'\n";
      return 2;
    }
    if (!ok) {
      err << "aggscan report: " << a << " needs a value\n";
      return 2;
    }
  }
  if (target.empty() == batch.empty()) {
    err << "aggscan report: give a sample (ID or directory) or --batch NAME, not both\n";
    PrintReportUsage(err);
    return 2;
  }
  if (!spec.empty() && batch.empty()) {
    err << "aggscan report: --spec checks a batch's gradation: use it with --batch\n";
    return 2;
  }
  if (state_dir.empty() && !config_path.empty()) {
    std::vector<ConfigProblem> problems;
    Result<Config> c = LoadConfigFile(config_path, &problems);
    if (!c) {
      err << "aggscan report: " << c.error().ToString() << "\n";
      return 1;
    }
    state_dir = c->daemon.state_dir;
  }
  if (state_dir.empty()) {
    const char* e = std::getenv("AGGSCAN_STATE_DIR");
    state_dir = e && *e ? e : kDefaultStateDir;
  }

  // The specification: a shipped name or a file; anything else is refused
  // before any work, naming what there is.
  std::string spec_path;
  if (!spec.empty()) {
    const std::string shipped = ReportDir() + "/specs/" + spec + ".toml";
    if (PathExists(shipped)) {
      spec_path = shipped;
    } else if (PathExists(spec)) {
      spec_path = spec;
    } else {
      err << "aggscan report: unknown gradation specification '" << spec
          << "': give a TOML file (see " << ReportDir()
          << "/specs/template.toml) or one of the shipped ones:";
      for (const std::string& n : KnownSpecs()) err << " " << n;
      err << "\n";
      return 1;
    }
  }

  json doc = {{"generated_utc", NowUtcString()}, {"software_version", SoftwareVersion()}};
  std::string stem;
  SampleStore store(state_dir);
  if (!batch.empty()) {
    Result<BatchDef> def = BatchStore(state_dir).Get(batch);
    if (!def) {
      err << "aggscan report: " << def.error().message << " in " << state_dir << "\n";
      return 1;
    }
    Result<json> list = store.List();
    if (!list) {
      err << "aggscan report: " << list.error().ToString() << "\n";
      return 1;
    }
    const BatchMembers members = ResolveBatch(*def, *list);
    if (members.ids.empty()) {
      err << "aggscan report: batch " << batch << " has no sample in " << state_dir
          << " (its lot, dates or list match none)\n";
      return 1;
    }
    doc["kind"] = "batch";
    doc["batch"] = def->ToJson();
    doc["batch"]["missing"] = members.missing;
    doc["samples"] = json::array();
    for (const std::string& id : members.ids) {
      Result<json> e = SampleEntry(store.SampleDir(id));
      if (!e) {
        err << "aggscan report: sample " << id << ": " << e.error().ToString() << "\n";
        return 1;
      }
      doc["samples"].push_back(std::move(*e));
    }
    stem = batch;
  } else {
    std::string dir = target;
    if (!PathExists(dir + "/" + layout::kSampleRecord)) {
      if (!layout::IsValidSampleId(target)) {
        err << "aggscan report: " << target << " is neither a sample directory nor a sample id\n";
        return 1;
      }
      dir = store.SampleDir(target);
      if (!PathExists(dir + "/" + layout::kSampleRecord)) {
        err << "aggscan report: no sample " << target << " in " << state_dir
            << " (give --state-dir DIR, or the sample's directory)\n";
        return 1;
      }
    }
    Result<json> e = SampleEntry(dir);
    if (!e) {
      err << "aggscan report: " << e.error().ToString() << "\n";
      return 1;
    }
    stem = (*e)["id"].get<std::string>();
    doc["kind"] = "rock";
    doc["samples"] = json::array({std::move(*e)});
  }
  if (html.empty() && pdf.empty()) {
    html = stem + "-report.html";
    pdf = stem + "-report.pdf";
  }

  // The document goes to the script through a private temporary file.
  char tmpl[] = "/tmp/aggscan-report-XXXXXX";
  const int fd = ::mkstemp(tmpl);
  if (fd < 0) {
    err << "aggscan report: cannot make a temporary file in /tmp\n";
    return 1;
  }
  ::close(fd);
  const std::string doc_path = tmpl;
  struct Remove {
    std::string path;
    ~Remove() { ::unlink(path.c_str()); }
  } remove{doc_path};
  if (Status s = jsonio::WriteFile(doc_path, doc); !s) {
    err << "aggscan report: " << s.error().ToString() << "\n";
    return 1;
  }
  std::vector<std::string> argv = {kPython, ReportDir() + "/" + kScript, "--input", doc_path};
  if (!html.empty()) argv.insert(argv.end(), {"--html", html});
  if (!pdf.empty()) argv.insert(argv.end(), {"--pdf", pdf});
  if (!spec_path.empty()) argv.insert(argv.end(), {"--spec", spec_path});
  const std::string log = doc_path + ".log";
  struct RemoveLog {
    std::string path;
    ~RemoveLog() { ::unlink(path.c_str()); }
  } remove_log{log};
  SubprocessOptions so;
  so.log_path = log;
  so.timeout_s = 600;
  Result<SubprocessResult> r = RunSubprocess(argv, so);
  if (!r) {
    err << "aggscan report: cannot run " << kPython << ": " << r.error().ToString()
        << " (apt-get install python3 python3-matplotlib weasyprint)\n";
    return 3;
  }
  if (!r->Succeeded()) {
    const std::string tail = TailOfFile(log, 12);
    err << tail << (tail.empty() || tail.back() == '\n' ? "" : "\n");
    if (r->exit_code == kScriptMissingLibrary) return 3;
    if (r->exit_code != kScriptBadInput)
      err << "aggscan report: the report script failed (" << r->Describe() << ")\n";
    return 1;
  }
  if (!html.empty()) out << "wrote " << html << "\n";
  if (!pdf.empty()) out << "wrote " << pdf << "\n";
  out << "report of " << (batch.empty() ? "rock " : "batch ") << stem << ": "
      << doc["samples"].size() << " sample(s), " << r->wall_s << " s\n";
  return 0;
}

}  // namespace aggscan
