// Turntable register-map profiles: TOML -> TurntableProfile, every problem
// reported with the file, the field and what to do.
#include "config/turntable_profile.h"

#include <toml++/toml.h>

#include <cstdio>
#include <cstdlib>
#include <optional>
#include <set>
#include <utility>

#include "common/fsutil.h"

namespace aggscan {
namespace {

std::string Hex(int v) {
  char buf[16];
  std::snprintf(buf, sizeof(buf), "0x%04X", v);
  return buf;
}

class ProfileParser {
 public:
  explicit ProfileParser(std::string file) : file_(std::move(file)) {}

  void Add(const std::string& field, const std::string& message) {
    problems_.push_back(file_ + ": " + field + ": " + message);
  }
  bool ok() const { return problems_.empty(); }
  std::string Joined() const {
    std::string s;
    for (const auto& p : problems_) s += (s.empty() ? "" : "\n") + p;
    return s;
  }
  size_t count() const { return problems_.size(); }
  const std::string& first() const { return problems_.front(); }

  // Keys of `t` outside `known` are reported (a typo must not silently drop a field).
  void OnlyKeys(const toml::table& t, const std::string& prefix,
                const std::set<std::string>& known) {
    for (auto&& [k, v] : t) {
      (void)v;
      const std::string key(k.str());
      if (!known.count(key)) {
        std::string list;
        for (const auto& n : known) list += (list.empty() ? "" : ", ") + n;
        Add(prefix + key, "unknown key; known here: " + list);
      }
    }
  }

  const toml::table* Table(const toml::table& root, const char* key, bool required,
                           const char* what) {
    const toml::node* n = root.get(key);
    if (!n) {
      if (required) Add(key, std::string("missing table; add [") + key + "] with " + what);
      return nullptr;
    }
    if (!n->is_table()) {
      Add(key, std::string("must be a table [") + key + "]");
      return nullptr;
    }
    return n->as_table();
  }

  // An integer in [lo, hi]; returns false (and reports) when absent and required or invalid.
  bool Int(const toml::table& t, const std::string& prefix, const char* key, int lo, int hi,
           bool required, const std::string& what, int* out) {
    const toml::node* n = t.get(key);
    const std::string field = prefix + key;
    if (!n) {
      if (required) Add(field, "missing; give " + what);
      return false;
    }
    const auto* i = n->as_integer();
    if (!i) {
      Add(field, "must be an integer (decimal or 0x hex): " + what);
      return false;
    }
    if (i->get() < lo || i->get() > hi) {
      Add(field, "must be in " + std::to_string(lo) + ".." + std::to_string(hi) + ", got " +
                     std::to_string(i->get()));
      return false;
    }
    *out = static_cast<int>(i->get());
    return true;
  }

  bool String(const toml::table& t, const std::string& prefix, const char* key, bool required,
              const std::string& what, std::string* out) {
    const toml::node* n = t.get(key);
    if (!n) {
      if (required) Add(prefix + key, "missing; give " + what);
      return false;
    }
    const auto* s = n->as_string();
    if (!s) {
      Add(prefix + key, "must be a string: " + what);
      return false;
    }
    *out = s->get();
    return true;
  }

  // { address = A, value = V }
  void Write(const toml::table& t, const std::string& prefix, const char* key, bool required,
             const std::string& what, RegisterWrite* out) {
    const toml::node* n = t.get(key);
    const std::string field = prefix + key;
    if (!n) {
      if (required) Add(field, "missing; give { address = REGISTER, value = VALUE }: " + what);
      return;
    }
    const auto* w = n->as_table();
    if (!w) {
      Add(field, "must be a table { address = REGISTER, value = VALUE }: " + what);
      return;
    }
    OnlyKeys(*w, field + ".", {"address", "value"});
    RegisterWrite r;
    bool a = Int(*w, field + ".", "address", 0, 65535, true, "the holding register (0-based)",
                 &r.address);
    bool v = Int(*w, field + ".", "value", 0, 65535, true, "the 16-bit value written", &r.value);
    if (a && v) *out = r;
  }

