#include "cli/masks_command.h"

#include <limits.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <set>

#include "common/fsutil.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/subprocess.h"
#include "pipeline/masks/mask.h"
#include "pipeline/masks/mask_dataset.h"
#include "pipeline/masks/mask_net.h"
#include "pipeline/worker/side_job.h"
#include "store/layout.h"

#ifndef AGGSCAN_SOURCE_DIR
#define AGGSCAN_SOURCE_DIR ""
#endif

namespace aggscan {
namespace {

using json = nlohmann::json;
namespace fs = std::filesystem;

constexpr const char* kTrainScript = "train_masks.py";
// train_masks.py's exit status when a Python module is missing (its
// message names the Debian package).
constexpr int kScriptMissingModule = 3;
// The IoU the segmentation must reach on every view (the rig's mask
// requirement); the evaluation counts the views below it.
constexpr double kIouGoal = 0.98;

std::string TrainScriptPath() {
  if (const char* e = std::getenv("AGGSCAN_TRAIN_MASKS_SCRIPT"); e && *e) return e;
  std::string installed = ExecutableDir() + "/../share/aggscan/masks/" + kTrainScript;
  if (PathExists(installed)) return installed;
  return std::string(AGGSCAN_SOURCE_DIR) + "/scripts/masks/" + kTrainScript;
}

bool ParseInt(const std::string& s, int lo, int hi, int* v) {
  char* end = nullptr;
  const long x = std::strtol(s.c_str(), &end, 10);
  if (end == s.c_str() || *end != '\0' || x < lo || x > hi) return false;
  *v = static_cast<int>(x);
  return true;
}

bool ParseSize(const std::string& s, int* w, int* h) {
  const auto x = s.find('x');
  return x != std::string::npos && ParseInt(s.substr(0, x), 32, 4096, w) &&
         ParseInt(s.substr(x + 1), 32, 4096, h) && *w % 16 == 0 && *h % 16 == 0;
}

std::optional<json> ReadJson(const std::string& path) {
  std::ifstream f(path);
  if (!f) return std::nullopt;
  try {
    return json::parse(f);
  } catch (const json::exception&) {
    return std::nullopt;
  }
}

// --- dataset ---------------------------------------------------------------

int DatasetCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::string out_dir;
  std::vector<std::string> samples;
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--out" && i + 1 < args.size()) {
      out_dir = args[++i];
    } else if (!args[i].empty() && args[i][0] == '-') {
      err << "aggscan masks dataset: unknown option '" << args[i] << "'\n";
      return 2;
    } else {
      samples.push_back(args[i]);
    }
  }
  if (out_dir.empty() || samples.empty()) {
    err << "aggscan masks dataset: give --out DIR and one or more reconstructed sample "
           "directories\n";
    return 2;
  }
  for (const auto& s : samples) {
    if (!fs::is_directory(s)) {
      err << "aggscan masks dataset: " << s << " is not a directory\n";
      return 2;
    }
  }
  auto sum = MakeMaskDataset(samples, out_dir);
  if (!sum) {
    err << "aggscan masks dataset: " << sum.error().message << "\n";
    return 1;
  }
  for (const auto& s : sum->skipped) err << "aggscan masks dataset: skipped " << s << "\n";
  std::map<std::string, int> per_sample;
  double low = 1;
  for (const auto& p : sum->pairs) {
    ++per_sample[p.sample];
    if (p.agreement_iou >= 0) low = std::min(low, p.agreement_iou);
  }
  for (const auto& [s, n] : per_sample) out << s << ": " << n << " pairs\n";
  out << sum->pairs.size() << " pairs from " << sum->samples.size() << " samples in " << out_dir
      << " (index.json, index.csv); lowest IoU of a projection with the worker's own mask " << low
      << "\n";
  return 0;
}

// --- train -----------------------------------------------------------------

