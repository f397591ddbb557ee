#include "store/batches.h"

#include <dirent.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <set>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "store/layout.h"

namespace aggscan {

using nlohmann::json;

namespace {

Error Bad(const std::string& m) { return MakeError(ErrorClass::kInvalidArgument, m); }

// YYYY-MM-DD with a real month and day (the 31st of any month is let
// through: a range's end, not a calendar).
bool IsDate(const std::string& s) {
  if (s.size() != 10 || s[4] != '-' || s[7] != '-') return false;
  for (size_t i : {0, 1, 2, 3, 5, 6, 8, 9}) {
    if (s[i] < '0' || s[i] > '9') return false;
  }
  const int month = std::stoi(s.substr(5, 2));
  const int day = std::stoi(s.substr(8, 2));
  return month >= 1 && month <= 12 && day >= 1 && day <= 31;
}

Result<std::string> OptText(const json& doc, const char* key) {
  const auto it = doc.find(key);
  if (it == doc.end() || it->is_null()) return std::string();
  if (!it->is_string()) return Bad(std::string("\"") + key + "\" must be a string");
  return it->get<std::string>();
}

}  // namespace

json BatchDef::ToJson() const {
  json j = {{"name", name}, {"samples", samples}};
  if (!lot.empty()) j["lot"] = lot;
  if (!from_date.empty()) j["from"] = from_date;
  if (!to_date.empty()) j["to"] = to_date;
  if (!notes.empty()) j["notes"] = notes;
  if (!created_utc.empty()) j["created_utc"] = created_utc;
  if (!updated_utc.empty()) j["updated_utc"] = updated_utc;
  return j;
}

Result<BatchDef> BatchFromRequest(const std::string& name, const json& doc) {
  if (!layout::IsValidSampleId(name)) {
    return Bad("invalid batch name \"" + name +
               "\": use 1-64 characters from A-Z a-z 0-9 . _ -, not starting with '.' or '-'");
  }
  if (!doc.is_object()) {
    return Bad(
        "expected a JSON object {\"lot\", \"from\", \"to\", \"samples\": [ids], \"notes\"}, at "
        "least one of lot, from/to or samples");
  }
  for (const auto& [k, v] : doc.items()) {
    if (k != "lot" && k != "from" && k != "to" && k != "samples" && k != "notes" && k != "name" &&
        k != "created_utc" && k != "updated_utc")
      return Bad("unknown field \"" + k + "\": a batch has lot, from, to, samples, notes");
  }
  BatchDef b;
  b.name = name;
  for (auto [key, out] : {std::pair<const char*, std::string*>{"lot", &b.lot},
                          {"from", &b.from_date},
                          {"to", &b.to_date},
                          {"notes", &b.notes}}) {
    Result<std::string> t = OptText(doc, key);
    if (!t) return t.error();
    *out = *t;
  }
  for (auto [key, v] :
       {std::pair<const char*, const std::string*>{"from", &b.from_date}, {"to", &b.to_date}}) {
    if (!v->empty() && !IsDate(*v))
      return Bad(std::string("\"") + key + "\" is \"" + *v + "\": give a date as YYYY-MM-DD (UTC)");
  }
  if (!b.from_date.empty() && !b.to_date.empty() && b.from_date > b.to_date)
    return Bad("\"from\" " + b.from_date + " is after \"to\" " + b.to_date);
  if (const auto it = doc.find("samples"); it != doc.end() && !it->is_null()) {
    if (!it->is_array()) return Bad("\"samples\" must be a list of sample ids");
    std::set<std::string> seen;
    for (const json& e : *it) {
      if (!e.is_string() || !layout::IsValidSampleId(e.get<std::string>()))
        return Bad("\"samples\" holds " + e.dump() + ", which is not a sample id");
      if (seen.insert(e.get<std::string>()).second) b.samples.push_back(e.get<std::string>());
    }
  }
  if (b.lot.empty() && b.from_date.empty() && b.to_date.empty() && b.samples.empty()) {
    return Bad("batch \"" + name +
               "\" names no sample: give a lot, a date range (from, to) or a list of samples");
  }
  return b;
}

BatchMembers ResolveBatch(const BatchDef& def, const json& samples) {
  BatchMembers out;
  const bool by_criteria = !def.lot.empty() || !def.from_date.empty() || !def.to_date.empty();
  std::set<std::string> listed(def.samples.begin(), def.samples.end());
  std::set<std::string> present;
  for (const json& s : samples.is_array() ? samples : json::array()) {
    if (!s.is_object()) continue;
    const std::string id = s.value("id", "");
    present.insert(id);
    bool in = listed.count(id) > 0;
    if (!in && by_criteria) {
      const std::string created = s.value("created_utc", "");
      const json meta = s.value("meta", json::object());
      const std::string lot =
          meta.is_object() && meta.contains("lot") && meta["lot"].is_string() ? meta["lot"] : "";
      in = (def.lot.empty() || lot == def.lot) &&
           (def.from_date.empty() || created.substr(0, 10) >= def.from_date) &&
           (def.to_date.empty() || (!created.empty() && created.substr(0, 10) <= def.to_date));
    }
    if (in) out.ids.push_back(id);
  }
  for (const std::string& id : def.samples) {
    if (present.count(id) == 0) out.missing.push_back(id);
  }
  return out;
}

Result<BatchDef> BatchStore::Put(BatchDef def) {
  if (Status s = MakeDirsDurable(dir_); !s) return s.error();
  const std::string now = NowUtcString();
  def.created_utc = now;
  if (Result<BatchDef> old = Get(def.name)) def.created_utc = old->created_utc;
  def.updated_utc = now;
  if (Status s = jsonio::WriteFile(Path(def.name), def.ToJson()); !s) return s.error();
  return def;
}

Result<BatchDef> BatchStore::Get(const std::string& name) const {
  if (!layout::IsValidSampleId(name)) return BatchFromRequest(name, json::object()).error();
  if (!PathExists(Path(name))) {
    std::string known;
    for (const BatchDef& b : List()) known += (known.empty() ? "" : ", ") + b.name;
    return MakeError(
        ErrorClass::kNotFound,
        "no batch \"" + name + "\"" +
            (known.empty() ? std::string(" (there is none yet: `aggscan batch set NAME "
                                         "--lot LOT` makes one)")
                           : " (there are: " + known + ")"));
  }
  Result<json> j = jsonio::ReadFile(Path(name), "batch");
  if (!j) return j.error();
  Result<BatchDef> b = BatchFromRequest(name, *j);
  if (!b) {
    return MakeError(ErrorClass::kCorrupt,
                     Path(name) + " does not read: " + b.error().message + "; set the batch again");
  }
  b->created_utc = j->value("created_utc", "");
  b->updated_utc = j->value("updated_utc", "");
  return b;
}

std::vector<BatchDef> BatchStore::List(std::vector<std::string>* problems) const {
  std::vector<BatchDef> out;
  DIR* d = ::opendir(dir_.c_str());
  if (d == nullptr) return out;
  std::vector<std::string> names;
  while (const dirent* e = ::readdir(d)) {
    const std::string n = e->d_name;
    if (n.size() > 5 && n.compare(n.size() - 5, 5, ".json") == 0)
      names.push_back(n.substr(0, n.size() - 5));
  }
  ::closedir(d);
  std::sort(names.begin(), names.end());
  for (const std::string& n : names) {
    if (!layout::IsValidSampleId(n)) continue;
    Result<BatchDef> b = Get(n);
    if (b) {
      out.push_back(std::move(*b));
    } else if (problems != nullptr) {
      problems->push_back(b.error().message);
    }
  }
  return out;
}

Status BatchStore::Remove(const std::string& name) {
  Result<BatchDef> b = Get(name);
  if (!b) return b.error();
  if (::unlink(Path(name).c_str()) != 0) {
    return MakeError(ErrorClass::kIo, "cannot remove " + Path(name) + ": " + std::strerror(errno));
  }
  return OkStatus();
}

}  // namespace aggscan