  // { address = A, bit = B [, active_low = true] }
  void Flag(const toml::table& t, const char* key, bool required, const std::string& what,
            StatusFlag* out) {
    const toml::node* n = t.get(key);
    const std::string field = std::string("status.") + key;
    if (!n) {
      if (required) Add(field, "missing; give { address = REGISTER, bit = 0..15 }: " + what);
      return;
    }
    const auto* f = n->as_table();
    if (!f) {
      Add(field, "must be a table { address = REGISTER, bit = 0..15 }: " + what);
      return;
    }
    OnlyKeys(*f, field + ".", {"address", "bit", "active_low"});
    StatusFlag s;
    bool a = Int(*f, field + ".", "address", 0, 65535, true, "the status register (0-based)",
                 &s.address);
    bool b =
        Int(*f, field + ".", "bit", 0, 15, true, "the bit number, 0 = least significant", &s.bit);
    if (const toml::node* al = f->get("active_low")) {
      if (const auto* bv = al->as_boolean()) {
        s.active_low = bv->get();
      } else {
        Add(field + ".active_low", "must be true or false");
      }
    }
    if (a && b) *out = s;
  }

  void Scaled(const toml::table& root, const char* key, const std::vector<std::string>& units,
              int* unit_index, ScaledRegisters* out) {
    const toml::table* t = Table(root, key, false, "");
    if (!t) return;
    const std::string p = std::string(key) + ".";
    OnlyKeys(*t, p, {"addresses", "unit", "scale"});
    const toml::node* a = t->get("addresses");
    if (!a || !a->is_array() || a->as_array()->empty()) {
      Add(p + "addresses", "must be a non-empty array of registers, e.g. [7]; or leave out [" +
                               std::string(key) + "] when the controller has no such register");
    } else {
      for (const auto& el : *a->as_array()) {
        const auto* i = el.as_integer();
        if (!i || i->get() < 0 || i->get() > 65535) {
          Add(p + "addresses", "every entry must be a register 0..65535");
          continue;
        }
        out->addresses.push_back(static_cast<int>(i->get()));
      }
    }
    std::string unit;
    std::string list;
    for (const auto& u : units) list += (list.empty() ? "" : " | ") + u;
    if (String(*t, p, "unit", true, "the physical unit: " + list, &unit)) {
      bool found = false;
      for (size_t i = 0; i < units.size(); ++i) {
        if (units[i] == unit) *unit_index = static_cast<int>(i), found = true;
      }
      if (!found) Add(p + "unit", "must be one of " + list + ", got \"" + unit + "\"");
    }
    if (const toml::node* s = t->get("scale")) {
      std::optional<double> v = s->value<double>();
      if (!v || !(*v > 0)) {
        Add(p + "scale", "must be a number > 0 (physical units per register count, e.g. 0.1)");
      } else {
        out->scale = *v;
      }
    }
  }

  // Every register the profile reads or writes, with what it is, so that two
  // roles on one register are found (a contradiction, never intended).
  void CheckOverlaps(const TurntableProfile& p) {
    std::map<int, std::string> owner;
    auto claim = [&](int address, const std::string& role) {
      if (address < 0) return;
      auto [it, fresh] = owner.emplace(address, role);
      if (!fresh && it->second != role) {
        Add(role, "register " + Hex(address) + " is also " + it->second +
                      "; give each value its own register");
      }
    };
    claim(p.target_address, "position.target");
    if (p.target_address >= 0) claim(p.target_address + 1, "position.target");
    claim(p.actual_address, "position.actual");
    if (p.actual_address >= 0) claim(p.actual_address + 1, "position.actual");
    for (int a : p.speed.addresses) claim(a, "speed.addresses");
    for (int a : p.accel.addresses) claim(a, "accel.addresses");
    // Command registers may be shared by several commands (one command
    // register, different values) and status flags share status registers.
    std::map<int, std::map<int, std::string>> cmd_values;
    for (auto [w, name] : {std::pair{&p.move, "commands.move"},
                           {&p.home, "commands.home"},
                           {&p.stop, "commands.stop"},
                           {&p.reset_alarm, "commands.reset_alarm"}}) {
      if (w->address < 0) continue;
      auto it = owner.find(w->address);
      if (it != owner.end() && it->second.rfind("commands.", 0) != 0) {
        Add(name, "register " + Hex(w->address) + " is also " + it->second +
                      "; a command needs its own register");
      }
      owner.emplace(w->address, name);
      auto [vit, fresh] = cmd_values[w->address].emplace(w->value, name);
      if (!fresh) {
        Add(name, "same register and value as " + vit->second +
                      "; the controller could not tell the two commands apart");
      }
    }
    std::map<std::pair<int, int>, std::string> bits;
    for (auto [f, name] : {std::pair{&p.enabled, "status.enabled"},
                           {&p.moving, "status.moving"},
                           {&p.in_position, "status.in_position"},
                           {&p.homed, "status.homed"},
                           {&p.alarm, "status.alarm"}}) {
      if (!f->present()) continue;
      auto it = owner.find(f->address);
      if (it != owner.end() && it->second.rfind("status.", 0) != 0) {
        Add(name, "register " + Hex(f->address) + " is also " + it->second +
                      "; status bits need a status register");
      }
      owner.emplace(f->address, name);
      auto [bit, fresh] = bits.emplace(std::pair{f->address, f->bit}, name);
      if (!fresh) {
        Add(name, "same register and bit as " + bit->second + "; each flag needs its own bit");
      }
    }
    claim(p.alarm_code_address, "alarm.code");
  }