// A python3 that imports torch and cv2: Debian's own first (a python3
// earlier on PATH, e.g. pyenv's, does not see Debian's python3-torch).
Result<std::string> FindPython(const std::string& wanted) {
  std::vector<std::string> candidates;
  if (!wanted.empty())
    candidates.push_back(wanted);
  else
    candidates = {"/usr/bin/python3", "python3"};
  std::string last;
  SubprocessOptions so;
  so.timeout_s = 120;
  for (const auto& py : candidates) {
    auto r = RunSubprocess({py, "-c", "import torch, cv2"}, so);
    if (r && r->Succeeded()) return py;
    last = py + (r ? ": " + r->Describe() : ": " + r.error().message);
  }
  return MakeError(
      ErrorClass::kNotFound,
      "no python3 that imports torch and cv2 (" + last +
          "): install Debian's python3-torch and python3-opencv (apt-get install python3-torch "
          "python3-opencv, or scripts/install-deps.sh), or give --python PATH");
}

std::string ConfigLines(const std::string& model, int w, int h) {
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "[mask]\nmethod = \"onnx\"\nmodel = \"%s\"\ninput_width = %d\ninput_height = %d\n"
                "mean_r = 0.485\nmean_g = 0.456\nmean_b = 0.406\nstd_r = 0.229\nstd_g = "
                "0.224\nstd_b = 0.225\n"
                "output = \"probability\"\nthreshold = 0.5\n",
                model.c_str(), w, h);
  return buf;
}

int TrainCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::string dataset, model, python;
  std::vector<std::string> backgrounds;
  int epochs = 30, width = 320, height = 320, seed = 1, threads = 2;
  for (size_t i = 0; i < args.size(); ++i) {
    const bool has = i + 1 < args.size();
    if (args[i] == "--dataset" && has) {
      dataset = args[++i];
    } else if (args[i] == "--out" && has) {
      model = args[++i];
    } else if (args[i] == "--python" && has) {
      python = args[++i];
    } else if (args[i] == "--backgrounds" && has) {
      const std::string& dir = args[++i];
      if (!fs::is_directory(dir)) {
        err << "aggscan masks train: --backgrounds " << dir
            << " is not a folder (give a folder of empty-turntable photos)\n";
        return 2;
      }
      backgrounds.push_back(fs::absolute(dir).lexically_normal().string());
    } else if (args[i] == "--epochs" && has) {
      if (!ParseInt(args[++i], 1, 10000, &epochs)) {
        err << "aggscan masks train: --epochs needs a whole number from 1 to 10000\n";
        return 2;
      }
    } else if (args[i] == "--seed" && has) {
      if (!ParseInt(args[++i], 0, 1 << 30, &seed)) {
        err << "aggscan masks train: --seed needs a whole number >= 0\n";
        return 2;
      }
    } else if (args[i] == "--threads" && has) {
      if (!ParseInt(args[++i], 1, 256, &threads)) {
        err << "aggscan masks train: --threads needs a whole number from 1 to 256\n";
        return 2;
      }
    } else if (args[i] == "--input" && has) {
      if (!ParseSize(args[++i], &width, &height)) {
        err << "aggscan masks train: --input needs WxH, each a multiple of 16 from 32 (320x320)\n";
        return 2;
      }
    } else {
      err << "aggscan masks train: unexpected argument '" << args[i] << "'\n";
      return 2;
    }
  }
  if (dataset.empty() || model.empty()) {
    err << "aggscan masks train: give --dataset DIR (from `aggscan masks dataset`) and --out "
           "MODEL.onnx\n";
    return 2;
  }
  if (!PathExists(dataset + "/index.json")) {
    err << "aggscan masks train: " << dataset
        << "/index.json not found: make the dataset first (aggscan masks dataset --out " << dataset
        << " SAMPLE_DIR...)\n";
    return 1;
  }
  const std::string script = TrainScriptPath();
  if (!PathExists(script)) {
    err << "aggscan masks train: the training script " << script
        << " is missing: reinstall aggscan, or set AGGSCAN_TRAIN_MASKS_SCRIPT to scripts/masks/"
        << kTrainScript << "\n";
    return 1;
  }
  auto py = FindPython(python);
  if (!py) {
    err << "aggscan masks train: " << py.error().message << "\n";
    return 1;
  }
  const std::string abs_model = fs::absolute(model).lexically_normal().string();
  const std::string log = abs_model + ".log";
  std::error_code ec;
  fs::remove(log, ec);
  out << "aggscan masks train: training with " << *py << " " << script << " (log: " << log << ")\n"
      << std::flush;
  std::vector<std::string> argv = {*py,         script,
                                   "--dataset", dataset,
                                   "--out",     abs_model,
                                   "--epochs",  std::to_string(epochs),
                                   "--width",   std::to_string(width),
                                   "--height",  std::to_string(height),
                                   "--seed",    std::to_string(seed),
                                   "--threads", std::to_string(threads)};
  if (!backgrounds.empty()) {
    argv.push_back("--backgrounds");
    argv.insert(argv.end(), backgrounds.begin(), backgrounds.end());
  }
  SubprocessOptions so;
  so.log_path = log;
  auto r = RunSubprocess(argv, so);
  if (!r) {
    err << "aggscan masks train: cannot run " << *py << ": " << r.error().message << "\n";
    return 1;
  }
  if (!r->Succeeded()) {
    err << "aggscan masks train: the training " << r->Describe() << "; "
        << (r->exit_code == kScriptMissingModule ? "install what it names" : "see " + log) << ":\n"
        << TailOfFile(log, 6) << "\n";
    return 1;
  }
  // The worker must be able to load what was written (the same check as at
  // its start).
  MaskNetOptions o;
  o.model_path = abs_model;
  o.input_size = cv::Size(width, height);
  auto net = MaskNet::Load(o);
  if (!net) {
    err << "aggscan masks train: the exported model does not load in the worker: "
        << net.error().message << "\n";
    return 1;
  }
  const std::string lines = ConfigLines(abs_model, width, height);
  const std::string toml = fs::path(abs_model).replace_extension(".mask.toml").string();
  if (Status s = WriteFileAtomic(toml, lines); !s) {
    err << "aggscan masks train: " << s.error().message << "\n";
    return 1;
  }
  out << TailOfFile(log, 2) << "\n"
      << "Config lines to use it (also in " << toml << "; put them in the worker's config):\n"
      << lines;
  return 0;
}

