#include "pipeline/masks/mask_dataset.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>

#include "common/fsutil.h"
#include "common/json_io.h"
#include "pipeline/core/geometry.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/records.h"
#include "store/layout.h"
#include "store/sample_files.h"

namespace aggscan {
namespace {

using json = nlohmann::json;
namespace fs = std::filesystem;

Result<json> ReadJsonFile(const std::string& path) { return jsonio::ReadFile(path, "record"); }

std::string SampleName(const std::string& dir) {
  fs::path p = fs::path(dir).lexically_normal();
  if (p.filename().empty()) p = p.parent_path();
  return p.filename().string();
}

std::string CsvField(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string q = "\"";
  for (char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

}  // namespace

cv::Mat RenderMeshSilhouette(const Mesh& mesh, const Eigen::Isometry3d& cam_from_object,
                             const CameraModel& cam) {
  constexpr int kShift = 4;  // fillConvexPoly's fractional bits: vertices at 1/16 px
  std::vector<cv::Point> pts(mesh.vertices.size());
  std::vector<char> in_front(mesh.vertices.size(), 0);
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    const Eigen::Vector3d pc = cam_from_object * Eigen::Vector3d(mesh.vertices[i].data());
    double u = 0, v = 0;
    in_front[i] = cam.Project({pc.x(), pc.y(), pc.z()}, &u, &v);
    // Pixel centres at integer coordinates; the fixed-point origin is the
    // pixel's corner.
    pts[i] =
        cv::Point(static_cast<int>(std::lround((u + 0.5) * (1 << kShift) - (1 << (kShift - 1)))),
                  static_cast<int>(std::lround((v + 0.5) * (1 << kShift) - (1 << (kShift - 1)))));
  }
  cv::Mat sil = cv::Mat::zeros(cam.height, cam.width, CV_8UC1);
  for (const auto& f : mesh.faces) {
    if (!in_front[f[0]] || !in_front[f[1]] || !in_front[f[2]]) continue;
    const cv::Point tri[3] = {pts[f[0]], pts[f[1]], pts[f[2]]};
    cv::fillConvexPoly(sil, tri, 3, cv::Scalar(255), cv::LINE_8, kShift);
  }
  return sil;
}

double MaskIoUIgnoring(const cv::Mat& a, const cv::Mat& b, const cv::Mat& ignore) {
  CV_Assert(a.size() == b.size() && a.type() == CV_8UC1 && b.type() == CV_8UC1);
  cv::Mat inter = (a != 0) & (b != 0), uni = (a != 0) | (b != 0);
  if (!ignore.empty()) {
    CV_Assert(ignore.size() == a.size() && ignore.type() == CV_8UC1);
    const cv::Mat keep = ignore == 0;
    inter &= keep;
    uni &= keep;
  }
  const double u = cv::countNonZero(uni);
  return u > 0 ? cv::countNonZero(inter) / u : 1.0;
}

Result<std::vector<ProjectedView>> ProjectReconstruction(const std::string& sample_dir) {
  const std::string results = sample_dir + "/" + layout::kResultsDir;
  const std::string redo =
      ": reconstruct the sample first (aggscan reconstruct " + sample_dir + ")";
  for (const char* f :
       {layout::kMorphology, layout::kMeshPly, layout::kStitch, layout::kCalibrationUsed}) {
    if (!PathExists(results + "/" + f)) {
      return MakeError(ErrorClass::kNotFound, sample_dir + " has no results/" + f + redo);
    }
  }
  auto cal_json = ReadJsonFile(layout::ResultsPath(sample_dir, layout::kCalibrationUsed));
  if (!cal_json) return cal_json.error();
  auto cal =
      CalibrationFromJson(*cal_json, layout::ResultsPath(sample_dir, layout::kCalibrationUsed));
  if (!cal) return cal.error();
  auto mesh = LoadMesh(layout::ResultsPath(sample_dir, layout::kMeshPly), "mm");
  if (!mesh) return mesh.error();
  auto stitch = records::Read<records::StitchRecord>(
      layout::ResultsPath(sample_dir, layout::kStitch), "stitch record", redo.substr(2));
  if (!stitch) return stitch.error();
  const std::map<int, Pose>& table_from_object = stitch->table_from_object;
  std::vector<ProjectedView> out;
  for (const auto& [side, table_T] : table_from_object) {
    const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
    const std::string poses_path = layout::ResultsPath(sample_dir, layout::PosesName(side));
    auto poses = records::Read<records::PosesRecord>(poses_path, "poses record", redo.substr(2));
    if (!poses) {
      if (poses.error().cls != ErrorClass::kNotFound) return poses.error();
      return MakeError(poses.error().cls, poses.error().message + redo, poses.error().detail);
    }
    struct Posed {
      Eigen::Isometry3d cam_from_table;
      std::string image, mask, pose;
    };
    std::map<int, Posed> views;
    for (const records::PosedViewRecord& v : poses->views)
      views[v.view] = {v.cam_from_table, v.image, v.mask, "poses"};
    // A turntable-posed side: the views the worker left out (their mask
    // failed, the very views a better mask is for) have a pose too, from
    // the calibration and the angle the turntable measured.
    const std::string& method = poses->method;
    if (method.rfind("turntable", 0) == 0) {
      auto manifest = ReadSideManifest(side_dir);
      if (manifest) {
        for (const SideManifest::Entry& v : manifest->views) {
          if (views.count(v.view)) continue;
          auto sidecar = ReadViewSidecarFile(side_dir + "/" +
                                             v.sidecar.value_or(layout::ViewSidecarName(v.view)));
          if (!sidecar || !sidecar->measured_angle_deg) continue;
          views[v.view] = {geom::IsoFromRowMajor(cal->CamFromTable(*sidecar->measured_angle_deg)),
                           v.image, "", "turntable"};
        }
      }
    }
    for (const auto& [view, p] : views) {
      ProjectedView pv;
      pv.side = side;
      pv.view = view;
      pv.image = side_dir + "/" + p.image;
      pv.pose = p.pose;
      pv.silhouette = RenderMeshSilhouette(*mesh, p.cam_from_table * table_T, cal->camera);
      if (!p.mask.empty()) {
        auto m = LoadImage(results + "/" + p.mask, ImageMode::kGray);
        if (m && m->size() == pv.silhouette.size())
          pv.agreement_iou = MaskIoUIgnoring(*m, pv.silhouette);
      }
      out.push_back(std::move(pv));
    }
  }
  return out;
}

Result<MaskDatasetSummary> MakeMaskDataset(const std::vector<std::string>& sample_dirs,
                                           const std::string& out_dir) {
  std::error_code ec;
  fs::create_directories(out_dir + "/images", ec);
  if (!ec) fs::create_directories(out_dir + "/masks", ec);
  if (ec)
    return MakeError(ErrorClass::kIo, "cannot create the dataset directory " + out_dir,
                     ec.message());
  MaskDatasetSummary sum;
  std::set<std::string> names;
  for (const std::string& dir : sample_dirs) {
    std::string name = SampleName(dir);
    if (!names.insert(name).second) {
      sum.skipped.push_back(dir + ": another sample directory of the same name " + name +
                            " is already in");
      continue;
    }
    auto views = ProjectReconstruction(dir);
    if (!views) {
      sum.skipped.push_back(dir + ": " + views.error().message);
      continue;
    }
    int written = 0;
    for (const ProjectedView& v : *views) {
      // The photo must decode (a damaged one is no training pair) and match
      // the calibration's size (the silhouette's).
      auto photo = LoadImage(v.image, ImageMode::kColor);
      if (!photo || photo->size() != v.silhouette.size()) continue;
      const std::string stem =
          name + "_" + layout::SideDirName(v.side) + "_" + layout::ViewStem(v.view);
      MaskPairRecord r;
      r.sample = name;
      r.side = v.side;
      r.view = v.view;
      r.pose = v.pose;
      r.agreement_iou = v.agreement_iou;
      r.image = "images/" + stem + fs::path(v.image).extension().string();
      r.mask = "masks/" + stem + ".png";
      fs::copy_file(v.image, out_dir + "/" + r.image, fs::copy_options::overwrite_existing, ec);
      if (ec)
        return MakeError(ErrorClass::kIo, "cannot copy " + v.image + " into " + out_dir,
                         ec.message());
      std::vector<unsigned char> png;
      cv::imencode(".png", v.silhouette, png);
      if (Status s = WriteFileAtomic(out_dir + "/" + r.mask, png); !s) return s.error();
      sum.pairs.push_back(std::move(r));
      ++written;
    }
    if (written == 0) {
      sum.skipped.push_back(dir + ": no view's photo could be read");
    } else {
      sum.samples.push_back(name);
    }
  }
  if (sum.pairs.empty()) {
    std::string why;
    for (const auto& s : sum.skipped) why += "\n  " + s;
    return MakeError(ErrorClass::kNotFound,
                     "no training pair: none of the samples is reconstructed with readable "
                     "photos (aggscan reconstruct SAMPLE_DIR makes results/mesh.ply)" +
                         why);
  }
  json pairs = json::array();
  std::ostringstream csv;
  csv << "image,mask,sample,side,view,pose,agreement_iou\n";
  for (const auto& r : sum.pairs) {
    pairs.push_back({{"image", r.image},
                     {"mask", r.mask},
                     {"sample", r.sample},
                     {"side", r.side},
                     {"view", r.view},
                     {"pose", r.pose},
                     {"agreement_iou", r.agreement_iou}});
    csv << CsvField(r.image) << "," << CsvField(r.mask) << "," << CsvField(r.sample) << ","
        << r.side << "," << r.view << "," << r.pose << "," << r.agreement_iou << "\n";
  }
  const json index = {
      {"format", "aggscan mask dataset 1"},
      {"mask_source",
       "the sample's reconstructed mesh (results/mesh.ply) projected into each view"},
      {"pairs", pairs},
      {"samples", sum.samples},
      {"skipped", sum.skipped}};
  if (Status s = WriteFileAtomic(out_dir + "/index.json", index.dump(1) + "\n"); !s)
    return s.error();
  if (Status s = WriteFileAtomic(out_dir + "/index.csv", csv.str()); !s) return s.error();
  return sum;
}

}  // namespace aggscan