  Result<TurntableProfile> Parse(const std::string& text) {
    toml::table root;
    try {
      root = toml::parse(text, file_);
    } catch (const toml::parse_error& e) {
      return MakeError(ErrorClass::kInvalidConfig,
                       file_ + ":" + std::to_string(e.source().begin.line) +
                           ": TOML syntax error: " + std::string(e.description()) +
                           "; fix the turntable profile");
    }
    OnlyKeys(root, "",
             {"profile", "position", "speed", "accel", "commands", "status", "alarm", "on_open"});
    TurntableProfile p;
    p.file = file_;

    if (const toml::table* t = Table(root, "profile", true, "name, model, source, word_order")) {
      OnlyKeys(*t, "profile.", {"name", "model", "source", "word_order", "read_max_gap"});
      String(*t, "profile.", "name", true, "a short name, e.g. \"generic\"", &p.name);
      String(*t, "profile.", "model", false, "", &p.model);
      String(*t, "profile.", "source", false, "", &p.source);
      std::string order;
      if (String(*t, "profile.", "word_order", true,
                 "\"high_first\" or \"low_first\": which register of an int32 holds its high word "
                 "(see the controller manual)",
                 &order)) {
        if (order == "high_first") {
          p.word_order = WordOrder::kHighFirst;
        } else if (order == "low_first") {
          p.word_order = WordOrder::kLowFirst;
        } else {
          Add("profile.word_order",
              "must be \"high_first\" or \"low_first\", got \"" + order + "\"");
        }
      }
      Int(*t, "profile.", "read_max_gap", 0, 64, false, "", &p.read_max_gap);
    }

    if (const toml::table* t = Table(root, "position", true, "target and actual registers")) {
      OnlyKeys(*t, "position.", {"target", "actual"});
      Int(*t, "position.", "target", 0, 65534, true,
          "the first of the two registers of the int32 target position (steps)", &p.target_address);
      Int(*t, "position.", "actual", 0, 65534, true,
          "the first of the two registers of the int32 measured position (steps)",
          &p.actual_address);
    }

    int su = 0, au = 0;
    Scaled(root, "speed", {"table_deg_per_s", "motor_rpm", "steps_per_s"}, &su, &p.speed);
    p.speed_unit = static_cast<SpeedUnit>(su);
    Scaled(root, "accel", {"table_deg_per_s2", "steps_per_s2", "ms_per_1000rpm"}, &au, &p.accel);
    p.accel_unit = static_cast<AccelUnit>(au);

    if (const toml::table* t =
            Table(root, "commands", true, "move, home, stop (and reset_alarm)")) {
      OnlyKeys(*t, "commands.", {"move", "home", "stop", "reset_alarm"});
      Write(*t, "commands.", "move", true, "what starts the move to the target", &p.move);
      Write(*t, "commands.", "home", true, "what starts homing", &p.home);
      Write(*t, "commands.", "stop", true, "what stops motion", &p.stop);
      Write(*t, "commands.", "reset_alarm", false, "", &p.reset_alarm);
    }

    if (const toml::table* t = Table(root, "status", true, "moving and in_position flags")) {
      OnlyKeys(*t, "status.", {"enabled", "moving", "in_position", "homed", "alarm"});
      Flag(*t, "enabled", false, "", &p.enabled);
      Flag(*t, "moving", true, "the bit that is set while the platter moves", &p.moving);
      Flag(*t, "in_position", true, "the bit set when a move or homing has completed",
           &p.in_position);
      Flag(*t, "homed", false, "", &p.homed);
      Flag(*t, "alarm", false, "", &p.alarm);
    }

    if (const toml::table* t = Table(root, "alarm", false, "")) {
      OnlyKeys(*t, "alarm.", {"code", "texts"});
      Int(*t, "alarm.", "code", 0, 65535, false, "", &p.alarm_code_address);
      if (const toml::node* tx = t->get("texts")) {
        if (!tx->is_table()) {
          Add("alarm.texts", "must be a table of \"CODE\" = \"text\"");
        } else {
          for (auto&& [k, v] : *tx->as_table()) {
            const std::string key(k.str());
            char* end = nullptr;
            long code = std::strtol(key.c_str(), &end, 0);
            if (key.empty() || *end != '\0' || code < 0 || code > 65535) {
              Add("alarm.texts." + key, "key must be an alarm code, e.g. \"7\" or \"0x07\"");
              continue;
            }
            if (!v.is_string()) {
              Add("alarm.texts." + key, "must be the operator text of that alarm code");
              continue;
            }
            p.alarm_texts[static_cast<int>(code)] = v.as_string()->get();
          }
        }
      }
    }
    if (!p.alarm.present() && p.alarm_code_address < 0 && root.contains("status")) {
      Add("status.alarm",
          "missing, and there is no alarm.code either; give one of them so that "
          "alarms can be seen");
    }

    if (const toml::node* n = root.get("on_open")) {
      const auto* arr = n->as_array();
      if (!arr) {
        Add("on_open", "must be an array of tables [[on_open]] with address and value");
      } else {
        for (size_t i = 0; i < arr->size(); ++i) {
          const std::string f = "on_open[" + std::to_string(i) + "]";
          const auto* t = arr->get(i)->as_table();
          if (!t) {
            Add(f, "must be a table { address, value }");
            continue;
          }
          OnlyKeys(*t, f + ".", {"address", "value"});
          RegisterWrite w;
          if (Int(*t, f + ".", "address", 0, 65535, true, "the register", &w.address) &&
              Int(*t, f + ".", "value", 0, 65535, true, "the value", &w.value)) {
            p.on_open.push_back(w);
          }
        }
      }
    }

    if (ok()) CheckOverlaps(p);
    if (!ok()) {
      std::string msg = count() == 1 ? first()
                                     : std::to_string(count()) + " problems in turntable profile " +
                                           file_ + ", first: " + first();
      return MakeError(ErrorClass::kInvalidConfig, msg, Joined());
    }
    return p;
  }

 private:
  std::string file_;
  std::vector<std::string> problems_;
};

}  // namespace

const char* WordOrderName(WordOrder w) {
  return w == WordOrder::kHighFirst ? "high_first" : "low_first";
}

Result<TurntableProfile> ParseTurntableProfile(const std::string& toml, const std::string& file) {
  return ProfileParser(file).Parse(toml);
}

Result<TurntableProfile> LoadTurntableProfile(const std::string& path) {
  Result<std::string> text = ReadFile(path);
  if (!text) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "cannot read turntable profile " + path +
                         "; check turntable.modbus.profile and turntable.modbus.profile_dir",
                     text.error().ToString());
  }
  return ParseTurntableProfile(*text, path);
}

Result<TurntableProfile> FindTurntableProfile(const std::string& profile, const std::string& dir) {
  const bool is_path = profile.find('/') != std::string::npos ||
                       (profile.size() > 5 && profile.compare(profile.size() - 5, 5, ".toml") == 0);
  if (is_path) return LoadTurntableProfile(profile);
  return LoadTurntableProfile(dir + "/" + profile + ".toml");
}

}  // namespace aggscan