// --- eval ------------------------------------------------------------------

struct Scores {
  double classical = -1, empty = -1, net_raw = -1, net = -1;   // -1: not scored
  cv::Mat classical_mask, empty_mask, net_raw_mask, net_mask;  // 0/255, for --save
};

// The masks scored, as 0/255 PNGs next to each other under `dir` (made on
// demand): STEM_classical.png, STEM_trained.png, STEM_network.png.
Status SaveMasks(const std::string& dir, const std::string& stem, const Scores& s) {
  if (Status st = MakeDirsDurable(dir); !st) return st;
  const std::pair<const char*, const cv::Mat*> masks[] = {{"classical", &s.classical_mask},
                                                          {"empty", &s.empty_mask},
                                                          {"trained", &s.net_mask},
                                                          {"network", &s.net_raw_mask}};
  for (const auto& [what, m] : masks) {
    if (m->empty()) continue;
    const std::string path = dir + "/" + stem + "_" + what + ".png";
    if (!cv::imwrite(path, *m)) return MakeError(ErrorClass::kIo, "cannot write " + path);
  }
  return {};
}

struct Summary {
  std::vector<double> classical, empty, net_raw, net;
  void Add(const Scores& s) {
    classical.push_back(s.classical);
    if (s.empty >= 0) empty.push_back(s.empty);
    if (s.net >= 0) {
      net_raw.push_back(s.net_raw);
      net.push_back(s.net);
    }
  }
  static json Stat(const std::vector<double>& v) {
    if (v.empty()) return nullptr;
    double mean = 0, lo = 1;
    int below = 0;
    for (double x : v) {
      mean += x;
      lo = std::min(lo, x);
      below += x < kIouGoal;
    }
    return {{"min", lo}, {"mean", mean / v.size()}, {"views", v.size()}, {"below_goal", below}};
  }
  json ToJson() const {
    json j = {{"classical", Stat(classical)}};
    if (!empty.empty()) j["classical_empty_turntable"] = Stat(empty);
    if (!net.empty()) {
      j["trained_raw"] = Stat(net_raw);
      j["trained"] = Stat(net);
    }
    return j;
  }
};

class Scorer {
 public:
  explicit Scorer(MaskNet* net) : net_(net) {}
  // `empty`: the empty turntable at this view, or none; the trained mask is
  // refined against it as the worker refines it.
  Scores Score(const cv::Mat& bgr, const cv::Mat& truth, const cv::Mat& ignore,
               const cv::Mat& empty = cv::Mat()) {
    Scores s;
    s.classical_mask = ComputeForegroundMask(bgr);
    s.classical = MaskIoUIgnoring(s.classical_mask, truth, ignore);
    if (!empty.empty()) {
      s.empty_mask = ComputeForegroundMask(bgr, empty, MaskOptions{});
      s.empty = MaskIoUIgnoring(s.empty_mask, truth, ignore);
    }
    if (net_) {
      auto p = net_->Probability(bgr);
      if (p) {
        s.net_raw_mask = *p > net_->options().threshold;
        s.net_raw = MaskIoUIgnoring(s.net_raw_mask, truth, ignore);
        s.net_mask = RefineForegroundMask(bgr, empty, s.net_raw_mask, MaskOptions{});
        s.net = MaskIoUIgnoring(s.net_mask, truth, ignore);
      }
    }
    return s;
  }

 private:
  MaskNet* net_;
};

void PrintScores(std::ostream& out, const std::string& what, const Scores& s) {
  char buf[256];
  std::string empty;
  if (s.empty >= 0) {
    std::snprintf(buf, sizeof buf, "  with empty turntable %.4f", s.empty);
    empty = buf;
  }
  if (s.net >= 0) {
    std::snprintf(buf, sizeof buf, "%-44s classical %.4f%s  trained %.4f  (network alone %.4f)\n",
                  what.c_str(), s.classical, empty.c_str(), s.net, s.net_raw);
  } else {
    std::snprintf(buf, sizeof buf, "%-44s classical %.4f%s\n", what.c_str(), s.classical,
                  empty.c_str());
  }
  out << buf;
}

void PrintSummary(std::ostream& out, const std::string& what, const Summary& s) {
  char buf[320];
  auto mm = [](const std::vector<double>& v, double* lo, double* mean) {
    *lo = 1;
    *mean = 0;
    for (double x : v) *lo = std::min(*lo, x), *mean += x;
    *mean /= std::max<size_t>(1, v.size());
  };
  double cl, cm;
  mm(s.classical, &cl, &cm);
  std::string empty;
  if (!s.empty.empty()) {
    double el, em;
    mm(s.empty, &el, &em);
    std::snprintf(buf, sizeof buf, " | with empty turntable min %.4f mean %.4f", el, em);
    empty = buf;
  }
  if (!s.net.empty()) {
    double nl, nm, rl, rm;
    mm(s.net, &nl, &nm);
    mm(s.net_raw, &rl, &rm);
    std::snprintf(buf, sizeof buf,
                  "%-36s %3zu views  classical min %.4f mean %.4f%s | trained min %.4f mean %.4f | "
                  "network alone "
                  "min %.4f mean %.4f\n",
                  what.c_str(), s.classical.size(), cl, cm, empty.c_str(), nl, nm, rl, rm);
  } else {
    std::snprintf(buf, sizeof buf, "%-36s %3zu views  classical min %.4f mean %.4f%s\n",
                  what.c_str(), s.classical.size(), cl, cm, empty.c_str());
  }
  out << buf;
}

int EvalCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::string model, grabcut, save;
  bool as_json = false, quiet = false;
  int width = 0, height = 0;
  double threshold = -1;
  std::vector<std::string> samples;
  for (size_t i = 0; i < args.size(); ++i) {
    const bool has = i + 1 < args.size();
    if (args[i] == "--model" && has) {
      model = args[++i];
    } else if (args[i] == "--grabcut" && has) {
      grabcut = args[++i];
    } else if (args[i] == "--save" && has) {
      save = args[++i];
    } else if (args[i] == "--threshold" && has) {
      char* end = nullptr;
      threshold = std::strtod(args[++i].c_str(), &end);
      if (*end != '\0' || !(threshold > 0 && threshold < 1)) {
        err << "aggscan masks eval: --threshold needs a probability between 0 and 1 (0.5)\n";
        return 2;
      }
    } else if (args[i] == "--input" && has) {
      if (!ParseSize(args[++i], &width, &height)) {
        err << "aggscan masks eval: --input needs WxH, each a multiple of 16 from 32\n";
        return 2;
      }
    } else if (args[i] == "--json") {
      as_json = true;
    } else if (args[i] == "--summary") {
      quiet = true;
    } else if (!args[i].empty() && args[i][0] == '-') {
      err << "aggscan masks eval: unknown option '" << args[i] << "'\n";
      return 2;
    } else {
      samples.push_back(args[i]);
    }
  }
  if (samples.empty() && grabcut.empty()) {
    err << "aggscan masks eval: give simulated sample directories (with truth/) and/or --grabcut "
           "DIR\n";
    return 2;
  }
  // The model and what it was trained on (MODEL.json, written by training).
  std::unique_ptr<MaskNet> net;
  std::set<std::string> trained_on;
  if (!model.empty()) {
    MaskNetOptions o;
    o.model_path = model;
    if (auto rep = ReadJson(model + ".json")) {
      o.input_size = cv::Size(rep->value("input_width", 320), rep->value("input_height", 320));
      for (const auto& s : rep->value("samples", json::array()))
        trained_on.insert(s.get<std::string>());
    }
    if (width > 0) o.input_size = cv::Size(width, height);
    if (threshold > 0) o.threshold = threshold;
    auto loaded = MaskNet::Load(o);
    if (!loaded) {
      err << "aggscan masks eval: " << loaded.error().message << "\n";
      return 1;
    }
    net = std::move(*loaded);
  }
  Scorer scorer(net.get());
  json report = {{"goal_iou", kIouGoal}, {"model", model}, {"views", json::array()}};
  std::map<std::string, Summary> by_sample, by_look, by_split;
  Summary all;
  const auto t0 = std::chrono::steady_clock::now();
  for (const std::string& dir : samples) {
    const std::string truth_dir = dir + "/" + layout::kTruthDir;
    if (!fs::is_directory(truth_dir)) {
      err << "aggscan masks eval: " << dir
          << " has no truth/ (only simulated samples carry truth masks)\n";
      return 1;
    }
    std::string name = fs::path(dir).lexically_normal().filename().string();
    if (name.empty()) name = fs::path(dir).lexically_normal().parent_path().filename().string();
    std::string look = "sim renderer";
    if (auto t = ReadJson(dir + "/truth.json");
        t && t->contains("renderer") && (*t)["renderer"].is_object()) {
      look = (*t)["renderer"].value("look", json::object()).value("name", "blender");
    }
    const std::string split =
        trained_on.empty() ? "" : (trained_on.count(name) ? "trained on" : "held out");
    // The sample's empty-turntable photos, matched to the views as the worker
    // matches them.
    const Result<EmptyTurntableSet> empty_set =
        LoadEmptyTurntableSet(dir + "/" + layout::kEmptyDir);
    if (!empty_set && empty_set.error().cls != ErrorClass::kNotFound) {
      err << "aggscan masks eval: " << empty_set.error().message << "\n";
      return 1;
    }
    int views = 0;
    for (int side = 1; side <= 8; ++side) {
      const std::string td = truth_dir + "/" + layout::SideDirName(side);
      if (!fs::is_directory(td)) continue;
      std::vector<std::string> files;
      for (const auto& e : fs::directory_iterator(td)) {
        const std::string f = e.path().filename().string();
        if (f.size() > 9 && f.ends_with("_mask.pgm")) files.push_back(f);
      }
      std::sort(files.begin(), files.end());
      for (const std::string& f : files) {
        const std::string stem = f.substr(0, f.size() - 9);  // view_NNN
        const std::string photo = dir + "/" + layout::SideDirName(side) + "/" + stem + ".jpg";
        auto bgr = LoadImage(photo, ImageMode::kColor);
        auto truth = LoadImage(td + "/" + f, ImageMode::kGray);
        if (!bgr || !truth || bgr->size() != truth->size()) {
          err << "aggscan masks eval: skipped " << photo
              << " (unreadable, or not the size of its truth mask)\n";
          continue;
        }
        // The empty turntable at this view, where the sample has it; one that
        // is not usable is named and the view scored without it.
        cv::Mat empty;
        if (empty_set) {
          std::string why;
          const std::string side_dir = dir + "/" + layout::SideDirName(side);
          empty = EmptyTurntablePhoto(dir, *empty_set, MeasuredAngle(side_dir, stem + ".json"),
                                      *bgr, WorkerOptions{}, &why);
          if (empty.empty()) {
            err << "aggscan masks eval: " << photo << ": " << why
                << "; the view is scored without an empty-turntable photo\n";
          }
        }
        const Scores s = scorer.Score(*bgr, *truth > 127, cv::Mat(), empty);
        if (!save.empty()) {
          if (Status st = SaveMasks(save + "/" + name + "/" + layout::SideDirName(side), stem, s);
              !st) {
            err << "aggscan masks eval: --save: " << st.error().message << "\n";
            return 1;
          }
        }
        const std::string what = name + " " + layout::SideDirName(side) + " " + stem;
        if (!quiet && !as_json) PrintScores(out, what, s);
        json v = {{"set", "simulated"}, {"sample", name}, {"look", look},
                  {"side", side},       {"view", stem},   {"classical", s.classical}};
        if (s.empty >= 0) v["classical_empty_turntable"] = s.empty;
        if (s.net >= 0) v["trained"] = s.net, v["trained_raw"] = s.net_raw;
        if (!split.empty()) v["split"] = split;
        report["views"].push_back(v);
        by_sample[name].Add(s);
        by_look[look].Add(s);
        if (!split.empty()) by_split[split].Add(s);
        all.Add(s);
        ++views;
      }
    }
    if (views == 0) {
      err << "aggscan masks eval: " << dir
          << " has no view with a truth mask and a readable photo\n";
      return 1;
    }
  }
  // GrabCut set: the stone photos, scored where the trimap is labelled
  // (128: the unlabelled border band).
  std::map<std::string, Scores> stones;
  if (!grabcut.empty()) {
    for (const char* stone : {"stone1", "stone2"}) {
      const std::string gt_path = grabcut + "/boundary_GT/" + stone + ".bmp";
      std::string photo;
      for (const char* ext : {".JPG", ".jpg", ".bmp"}) {
        if (PathExists(grabcut + "/data_GT/" + stone + ext))
          photo = grabcut + "/data_GT/" + stone + ext;
      }
      const cv::Mat bgr = photo.empty() ? cv::Mat() : cv::imread(photo, cv::IMREAD_COLOR);
      const cv::Mat gt = cv::imread(gt_path, cv::IMREAD_GRAYSCALE);
      if (bgr.empty() || gt.empty() || bgr.size() != gt.size()) {
        err << "aggscan masks eval: " << grabcut << " lacks a readable data_GT/" << stone
            << ".JPG and boundary_GT/" << stone
            << ".bmp of one size (the MSR GrabCut set's layout)\n";
        return 1;
      }
      const Scores s = scorer.Score(bgr, gt == 255, gt == 128);
      if (!save.empty()) {
        if (Status st = SaveMasks(save + "/grabcut", stone, s); !st) {
          err << "aggscan masks eval: --save: " << st.error().message << "\n";
          return 1;
        }
      }
      stones[stone] = s;
      if (!as_json) PrintScores(out, std::string("grabcut ") + stone, s);
      json v = {{"set", "grabcut"}, {"sample", stone}, {"classical", s.classical}};
      if (s.net >= 0) v["trained"] = s.net, v["trained_raw"] = s.net_raw;
      report["views"].push_back(v);
    }
  }
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  json summary = json::object();
  if (!samples.empty()) {
    summary["all_simulated"] = all.ToJson();
    for (const auto& [k, s] : by_sample) summary["by_sample"][k] = s.ToJson();
    for (const auto& [k, s] : by_look) summary["by_look"][k] = s.ToJson();
    for (const auto& [k, s] : by_split) summary["by_split"][k] = s.ToJson();
  }
  report["summary"] = summary;
  report["seconds"] = secs;
  if (as_json) {
    out << report.dump(1) << "\n";
    return 0;
  }
  if (!samples.empty()) {
    out << "\nIoU against the truth masks (goal " << kIouGoal
        << " on every view); 'with empty turntable' = the classical method against the photo of\n"
        << "the empty turntable at that view's angle (SAMPLE/empty/), 'trained' = the network's "
           "map "
        << "refined as the worker does, 'network alone' = its map thresholded:\n";
    for (const auto& [k, s] : by_sample) {
      PrintSummary(out,
                   k + (trained_on.empty()    ? ""
                        : trained_on.count(k) ? " (trained on)"
                                              : " (held out)"),
                   s);
    }
    for (const auto& [k, s] : by_look) PrintSummary(out, "look " + k, s);
    for (const auto& [k, s] : by_split) PrintSummary(out, k, s);
    PrintSummary(out, "all", all);
  }
  return 0;
}

void PrintDatasetUsage(std::ostream& o) {
  o << "  aggscan masks dataset --out DIR SAMPLE_DIR...\n"
       "      training pairs for the mask network from reconstructed samples: each photo with\n"
       "      the sample's mesh projected into it (PNG 0/255), index.json and index.csv\n";
}

void PrintTrainUsage(std::ostream& o) {
  o << "  aggscan masks train --dataset DIR --out MODEL.onnx [--epochs N (30)] [--input WxH "
       "(320x320)]\n"
       "                      [--seed N] [--threads N (2)] [--python PATH] [--backgrounds DIR]...\n"
       "      train the small salient-object network on the CPU (Debian's python3-torch and\n"
       "      python3-opencv), export it to ONNX, print the [mask] config lines to use it;\n"
       "      --backgrounds: photos of the empty turntable where the rig is to work (disc, floor,\n"
       "      lights): the dataset's rocks are also laid onto them with a drawn shadow, which\n"
       "      teaches the network that place without a rock from it\n";
}

void PrintEvalUsage(std::ostream& o) {
  o << "  aggscan masks eval [--model MODEL.onnx] [--grabcut DIR] [--summary | --json] "
       "[--save DIR] [--threshold P] SAMPLE_DIR...\n"
       "      IoU of the classical and the trained masks side by side against the truth masks\n"
       "      of simulated samples, per view and summarised (min/mean), and on the GrabCut\n"
       "      set's stone photos; where a sample has empty-turntable photos (SAMPLE/empty/)\n"
       "      the classical mask against the one of each view's angle too, and the trained\n"
       "      one refined against it; --save: every mask scored, as PNGs under DIR/SAMPLE/sideN/;\n"
       "      --threshold: the network's probability above which a pixel is rock (the worker's\n"
       "      [mask] threshold, 0.5)\n";
}

}  // namespace

void PrintMasksUsage(std::ostream& o) {
  PrintDatasetUsage(o);
  PrintTrainUsage(o);
  PrintEvalUsage(o);
}

int RunMasksCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  const std::string sub = args.empty() ? "" : args[0];
  // Before anything else: dataset and train write files.
  if (std::any_of(args.begin(), args.end(),
                  [](const std::string& a) { return a == "--help" || a == "-h"; })) {
    out << "usage:\n";
    if (sub == "dataset")
      PrintDatasetUsage(out);
    else if (sub == "train")
      PrintTrainUsage(out);
    else if (sub == "eval")
      PrintEvalUsage(out);
    else
      PrintMasksUsage(out);
    return 0;
  }
  const std::vector<std::string> rest(args.empty() ? args.end() : args.begin() + 1, args.end());
  if (sub == "dataset") return DatasetCommand(rest, out, err);
  if (sub == "train") return TrainCommand(rest, out, err);
  if (sub == "eval") return EvalCommand(rest, out, err);
  err << "aggscan masks: give dataset, train or eval\n";
  PrintMasksUsage(err);
  return 2;
}

}  // namespace aggscan
