#include "pipeline/sfm/colmap_sfm.h"

#include <sqlite3.h>
#include <sys/stat.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>

#include "common/fsutil.h"
#include "common/log.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/subprocess.h"

namespace aggscan {
namespace fs = std::filesystem;

namespace {

constexpr const char* kLog = "sfm";
constexpr double kPi = 3.14159265358979323846;

std::string Fmt(const char* fmt, double a, double b = 0, double c = 0) {
  char buf[256];
  std::snprintf(buf, sizeof buf, fmt, a, b, c);
  return buf;
}

double WrapDeg(double a) {  // to (-180, 180]
  a = std::fmod(a, 360.0);
  if (a <= -180) a += 360;
  if (a > 180) a -= 360;
  return a;
}

// Parameter count of the COLMAP models this module understands.
int ParamCount(const std::string& model) {
  if (model == "SIMPLE_PINHOLE") return 3;
  if (model == "PINHOLE") return 4;
  if (model == "SIMPLE_RADIAL") return 4;
  if (model == "RADIAL") return 5;
  if (model == "OPENCV") return 8;
  if (model == "FULL_OPENCV") return 12;
  return -1;
}

// COLMAP's numeric model ids (database cameras.model).
int ModelId(const std::string& model) {
  static const char* kNames[] = {"SIMPLE_PINHOLE", "PINHOLE",        "SIMPLE_RADIAL", "RADIAL",
                                 "OPENCV",         "OPENCV_FISHEYE", "FULL_OPENCV"};
  for (int i = 0; i < 7; ++i)
    if (model == kNames[i]) return i;
  return -1;
}

std::string JoinParams(const std::vector<double>& p) {
  std::string s;
  char buf[40];
  for (double v : p) {
    std::snprintf(buf, sizeof buf, "%.17g", v);
    if (!s.empty()) s += ',';
    s += buf;
  }
  return s;
}

}  // namespace

// ------------------------------------------------------------------ cameras

double SfmCamera::FocalPx() const {
  if (params.empty()) return 0;
  const bool two = model == "PINHOLE" || model == "OPENCV" || model == "FULL_OPENCV" ||
                   model == "OPENCV_FISHEYE";
  return two && params.size() >= 2 ? 0.5 * (params[0] + params[1]) : params[0];
}

bool ProjectColmap(const SfmCamera& cam, const Eigen::Vector3d& p, Eigen::Vector2d* px) {
  if (!(p.z() > 0) || static_cast<int>(cam.params.size()) != ParamCount(cam.model)) return false;
  const auto& k = cam.params;
  const double x = p.x() / p.z(), y = p.y() / p.z();
  const double r2 = x * x + y * y;
  double fx, fy, cx, cy, xd = x, yd = y;
  if (cam.model == "SIMPLE_PINHOLE" || cam.model == "SIMPLE_RADIAL" || cam.model == "RADIAL") {
    fx = fy = k[0];
    cx = k[1];
    cy = k[2];
    double radial = 0;
    if (cam.model == "SIMPLE_RADIAL") radial = k[3] * r2;
    if (cam.model == "RADIAL") radial = k[3] * r2 + k[4] * r2 * r2;
    xd = x * (1 + radial);
    yd = y * (1 + radial);
  } else {
    fx = k[0];
    fy = k[1];
    cx = k[2];
    cy = k[3];
    if (cam.model == "OPENCV" || cam.model == "FULL_OPENCV") {
      const double k1 = k[4], k2 = k[5], p1 = k[6], p2 = k[7];
      double radial = 1 + k1 * r2 + k2 * r2 * r2;
      if (cam.model == "FULL_OPENCV") {
        radial += k[8] * r2 * r2 * r2;
        radial /= 1 + k[9] * r2 + k[10] * r2 * r2 + k[11] * r2 * r2 * r2;
      }
      xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
      yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
    }
  }
  *px = Eigen::Vector2d(fx * xd + cx, fy * yd + cy);
  return true;
}

SfmCamera ColmapCameraFromOpenCv(const CameraModel& c) {
  SfmCamera out;
  out.id = 1;
  out.width = c.width;
  out.height = c.height;
  const double cx = c.cx + 0.5, cy = c.cy + 0.5;  // OpenCV: pixel centres at integers
  const bool radial_only = c.p1 == 0 && c.p2 == 0 && c.k3 == 0;
  const bool no_dist = radial_only && c.k1 == 0 && c.k2 == 0;
  const bool square = std::abs(c.fx - c.fy) <= 1e-9 * std::abs(c.fx);
  if (no_dist) {
    out.model = "PINHOLE";
    out.params = {c.fx, c.fy, cx, cy};
  } else if (radial_only && square) {
    out.model = "RADIAL";
    out.params = {c.fx, cx, cy, c.k1, c.k2};
  } else if (c.k3 == 0) {
    out.model = "OPENCV";
    out.params = {c.fx, c.fy, cx, cy, c.k1, c.k2, c.p1, c.p2};
  } else {
    out.model = "FULL_OPENCV";
    out.params = {c.fx, c.fy, cx, cy, c.k1, c.k2, c.p1, c.p2, c.k3, 0, 0, 0};
  }
  return out;
}

Result<CameraModel> OpenCvCameraFromColmap(const SfmCamera& cam) {
  if (static_cast<int>(cam.params.size()) != ParamCount(cam.model)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "camera model " + cam.model + " has no OpenCV equivalent here");
  }
  const auto& k = cam.params;
  CameraModel c;
  c.width = cam.width;
  c.height = cam.height;
  if (cam.model == "SIMPLE_PINHOLE" || cam.model == "SIMPLE_RADIAL" || cam.model == "RADIAL") {
    c.fx = c.fy = k[0];
    c.cx = k[1] - 0.5;
    c.cy = k[2] - 0.5;
    if (cam.model == "SIMPLE_RADIAL") c.k1 = k[3];
    if (cam.model == "RADIAL") {
      c.k1 = k[3];
      c.k2 = k[4];
    }
    return c;
  }
  c.fx = k[0];
  c.fy = k[1];
  c.cx = k[2] - 0.5;
  c.cy = k[3] - 0.5;
  if (cam.model == "OPENCV" || cam.model == "FULL_OPENCV") {
    c.k1 = k[4];
    c.k2 = k[5];
    c.p1 = k[6];
    c.p2 = k[7];
  }
  if (cam.model == "FULL_OPENCV") {
    if (k[9] != 0 || k[10] != 0 || k[11] != 0) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "FULL_OPENCV camera with k4..k6 has no 5-parameter OpenCV equivalent");
    }
    c.k3 = k[8];
  }
  return c;
}

// -------------------------------------------------------------- text model

const SfmCamera* SfmModel::FindCamera(int id) const {
  for (const auto& c : cameras)
    if (c.id == id) return &c;
  return nullptr;
}
const SfmImage* SfmModel::FindImage(int id) const {
  for (const auto& i : images)
    if (i.id == id) return &i;
  return nullptr;
}
const SfmImage* SfmModel::FindImageByName(const std::string& name) const {
  for (const auto& i : images)
    if (i.name == name) return &i;
  return nullptr;
}

namespace {

// Reads data lines of a COLMAP text file; `keep_empty` keeps empty lines
// (images.txt: an image without observations has an empty second line).
Result<std::vector<std::pair<int, std::string>>> ReadDataLines(const std::string& path,
                                                               bool keep_empty) {
  std::ifstream f(path);
  if (!f) {
    return PathExists(path)
               ? ErrnoError("cannot read " + path, errno)
               : MakeError(ErrorClass::kNotFound, "COLMAP model file missing: " + path);
  }
  std::vector<std::pair<int, std::string>> lines;
  std::string line;
  int no = 0;
  while (std::getline(f, line)) {
    ++no;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (!line.empty() && line[0] == '#') continue;
    if (line.empty() && !keep_empty) continue;
    lines.emplace_back(no, line);
  }
  return lines;
}

Error ParseError(const std::string& path, int line, const std::string& what) {
  return MakeError(ErrorClass::kCorrupt, "cannot parse COLMAP model " + path + " line " +
                                             std::to_string(line) + ": " + what);
}

}  // namespace

Result<SfmModel> ReadColmapTextModel(const std::string& dir) {
  SfmModel m;
  const std::string cam_path = dir + "/cameras.txt", img_path = dir + "/images.txt",
                    pts_path = dir + "/points3D.txt";

  auto cam_lines = ReadDataLines(cam_path, false);
  if (!cam_lines) return cam_lines.error();
  for (const auto& [no, line] : *cam_lines) {
    std::istringstream ss(line);
    SfmCamera c;
    if (!(ss >> c.id >> c.model >> c.width >> c.height))
      return ParseError(cam_path, no, "expected ID MODEL WIDTH HEIGHT PARAMS");
    double v;
    while (ss >> v) c.params.push_back(v);
    const int want = ParamCount(c.model);
    if (want >= 0 && static_cast<int>(c.params.size()) != want) {
      return ParseError(cam_path, no, c.model + " needs " + std::to_string(want) + " parameters");
    }
    m.cameras.push_back(std::move(c));
  }

  auto img_lines = ReadDataLines(img_path, true);
  if (!img_lines) return img_lines.error();
  const auto& il = *img_lines;
  for (size_t i = 0; i < il.size(); ++i) {
    if (il[i].second.empty()) continue;  // trailing blank line
    std::istringstream ss(il[i].second);
    SfmImage im;
    double qw, qx, qy, qz, tx, ty, tz;
    if (!(ss >> im.id >> qw >> qx >> qy >> qz >> tx >> ty >> tz >> im.camera_id >> im.name)) {
      return ParseError(img_path, il[i].first,
                        "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
    }
    Eigen::Quaterniond q(qw, qx, qy, qz);
    if (!(std::abs(q.norm() - 1) < 1e-3))
      return ParseError(img_path, il[i].first, "quaternion is not unit length");
    im.R_cam_world = q.normalized().toRotationMatrix();
    im.t_cam_world = Eigen::Vector3d(tx, ty, tz);
    if (!m.FindCamera(im.camera_id))
      return ParseError(img_path, il[i].first, "unknown camera " + std::to_string(im.camera_id));
    if (i + 1 < il.size()) {
      ++i;
      std::istringstream ps(il[i].second);
      double x, y;
      long long pid;
      while (ps >> x >> y >> pid) {
        im.points2d.emplace_back(x, y);
        im.point3d_ids.push_back(pid);
      }
      if (!ps.eof()) return ParseError(img_path, il[i].first, "expected X Y POINT3D_ID triples");
    }
    m.images.push_back(std::move(im));
  }

  auto pt_lines = ReadDataLines(pts_path, false);
  if (!pt_lines) return pt_lines.error();
  std::map<int, const SfmImage*> by_id;
  for (const auto& im : m.images) by_id[im.id] = &im;
  m.points.reserve(pt_lines->size());
  for (const auto& [no, line] : *pt_lines) {
    std::istringstream ss(line);
    SfmPoint p;
    int r, g, b;
    if (!(ss >> p.id >> p.xyz.x() >> p.xyz.y() >> p.xyz.z() >> r >> g >> b >> p.error_px)) {
      return ParseError(pts_path, no, "expected POINT3D_ID X Y Z R G B ERROR TRACK");
    }
    p.rgb = {static_cast<uint8_t>(r), static_cast<uint8_t>(g), static_cast<uint8_t>(b)};
    SfmTrackElement t;
    while (ss >> t.image_id >> t.point2d_idx) {
      auto it = by_id.find(t.image_id);
      if (it == by_id.end())
        return ParseError(pts_path, no,
                          "track refers to unknown image " + std::to_string(t.image_id));
      if (t.point2d_idx < 0 || t.point2d_idx >= static_cast<int>(it->second->points2d.size())) {
        return ParseError(
            pts_path, no,
            "track refers to a missing 2D point of image " + std::to_string(t.image_id));
      }
      p.track.push_back(t);
    }
    if (!ss.eof()) return ParseError(pts_path, no, "expected IMAGE_ID POINT2D_IDX pairs");
    m.points.push_back(std::move(p));
  }
  return m;
}

Status WriteColmapTextModel(const std::string& dir, const SfmModel& m) {
  if (auto st = MakeDirsDurable(dir); !st) return st;
  char buf[256];
  std::string cams =
      "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, "
      "PARAMS[]\n";
  for (const auto& c : m.cameras) {
    std::snprintf(buf, sizeof buf, "%d %s %d %d", c.id, c.model.c_str(), c.width, c.height);
    cams += buf;
    for (double v : c.params) {
      std::snprintf(buf, sizeof buf, " %.17g", v);
      cams += buf;
    }
    cams += '\n';
  }
  std::string imgs =
      "# Image list with two lines of data per image:\n"
      "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
      "#   POINTS2D[] as (X, Y, POINT3D_ID)\n";
  for (const auto& im : m.images) {
    Eigen::Quaterniond q(im.R_cam_world);
    q.normalize();
    if (q.w() < 0) q.coeffs() *= -1;
    std::snprintf(buf, sizeof buf, "%d %.17g %.17g %.17g %.17g %.17g %.17g %.17g %d ", im.id, q.w(),
                  q.x(), q.y(), q.z(), im.t_cam_world.x(), im.t_cam_world.y(), im.t_cam_world.z(),
                  im.camera_id);
    imgs += buf;
    imgs += im.name;
    imgs += '\n';
    for (size_t k = 0; k < im.points2d.size(); ++k) {
      std::snprintf(buf, sizeof buf, "%s%.10g %.10g %lld", k ? " " : "", im.points2d[k].x(),
                    im.points2d[k].y(), static_cast<long long>(im.point3d_ids[k]));
      imgs += buf;
    }
    imgs += '\n';
  }
  std::string pts =
      "# 3D point list with one line of data per point:\n"
      "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n";
  for (const auto& p : m.points) {
    std::snprintf(buf, sizeof buf, "%lld %.17g %.17g %.17g %d %d %d %.10g",
                  static_cast<long long>(p.id), p.xyz.x(), p.xyz.y(), p.xyz.z(), p.rgb[0], p.rgb[1],
                  p.rgb[2], p.error_px);
    pts += buf;
    for (const auto& t : p.track) {
      std::snprintf(buf, sizeof buf, " %d %d", t.image_id, t.point2d_idx);
      pts += buf;
    }
    pts += '\n';
  }
  if (auto st = WriteFileAtomic(dir + "/cameras.txt", cams); !st) return st;
  if (auto st = WriteFileAtomic(dir + "/images.txt", imgs); !st) return st;
  return WriteFileAtomic(dir + "/points3D.txt", pts);
}

double MeanReprojectionErrorPx(const SfmModel& m) {
  std::map<int, const SfmImage*> by_id;
  for (const auto& im : m.images) by_id[im.id] = &im;
  std::map<int, const SfmCamera*> cams;
  for (const auto& c : m.cameras) cams[c.id] = &c;
  double sum = 0, fallback_sum = 0;
  long n = 0, fallback_n = 0;
  bool projectable = true;
  for (const auto& p : m.points) {
    fallback_sum += p.error_px;
    ++fallback_n;
    for (const auto& t : p.track) {
      const SfmImage* im = by_id.at(t.image_id);
      Eigen::Vector2d px;
      if (!ProjectColmap(*cams.at(im->camera_id), im->R_cam_world * p.xyz + im->t_cam_world, &px)) {
        if (ParamCount(cams.at(im->camera_id)->model) < 0) projectable = false;
        continue;  // behind the camera: counted by the points_in_front check
      }
      sum += (px - im->points2d[t.point2d_idx]).norm();
      ++n;
    }
  }
  if (!projectable) return fallback_n ? fallback_sum / fallback_n : 0;
  return n ? sum / n : 0;
}

// --------------------------------------------------------------- similarity

Result<Similarity3> EstimateSimilarity(const std::vector<Eigen::Vector3d>& src,
                                       const std::vector<Eigen::Vector3d>& dst, bool with_scale,
                                       double* rms) {
  if (src.size() != dst.size()) {
    return MakeError(ErrorClass::kInvalidArgument, "similarity: point lists differ in length");
  }
  const size_t n = src.size();
  if (n < 3)
    return MakeError(ErrorClass::kInvalidArgument, "similarity: needs at least 3 point pairs");
  Eigen::Vector3d ms = Eigen::Vector3d::Zero(), md = Eigen::Vector3d::Zero();
  for (size_t i = 0; i < n; ++i) {
    ms += src[i];
    md += dst[i];
  }
  ms /= static_cast<double>(n);
  md /= static_cast<double>(n);
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero(), css = Eigen::Matrix3d::Zero();
  double var_s = 0;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d a = src[i] - ms, b = dst[i] - md;
    cov += b * a.transpose();
    css += a * a.transpose();
    var_s += a.squaredNorm();
  }
  cov /= static_cast<double>(n);
  var_s /= static_cast<double>(n);
  // Both point sets must span at least a plane, or the rotation about the
  // line they lie on is undetermined.
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(css);
  const Eigen::Vector3d& ev = es.eigenvalues();  // ascending
  if (!(ev(2) > 0) || ev(1) < 1e-10 * ev(2)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "similarity: source points are (nearly) collinear or coincide");
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(cov, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d& U = svd.matrixU();
  const Eigen::Matrix3d& V = svd.matrixV();
  Eigen::Vector3d d(1, 1, 1);
  if (U.determinant() * V.determinant() < 0) d(2) = -1;  // no reflection
  Similarity3 s;
  s.R = U * d.asDiagonal() * V.transpose();
  s.scale = with_scale ? svd.singularValues().dot(d) / var_s : 1.0;
  if (!(s.scale > 0) || !std::isfinite(s.scale)) {
    return MakeError(ErrorClass::kInvalidArgument, "similarity: degenerate destination points");
  }
  s.t = md - s.scale * s.R * ms;
  if (rms) {
    double e = 0;
    for (size_t i = 0; i < n; ++i) e += (s.Apply(src[i]) - dst[i]).squaredNorm();
    *rms = std::sqrt(e / static_cast<double>(n));
  }
  return s;
}

void ApplySimilarity(const Similarity3& s, SfmModel* m) {
  for (auto& p : m->points) p.xyz = s.Apply(p.xyz);
  for (auto& im : m->images) {
    const Eigen::Vector3d c = s.Apply(im.Centre());
    im.R_cam_world = im.R_cam_world * s.R.transpose();
    im.t_cam_world = -im.R_cam_world * c;
  }
}

// ------------------------------------------------------------ plausibility

bool SfmCheckReport::ok() const { return FirstFailure() == nullptr; }

const SfmCheck* SfmCheckReport::FirstFailure() const {
  for (const auto& c : checks)
    if (c.applicable && !c.passed) return &c;
  return nullptr;
}

const SfmCheck* SfmCheckReport::Find(const std::string& name) const {
  for (const auto& c : checks)
    if (c.name == name) return &c;
  return nullptr;
}

Error SfmCheckReport::ToError() const {
  const SfmCheck* f = FirstFailure();
  if (!f) return MakeError(ErrorClass::kInternal, "SfM model checks passed; no error to report");
  std::string all;
  for (const auto& c : checks) {
    if (c.applicable && !c.passed) all += (all.empty() ? "" : "; ") + c.name + ": " + c.detail;
  }
  return MakeError(
      ErrorClass::kCorrupt,
      "SfM model rejected: check " + f->name + " failed: " + f->detail + ". " + f->advice, all);
}

nlohmann::json SfmCheckReport::ToJson() const {
  nlohmann::json a = nlohmann::json::array();
  for (const auto& c : checks) {
    nlohmann::json j{{"name", c.name}, {"applicable", c.applicable}, {"detail", c.detail}};
    if (c.applicable) {
      j["passed"] = c.passed;
      j["value"] = std::isfinite(c.value) ? nlohmann::json(c.value) : nlohmann::json(nullptr);
      j["limit"] = c.limit;
    }
    a.push_back(std::move(j));
  }
  return {{"ok", ok()}, {"checks", std::move(a)}};
}

namespace {

SfmCheck NotApplicable(const std::string& name, const std::string& why) {
  SfmCheck c;
  c.name = name;
  c.applicable = false;
  c.detail = why;
  return c;
}

SfmCheck Bound(const std::string& name, double value, double limit, bool upper,
               const std::string& detail, const std::string& advice) {
  SfmCheck c;
  c.name = name;
  c.value = value;
  c.limit = limit;
  c.passed = std::isfinite(value) && (upper ? value <= limit : value >= limit);
  c.detail = detail;
  c.advice = advice;
  return c;
}

// Geometry of a ring of camera centres: plane, circle, axis.
struct RingFit {
  Eigen::Vector3d centre, normal, u, v;
  double radius = 0, plane_rms = 0, radial_rms = 0;
};

std::optional<RingFit> FitRing(const std::vector<Eigen::Vector3d>& pts) {
  const size_t n = pts.size();
  if (n < 4) return std::nullopt;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& p : pts) mean += p;
  mean /= static_cast<double>(n);
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : pts) cov += (p - mean) * (p - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  RingFit r;
  r.normal = es.eigenvectors().col(0);
  r.u = es.eigenvectors().col(2);
  r.v = r.normal.cross(r.u);
  // Kåsa circle fit in the plane: x² + y² + a x + b y + c = 0.
  Eigen::MatrixXd A(n, 3);
  Eigen::VectorXd rhs(n);
  std::vector<Eigen::Vector2d> q(n);
  for (size_t i = 0; i < n; ++i) {
    q[i] = Eigen::Vector2d((pts[i] - mean).dot(r.u), (pts[i] - mean).dot(r.v));
    A.row(static_cast<Eigen::Index>(i)) << q[i].x(), q[i].y(), 1;
    rhs(static_cast<Eigen::Index>(i)) = -q[i].squaredNorm();
  }
  const Eigen::Vector3d abc = A.colPivHouseholderQr().solve(rhs);
  const Eigen::Vector2d c2(-abc(0) / 2, -abc(1) / 2);
  const double r2 = c2.squaredNorm() - abc(2);
  if (!(r2 > 0)) return std::nullopt;
  r.radius = std::sqrt(r2);
  r.centre = mean + c2.x() * r.u + c2.y() * r.v;
  double pe = 0, re = 0;
  for (size_t i = 0; i < n; ++i) {
    const double h = (pts[i] - mean).dot(r.normal);
    pe += h * h;
    const double d = (q[i] - c2).norm() - r.radius;
    re += d * d;
  }
  r.plane_rms = std::sqrt(pe / static_cast<double>(n));
  r.radial_rms = std::sqrt(re / static_cast<double>(n));
  return r;
}

}  // namespace

SfmCheckReport CheckSfmModel(const SfmModel& m, const SfmExpectations& e,
                             const SfmCheckOptions& o) {
  SfmCheckReport rep;
  auto& out = rep.checks;
  const int nreg = static_cast<int>(m.images.size());
  const int nin = std::max(e.num_input_images, nreg);
  const double frac = nin ? static_cast<double>(nreg) / nin : 0;
  {
    SfmCheck c = Bound(
        "registered_fraction", frac, o.min_registered_fraction, false,
        std::to_string(nreg) + " of " + std::to_string(nin) + " views registered" +
            Fmt(" (%.0f %%, need %.0f %%)", 100 * frac, 100 * o.min_registered_fraction),
        "too few views joined the model: check that the masks cover the rock, use low-texture SIFT "
        "(SiftOptions::LowTexture), match more neighbours, fix the intrinsics from the rig "
        "calibration, "
        "or re-shoot with smaller turntable steps");
    if (nreg < o.min_registered) c.passed = false;
    out.push_back(c);
  }
  out.push_back(Bound(
      "point_count", static_cast<double>(m.points.size()), o.min_points, false,
      std::to_string(m.points.size()) + " 3D points (need " + std::to_string(o.min_points) + ")",
      "too few triangulated points: the object has too little texture or the views overlap too "
      "little"));

  const double reproj = MeanReprojectionErrorPx(m);
  out.push_back(
      Bound("reprojection_error", reproj, o.max_mean_reprojection_px, true,
            Fmt("mean reprojection error %.3f px (limit %.2f)", reproj, o.max_mean_reprojection_px),
            "bad matches or a wrong lens model: calibrate the camera and fix its intrinsics"));

  // Intrinsics: unchanged when fixed, near the expected focal otherwise.
  if (e.fixed_camera) {
    const SfmCamera want = ColmapCameraFromOpenCv(*e.fixed_camera);
    double worst = 0;
    std::string what = "every camera keeps the fixed " + want.model + " parameters";
    for (const auto& c : m.cameras) {
      if (c.model != want.model || c.params.size() != want.params.size()) {
        worst = INFINITY;
        what =
            "camera " + std::to_string(c.id) + " is " + c.model + ", fixed model was " + want.model;
        break;
      }
      const double scale = std::max(1.0, std::abs(want.params[0]));
      for (size_t k = 0; k < c.params.size(); ++k) {
        worst = std::max(worst, std::abs(c.params[k] - want.params[k]) / scale);
      }
    }
    if (std::isfinite(worst) && worst > o.fixed_param_rel_tol)
      what = Fmt("fixed intrinsics changed by %.3g (relative)", worst);
    out.push_back(Bound("fixed_intrinsics", worst, o.fixed_param_rel_tol, true, what,
                        "COLMAP changed intrinsics that were passed as fixed: check the camera "
                        "model and flags (a bug)"));
    out.push_back(NotApplicable("focal_length", "intrinsics fixed"));
  } else if (e.expected_focal_px && *e.expected_focal_px > 0) {
    out.push_back(NotApplicable("fixed_intrinsics", "intrinsics not fixed"));
    double worst = 0, worst_f = 0;
    for (const auto& c : m.cameras) {
      const double rel = std::abs(c.FocalPx() - *e.expected_focal_px) / *e.expected_focal_px;
      if (rel >= worst) {
        worst = rel;
        worst_f = c.FocalPx();
      }
    }
    out.push_back(Bound("focal_length", worst, o.max_focal_rel_error, true,
                        Fmt("focal %.1f px vs expected %.1f px (%.0f %% off)", worst_f,
                            *e.expected_focal_px, 100 * worst) +
                            Fmt(", limit %.0f %%", 100 * o.max_focal_rel_error),
                        "COLMAP converged to a wrong focal length (known on low-texture objects): "
                        "fix the intrinsics "
                        "from the rig calibration (aggscan calibrate)"));
  } else {
    out.push_back(NotApplicable("fixed_intrinsics", "intrinsics not fixed"));
    out.push_back(NotApplicable("focal_length", "no expected focal length given"));
  }

  // Cheirality of every observation.
  {
    std::map<int, const SfmImage*> by_id;
    for (const auto& im : m.images) by_id[im.id] = &im;
    long total = 0, front = 0;
    for (const auto& p : m.points) {
      for (const auto& t : p.track) {
        auto it = by_id.find(t.image_id);
        if (it == by_id.end()) continue;
        ++total;
        if ((it->second->R_cam_world * p.xyz + it->second->t_cam_world).z() > 0) ++front;
      }
    }
    if (total == 0) {
      out.push_back(NotApplicable("points_in_front", "no observations"));
    } else {
      const double f = static_cast<double>(front) / total;
      out.push_back(Bound(
          "points_in_front", f, o.min_points_in_front, false,
          Fmt("%.2f %% of observations in front of their camera (need %.0f %%)", 100 * f,
              100 * o.min_points_in_front),
          "the model has points behind the cameras that see them: it is inconsistent; re-run with "
          "fixed intrinsics"));
    }
  }

  // Turntable ring.
  static const char* kRing[] = {"ring_plane",     "ring_circle", "ring_facing",
                                "ring_direction", "ring_angles", "ring_points"};
  if (!e.ring) {
    for (const char* n : kRing) out.push_back(NotApplicable(n, "not a turntable ring capture"));
    return rep;
  }
  std::vector<const SfmImage*> ordered;
  for (const auto& im : m.images) ordered.push_back(&im);
  std::sort(ordered.begin(), ordered.end(), [](const SfmImage* a, const SfmImage* b) {
    return a->input_index != b->input_index ? a->input_index < b->input_index : a->id < b->id;
  });
  std::vector<Eigen::Vector3d> centres;
  centres.reserve(ordered.size());
  for (const auto* im : ordered) centres.push_back(im->Centre());
  const auto ring = FitRing(centres);
  if (!ring) {
    const std::string why =
        nreg < 4 ? "fewer than 4 views registered" : "camera centres fit no circle";
    for (const char* n : kRing) {
      SfmCheck c = NotApplicable(n, why);
      if (nreg >= 4 && std::string(n) == "ring_circle") {  // 4+ views but collinear: a real failure
        c.applicable = true;
        c.passed = false;
        c.value = INFINITY;
        c.advice =
            "camera centres do not lie on a circle: the model is wrong for a turntable capture";
      }
      out.push_back(c);
    }
    return rep;
  }
  const double R = ring->radius;
  const std::string ring_advice =
      "camera centres do not form the turntable's ring: the model is wrong (e.g. wrong focal "
      "length or "
      "mis-ordered views); fix the intrinsics from the rig calibration, or use the calibrated "
      "turntable path";
  out.push_back(Bound("ring_plane", ring->plane_rms / R, o.max_ring_plane_rms, true,
                      Fmt("centres %.2f %% of the radius out of their plane (RMS; limit %.1f %%)",
                          100 * ring->plane_rms / R, 100 * o.max_ring_plane_rms),
                      ring_advice));
  out.push_back(
      Bound("ring_circle", ring->radial_rms / R, o.max_ring_radius_rms, true,
            Fmt("centres %.2f %% of the radius off the fitted circle (RMS; limit %.1f %%)",
                100 * ring->radial_rms / R, 100 * o.max_ring_radius_rms),
            ring_advice));

  // Each optical axis must pass near the ring axis, in front of the camera.
  {
    double worst = 0;
    std::string worst_name;
    for (const auto* im : ordered) {
      const Eigen::Vector3d c = im->Centre();
      const Eigen::Vector3d d = im->R_cam_world.transpose() * Eigen::Vector3d::UnitZ();
      const Eigen::Vector3d& a = ring->normal;
      const Eigen::Vector3d w = c - ring->centre;
      // Closest points of the ray c + s d and the line centre + t a.
      const double b = d.dot(a), dd = d.dot(w), ee = a.dot(w), den = 1 - b * b;
      double miss;
      if (den < 1e-9) {
        miss = (w - ee * a).norm();  // parallel: distance between the lines
      } else {
        const double s = (b * ee - dd) / den;
        const double t = (ee - b * dd) / den;
        miss = s <= 0 ? INFINITY : ((c + s * d) - (ring->centre + t * a)).norm();
      }
      if (miss / R >= worst) {
        worst = miss / R;
        worst_name = im->name;
      }
    }
    out.push_back(
        Bound("ring_facing", worst, o.max_axis_miss, true,
              std::isfinite(worst)
                  ? Fmt("optical axes pass the ring axis at up to %.3f radii (limit %.2f)", worst,
                        o.max_axis_miss) +
                        " (" + worst_name + ")"
                  : "camera " + worst_name + " looks away from the ring axis",
              "cameras do not look at the turntable axis: the rotations are wrong; fix the "
              "intrinsics from "
              "the rig calibration"));
  }

  // Angles around the ring, in capture order.
  std::vector<double> theta;
  for (const auto& c : centres) {
    const Eigen::Vector3d q = c - ring->centre;
    theta.push_back(std::atan2(q.dot(ring->v), q.dot(ring->u)) * 180 / kPi);
  }
  double sum = 0;
  std::vector<double> steps;
  for (size_t i = 1; i < theta.size(); ++i) {
    steps.push_back(WrapDeg(theta[i] - theta[i - 1]));
    sum += steps.back();
  }
  const double sense = sum >= 0 ? 1 : -1;
  {
    int backward = 0;
    for (double s : steps)
      if (sense * s < -o.max_angle_error_deg) ++backward;
    SfmCheck c = Bound(
        "ring_direction", backward, 0, true,
        std::to_string(backward) + " of " + std::to_string(steps.size()) +
            " steps between consecutive views go against the turning direction",
        "views are not ordered around the ring as captured: the model is wrong or the images are "
        "mis-ordered; check the view order and the intrinsics");
    out.push_back(c);
  }
  const bool have_angles = !e.angles_deg.empty();
  bool angles_ok = have_angles;
  for (const auto* im : ordered) {
    if (im->input_index < 0 || im->input_index >= static_cast<int>(e.angles_deg.size()))
      angles_ok = false;
  }
  if (!angles_ok) {
    out.push_back(NotApplicable("ring_angles", have_angles ? "views without an expected angle"
                                                           : "no expected angles given"));
  } else {
    // theta_i ≈ offset + sign * angle_i, the sign relating the model's sense
    // of rotation to the turntable's; offset as a circular mean.
    double asum = 0;
    for (size_t i = 1; i < ordered.size(); ++i) {
      asum += WrapDeg(e.angles_deg[ordered[i]->input_index] -
                      e.angles_deg[ordered[i - 1]->input_index]);
    }
    const double sign = asum >= 0 ? sense : -sense;
    double sx = 0, sy = 0;
    for (size_t i = 0; i < ordered.size(); ++i) {
      const double d = (theta[i] - sign * e.angles_deg[ordered[i]->input_index]) * kPi / 180;
      sx += std::cos(d);
      sy += std::sin(d);
    }
    const double offset = std::atan2(sy, sx) * 180 / kPi;
    double worst = 0;
    std::string worst_name;
    for (size_t i = 0; i < ordered.size(); ++i) {
      const double err =
          std::abs(WrapDeg(theta[i] - offset - sign * e.angles_deg[ordered[i]->input_index]));
      if (err >= worst) {
        worst = err;
        worst_name = ordered[i]->name;
      }
    }
    out.push_back(Bound(
        "ring_angles", worst, o.max_angle_error_deg, true,
        Fmt("view angles differ from the turntable's by up to %.2f deg (limit %.1f)", worst,
            o.max_angle_error_deg) +
            " (" + worst_name + ")",
        "camera positions do not follow the turntable angles: the model is wrong, or the turntable "
        "slipped; check the turntable and the intrinsics"));
  }
  // The object sits near the axis, inside the ring.
  if (m.points.empty()) {
    out.push_back(NotApplicable("ring_points", "no 3D points"));
  } else {
    std::vector<double> dist;
    dist.reserve(m.points.size());
    for (const auto& p : m.points) {
      const Eigen::Vector3d w = p.xyz - ring->centre;
      dist.push_back((w - w.dot(ring->normal) * ring->normal).norm() / R);
    }
    std::nth_element(dist.begin(), dist.begin() + static_cast<long>(dist.size() / 2), dist.end());
    const double med = dist[dist.size() / 2];
    out.push_back(Bound("ring_points", med, o.max_points_off_axis, true,
                        Fmt("median 3D point %.2f radii from the ring axis (limit %.2f)", med,
                            o.max_points_off_axis),
                        "the reconstructed points are not on the turntable: the static background "
                        "was reconstructed; "
                        "use foreground masks"));
  }
  return rep;
}

// --------------------------------------------------------------- the runner

SiftOptions SiftOptions::LowTexture() {
  SiftOptions s;
  s.peak_threshold = 0.002;
  s.estimate_affine_shape = true;
  s.domain_size_pooling = true;
  return s;
}

std::vector<std::pair<int, int>> CircularPairs(int n, int k) {
  std::vector<std::pair<int, int>> out;
  std::set<std::pair<int, int>> seen;
  for (int i = 0; i < n; ++i) {
    for (int d = 1; d <= k && d < n; ++d) {
      const int j = (i + d) % n;
      if (seen.insert({std::min(i, j), std::max(i, j)}).second) out.emplace_back(i, j);
    }
  }
  return out;
}

std::vector<std::pair<int, int>> AnglePairs(const std::vector<double>& angles_deg, int k) {
  const int n = static_cast<int>(angles_deg.size());
  std::vector<std::pair<int, int>> out;
  if (n < 2 || k < 1) return out;
  std::vector<double> steps;
  for (int i = 0; i < n; ++i) {
    if (!std::isfinite(angles_deg[i])) return out;
    if (i > 0) {
      const double d = std::abs(WrapDeg(angles_deg[i] - angles_deg[i - 1]));
      if (d > 1.0) steps.push_back(d);  // repeats of one angle are not steps
    }
  }
  if (steps.empty()) return out;
  std::nth_element(steps.begin(), steps.begin() + steps.size() / 2, steps.end());
  const double step = steps[steps.size() / 2];
  // Half a step of slack: the encoder's angles carry repeatability and backlash.
  const double window = std::min(180.0, (k + 0.5) * step);
  for (int i = 0; i < n; ++i) {
    for (int j = i + 1; j < n; ++j) {
      if (std::abs(WrapDeg(angles_deg[j] - angles_deg[i])) <= window) out.emplace_back(i, j);
    }
  }
  return out;
}

std::vector<std::string> ColmapSfmOptions::Check() const {
  std::vector<std::string> p;
  if (colmap_binary.empty()) p.push_back("colmap_binary is empty");
  if (workspace.empty()) p.push_back("workspace is empty");
  if (images.size() < 2)
    p.push_back("need at least 2 images, got " + std::to_string(images.size()));
  if (!masks.empty() && masks.size() != images.size()) {
    p.push_back("masks: " + std::to_string(masks.size()) + " given for " +
                std::to_string(images.size()) + " images");
  }
  std::set<std::string> names;
  for (const auto& im : images) {
    const std::string n = fs::path(im).filename().string();
    if (n.empty()) p.push_back("image path without a file name: " + im);
    if (!names.insert(n).second)
      p.push_back("image file name appears twice (COLMAP keys images by name): " + n);
  }
  if (fixed_camera && (fixed_camera->fx <= 0 || fixed_camera->fy <= 0 || fixed_camera->width <= 0 ||
                       fixed_camera->height <= 0)) {
    p.push_back("fixed_camera needs positive focal lengths and size");
  }
  if (expected_focal_px && !(*expected_focal_px > 0))
    p.push_back("expected_focal_px must be positive");
  if (ParamCount(free_camera_model) < 0 || free_camera_model == "FULL_OPENCV") {
    p.push_back(
        "free_camera_model must be SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV, got " +
        free_camera_model);
  }
  if (sift.max_image_size < 100) p.push_back("sift.max_image_size must be >= 100 px");
  if (sift.max_num_features < 100) p.push_back("sift.max_num_features must be >= 100");
  if (!(sift.peak_threshold > 0)) p.push_back("sift.peak_threshold must be positive");
  if (matching.mode == SfmMatching::kCircular && matching.circular_neighbours < 1) {
    p.push_back("matching.circular_neighbours must be >= 1");
  }
  if (!angles_deg.empty() && angles_deg.size() != images.size()) {
    p.push_back("angles_deg: " + std::to_string(angles_deg.size()) + " given for " +
                std::to_string(images.size()) + " images");
  }
  if (num_threads < 1) p.push_back("num_threads must be >= 1");
  if (!(step_timeout_s > 0)) p.push_back("step_timeout_s must be positive");
  return p;
}

const SfmImage* SfmResult::ImageForInput(int input_index) const {
  for (const auto& im : model.images)
    if (im.input_index == input_index) return &im;
  return nullptr;
}

namespace {

// Read-only look into COLMAP's database: what the steps really wrote.
class ColmapDb {
 public:
  static Result<ColmapDb> Open(const std::string& path, bool writable = false) {
    if (!PathExists(path))
      return MakeError(ErrorClass::kNotFound, "COLMAP database missing: " + path);
    sqlite3* db = nullptr;
    const int flags = writable ? SQLITE_OPEN_READWRITE : SQLITE_OPEN_READONLY;
    if (sqlite3_open_v2(path.c_str(), &db, flags, nullptr) != SQLITE_OK) {
      std::string msg = db ? sqlite3_errmsg(db) : "out of memory";
      sqlite3_close(db);
      return MakeError(ErrorClass::kCorrupt, "cannot open COLMAP database " + path, msg);
    }
    sqlite3_busy_timeout(db, 5000);
    return ColmapDb(db);
  }
  ColmapDb(ColmapDb&& o) noexcept : db_(o.db_) { o.db_ = nullptr; }
  ~ColmapDb() { sqlite3_close(db_); }

  // Runs `sql`, calling row(stmt) per result row.
  template <typename F>
  Status Query(const std::string& sql, F row) {
    sqlite3_stmt* st = nullptr;
    if (sqlite3_prepare_v2(db_, sql.c_str(), -1, &st, nullptr) != SQLITE_OK) {
      return MakeError(ErrorClass::kCorrupt, "COLMAP database is not as expected",
                       sqlite3_errmsg(db_));
    }
    int rc;
    while ((rc = sqlite3_step(st)) == SQLITE_ROW) row(st);
    std::string err = rc == SQLITE_DONE ? "" : sqlite3_errmsg(db_);
    sqlite3_finalize(st);
    if (!err.empty()) return MakeError(ErrorClass::kCorrupt, "COLMAP database query failed", err);
    return OkStatus();
  }
  Status Exec(const std::string& sql) {
    char* msg = nullptr;
    if (sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &msg) != SQLITE_OK) {
      std::string m = msg ? msg : "";
      sqlite3_free(msg);
      return MakeError(ErrorClass::kIo, "cannot modify COLMAP database", m);
    }
    return OkStatus();
  }

 private:
  explicit ColmapDb(sqlite3* db) : db_(db) {}
  sqlite3* db_;
};

struct FileStamp {
  long long size = -1, mtime_ns = -1;
};
FileStamp Stamp(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return {};
  return {static_cast<long long>(st.st_size),
          static_cast<long long>(st.st_mtim.tv_sec) * 1000000000LL + st.st_mtim.tv_nsec};
}

// One run: paths, the steps' bookkeeping.
class SfmRun {
 public:
  explicit SfmRun(const ColmapSfmOptions& o)
      : o_(o), ws_(fs::absolute(o.workspace).lexically_normal().string()) {}

  Result<SfmResult> Run();

 private:
  std::string P(const std::string& rel) const { return ws_ + "/" + rel; }
  Status PrepareWorkspace();
  Status ChooseCrop();
  Status ResolveCamera();
  void Uncrop(SfmModel* m) const;
  // Runs one COLMAP command; `step` names the log and the messages.
  Status Colmap(const std::string& step, const std::string& log_name, std::vector<std::string> args,
                double* wall_s);
  // Skips the stage if its marker matches and check() passes; else runs it.
  Status Stage(const std::string& name, const nlohmann::json& fingerprint,
               const std::function<Status()>& clean, const std::function<Status(double*)>& run,
               const std::function<Status()>& check);
  Status CheckExtraction();
  Status CheckMatching();
  Status CheckMapper();
  Status CheckConverted();
  std::vector<std::string> ModelDirs() const;  // sparse/<k> that hold a model, sorted by k

  const ColmapSfmOptions& o_;
  std::string ws_;
  std::vector<std::string> names_;
  bool redo_ = false;  // an earlier stage ran: every later one runs too
  std::vector<SfmStepTiming> timings_;
  std::string camera_model_, camera_params_;  // --ImageReader flags
  SfmCamera fixed_colmap_;                    // when fixed
  std::vector<double> fixed_params_;          // the fixed camera as passed (the window's)
  cv::Size frame_;                            // the input images' size
  cv::Rect crop_;                             // the window every image is cut to; empty: none
  int verified_pairs_ = 0;
};

Status SfmRun::Colmap(const std::string& step, const std::string& log_name,
                      std::vector<std::string> args, double* wall_s) {
  args.insert(args.begin(), {o_.colmap_binary, step});
  args.insert(args.end(), {"--log_to_stderr", "1"});  // glog to our log, not to files in /tmp
  SubprocessOptions so;
  so.log_path = P("logs/" + log_name + ".log");
  so.timeout_s = o_.step_timeout_s;
  so.cancel = o_.cancel;
  AGG_LOGI(kLog, "colmap %s (log %s)", step.c_str(), so.log_path.c_str());
  auto r = RunSubprocess(args, so);
  if (!r) {
    Error e = r.error();
    if (e.cls == ErrorClass::kNotFound) {
      e.message = "COLMAP not found at " + o_.colmap_binary +
                  ": install Debian's colmap package (scripts/install-deps.sh) or set the colmap "
                  "binary path";
    } else if (e.cls == ErrorClass::kTimeout) {
      e.message = "COLMAP " + step + " ran longer than " + Fmt("%.0f s", o_.step_timeout_s) +
                  " and was killed: reduce the image size or the number of pairs; log " +
                  so.log_path;
    }
    return e;
  }
  *wall_s = r->wall_s;
  if (!r->Succeeded()) {
    std::string msg = "COLMAP " + step + " failed (" + r->Describe() + ")";
    if (r->term_signal == 9) msg += ", possibly out of memory: lower the maximum image size";
    return MakeError(ErrorClass::kIo, msg + "; see " + so.log_path, TailOfFile(so.log_path, 6));
  }
  return OkStatus();
}

Status SfmRun::PrepareWorkspace() {
  for (const char* d : {"", "images", "masks", "logs", "stages"}) {
    if (auto st = MakeDirsDurable(P(d)); !st) return st;
  }
  std::set<std::string> want_images, want_masks;
  std::error_code ec;
  auto link = [&](const std::string& target, const std::string& at) -> Status {
    const std::string abs = fs::absolute(target).lexically_normal().string();
    if (!PathExists(abs)) return MakeError(ErrorClass::kNotFound, "SfM input missing: " + abs);
    std::error_code e2;
    if (fs::is_symlink(at, e2) && fs::read_symlink(at, e2).string() == abs) return OkStatus();
    fs::remove(at, e2);
    fs::create_symlink(abs, at, e2);
    if (e2) return MakeError(ErrorClass::kIo, "cannot link " + at + " -> " + abs, e2.message());
    return OkStatus();
  };
  if (auto st = ChooseCrop(); !st) return st;
  // A cut image replaces the link: written again on every run (cheap next
  // to SIFT), the extraction's fingerprint holds the window.
  auto cut = [&](const std::string& src, const std::string& at, ImageMode mode) -> Status {
    std::error_code e2;
    if (fs::is_symlink(at, e2)) fs::remove(at, e2);
    auto img = LoadImage(src, mode);
    if (!img)
      return MakeError(ErrorClass::kCorrupt, "cannot read " + src + ": " + img.error().message);
    if (img->size() != frame_) {
      return MakeError(ErrorClass::kInvalidArgument,
                       src + " is " + std::to_string(img->cols) + "x" + std::to_string(img->rows) +
                           ", the first image " + std::to_string(frame_.width) + "x" +
                           std::to_string(frame_.height) +
                           ": every image of a side must be one size");
    }
    std::vector<unsigned char> bytes;
    const bool png = mode == ImageMode::kGray;
    if (!cv::imencode(png ? ".png" : ".jpg", (*img)(crop_), bytes,
                      png ? std::vector<int>{} : std::vector<int>{cv::IMWRITE_JPEG_QUALITY, 97})) {
      return MakeError(ErrorClass::kIo, "cannot encode the window of " + src);
    }
    return WriteFileAtomic(at, bytes);
  };
  for (size_t i = 0; i < o_.images.size(); ++i) {
    const std::string name = fs::path(o_.images[i]).filename().string();
    names_.push_back(name);
    want_images.insert(name);
    if (!o_.masks.empty())
      want_masks.insert(name + ".png");  // COLMAP ignores other names, silently
    if (crop_.empty()) {
      if (auto st = link(o_.images[i], P("images/" + name)); !st) return st;
      if (!o_.masks.empty()) {
        if (auto st = link(o_.masks[i], P("masks/" + name + ".png")); !st) return st;
      }
    } else {
      if (auto st = cut(o_.images[i], P("images/" + name), ImageMode::kColor); !st) return st;
      if (auto st = cut(o_.masks[i], P("masks/" + name + ".png"), ImageMode::kGray); !st) return st;
    }
  }
  // COLMAP reads every file in images/: drop what an earlier run left.
  for (const auto& [dir, want] :
       {std::pair{P("images"), &want_images}, std::pair{P("masks"), &want_masks}}) {
    for (const auto& ent : fs::directory_iterator(dir, ec)) {
      if (!want->count(ent.path().filename().string())) fs::remove_all(ent.path(), ec);
    }
  }
  return FsyncDir(P("images"));
}

// The union of the masks' boxes, grown by 4 % of the frame's long side (at
// least 32 px) for the features' support, with even corners; empty when it
// would gain little or the camera's focal is unknown.
Status SfmRun::ChooseCrop() {
  auto first = LoadImage(o_.images[0], ImageMode::kUnchanged);
  if (!first)
    return MakeError(ErrorClass::kCorrupt,
                     "cannot read image " + o_.images[0] + ": " + first.error().message);
  frame_ = first->size();
  crop_ = cv::Rect();
  if (!o_.crop_to_masks || o_.masks.empty() || (!o_.fixed_camera && !o_.expected_focal_px))
    return OkStatus();
  cv::Rect box;
  for (const std::string& m : o_.masks) {
    auto mask = LoadImage(m, ImageMode::kGray);
    if (!mask)
      return MakeError(ErrorClass::kCorrupt, "cannot read mask " + m + ": " + mask.error().message);
    if (mask->size() != frame_) return OkStatus();  // the extraction names the mismatch
    const cv::Rect b = cv::boundingRect(*mask);
    if (b.area() > 0) box = box.area() > 0 ? (box | b) : b;
  }
  if (box.area() == 0) return OkStatus();
  const int margin = std::max(32, static_cast<int>(0.04 * std::max(frame_.width, frame_.height)));
  int x0 = std::max(0, box.x - margin) & ~1, y0 = std::max(0, box.y - margin) & ~1;
  int x1 = std::min(frame_.width, box.br().x + margin),
      y1 = std::min(frame_.height, box.br().y + margin);
  const cv::Rect w(x0, y0, x1 - x0, y1 - y0);
  if (2.0 * w.area() > static_cast<double>(frame_.area())) return OkStatus();
  crop_ = w;
  return OkStatus();
}

// A model found on the windows, in whole-frame pixels: the principal point
// and every observation move back by the window's corner (the poses and the
// points do not change).
void SfmRun::Uncrop(SfmModel* m) const {
  if (crop_.empty()) return;
  for (SfmCamera& c : m->cameras) {
    const bool one_focal = c.model == "SIMPLE_PINHOLE" || c.model == "SIMPLE_RADIAL" ||
                           c.model == "RADIAL" || c.model == "SIMPLE_RADIAL_FISHEYE" ||
                           c.model == "RADIAL_FISHEYE";
    const size_t k = one_focal ? 1 : 2;
    if (c.params.size() > k + 1) {
      c.params[k] += crop_.x;
      c.params[k + 1] += crop_.y;
    }
    c.width = frame_.width;
    c.height = frame_.height;
  }
  for (SfmImage& im : m->images) {
    for (Eigen::Vector2d& p : im.points2d) p += Eigen::Vector2d(crop_.x, crop_.y);
  }
}

// After PrepareWorkspace: frame_ is the first image's size.
Status SfmRun::ResolveCamera() {
  const int w = frame_.width, h = frame_.height;
  // On windows the principal point moves by the window's corner.
  const double dx = crop_.empty() ? 0.0 : crop_.x, dy = crop_.empty() ? 0.0 : crop_.y;
  if (o_.fixed_camera) {
    CameraModel cam = *o_.fixed_camera;
    if (cam.width != w || cam.height != h) {
      if (std::abs(static_cast<double>(cam.width) * h - static_cast<double>(cam.height) * w) >
          0.01 * w * h) {
        return MakeError(ErrorClass::kInvalidArgument,
                         "fixed intrinsics are for " + std::to_string(cam.width) + "x" +
                             std::to_string(cam.height) + " but the images are " +
                             std::to_string(w) + "x" + std::to_string(h) +
                             ": recalibrate at this resolution");
      }
      cam = cam.Resized(w, h);
    }
    fixed_colmap_ = ColmapCameraFromOpenCv(cam);
    camera_model_ = fixed_colmap_.model;
    fixed_params_ =
        crop_.empty()
            ? fixed_colmap_.params
            : ColmapCameraFromOpenCv(cam.Cropped(crop_.x, crop_.y, crop_.width, crop_.height))
                  .params;
    camera_params_ = JoinParams(fixed_params_);
    return OkStatus();
  }
  camera_model_ = o_.free_camera_model;
  if (o_.expected_focal_px) {  // a prior: COLMAP starts from it and refines it
    const double f = *o_.expected_focal_px, cx = w / 2.0 - dx, cy = h / 2.0 - dy;
    std::vector<double> p;
    if (camera_model_ == "SIMPLE_PINHOLE") p = {f, cx, cy};
    if (camera_model_ == "PINHOLE") p = {f, f, cx, cy};
    if (camera_model_ == "SIMPLE_RADIAL") p = {f, cx, cy, 0};
    if (camera_model_ == "RADIAL") p = {f, cx, cy, 0, 0};
    if (camera_model_ == "OPENCV") p = {f, f, cx, cy, 0, 0, 0, 0};
    camera_params_ = JoinParams(p);
  }
  return OkStatus();
}

Status SfmRun::Stage(const std::string& name, const nlohmann::json& fingerprint,
                     const std::function<Status()>& clean,
                     const std::function<Status(double*)>& run,
                     const std::function<Status()>& check) {
  const std::string marker = P("stages/" + name + ".json");
  if (!redo_ && PathExists(marker)) {
    auto text = ReadFile(marker);
    nlohmann::json j = text ? nlohmann::json::parse(*text, nullptr, false) : nlohmann::json();
    if (j.is_object() && j.value("fingerprint", nlohmann::json()) == fingerprint) {
      if (check().ok()) {
        AGG_LOGI(kLog, "%s: finished in an earlier run, reused", name.c_str());
        timings_.push_back({name, 0, true});
        return OkStatus();
      }
    }
  }
  redo_ = true;
  std::error_code ec;
  fs::remove(marker, ec);
  if (auto st = clean(); !st) return st;
  double wall = 0;
  if (auto st = run(&wall); !st) return st;
  if (auto st = check(); !st) return st;
  timings_.push_back({name, wall, false});
  nlohmann::json m{{"fingerprint", fingerprint}, {"wall_s", wall}};
  return WriteFileAtomic(marker, m.dump(1));
}

Status SfmRun::CheckExtraction() {
  const std::string log = P("logs/feature_extractor.log");
  if (!PathExists(P("database.db"))) {
    return MakeError(ErrorClass::kCorrupt, "COLMAP feature_extractor wrote no database; see " + log,
                     TailOfFile(log, 4));
  }
  auto db = ColmapDb::Open(P("database.db"));
  if (!db) return db.error();
  std::map<std::string, long> kp;
  auto st = db->Query(
      "SELECT images.name, COALESCE(keypoints.rows, 0) FROM images LEFT JOIN keypoints "
      "ON images.image_id = keypoints.image_id",
      [&](sqlite3_stmt* s) {
        kp[reinterpret_cast<const char*>(sqlite3_column_text(s, 0))] = sqlite3_column_int64(s, 1);
      });
  if (!st) return st;
  std::vector<std::string> missing;
  long with_features = 0;
  for (const auto& n : names_) {
    auto it = kp.find(n);
    if (it == kp.end())
      missing.push_back(n);
    else if (it->second > 0)
      ++with_features;
  }
  if (!missing.empty()) {
    return MakeError(ErrorClass::kCorrupt,
                     "COLMAP feature_extractor imported " +
                         std::to_string(names_.size() - missing.size()) + " of " +
                         std::to_string(names_.size()) + " images (first missing: " + missing[0] +
                         "): unreadable file or a different image size; see " + log,
                     TailOfFile(log, 4));
  }
  if (with_features < 2) {
    return MakeError(
        ErrorClass::kCorrupt,
        "COLMAP found features in only " + std::to_string(with_features) +
            " images: masks empty or images featureless; check the masks, use low-texture SIFT");
  }
  if (o_.fixed_camera) {  // the flags took effect: one camera with exactly our parameters
    int ncam = 0;
    bool same = true;
    st = db->Query("SELECT model, params FROM cameras", [&](sqlite3_stmt* s) {
      ++ncam;
      const int model = sqlite3_column_int(s, 0);
      const int bytes = sqlite3_column_bytes(s, 1);
      const auto* p = static_cast<const double*>(sqlite3_column_blob(s, 1));
      if (model != ModelId(fixed_colmap_.model) ||
          bytes != static_cast<int>(fixed_params_.size() * 8)) {
        same = false;
        return;
      }
      for (size_t k = 0; k < fixed_params_.size(); ++k) {
        if (std::abs(p[k] - fixed_params_[k]) > 1e-9 * std::max(1.0, std::abs(fixed_params_[k])))
          same = false;
      }
    });
    if (!st) return st;
    if (ncam != 1 || !same) {
      return MakeError(ErrorClass::kCorrupt, "COLMAP database holds " + std::to_string(ncam) +
                                                 " cameras, not the one fixed camera passed; see " +
                                                 log);
    }
  }
  return OkStatus();
}

Status SfmRun::CheckMatching() {
  auto db = ColmapDb::Open(P("database.db"));
  if (!db) return db.error();
  int verified = 0, tried = 0;
  auto st = db->Query("SELECT COUNT(*) FROM matches",
                      [&](sqlite3_stmt* s) { tried = sqlite3_column_int(s, 0); });
  if (!st) return st;
  st = db->Query("SELECT COUNT(*) FROM two_view_geometries WHERE rows >= " +
                     std::to_string(o_.matching.min_num_inliers),
                 [&](sqlite3_stmt* s) { verified = sqlite3_column_int(s, 0); });
  if (!st) return st;
  verified_pairs_ = verified;
  if (tried == 0) {
    return MakeError(ErrorClass::kCorrupt,
                     "COLMAP matcher wrote no matches; see " + P("logs/matcher.log"),
                     TailOfFile(P("logs/matcher.log"), 4));
  }
  if (verified == 0) {
    return MakeError(
        ErrorClass::kCorrupt,
        "no image pair has verified matches (" + std::to_string(tried) +
            " pairs tried): too little texture or overlap; use low-texture SIFT, more neighbours, "
            "smaller turntable steps, or known intrinsics");
  }
  return OkStatus();
}

// The registered views of the largest model under `dir` (COLMAP's binary
// images.bin starts with their count, a little-endian uint64); 0 when none.
int64_t LargestModelViews(const std::string& dir) {
  int64_t best = 0;
  std::error_code ec;
  for (const auto& ent : fs::directory_iterator(dir, ec)) {
    std::ifstream f(ent.path() / "images.bin", std::ios::binary);
    uint64_t count = 0;
    if (f.read(reinterpret_cast<char*>(&count), sizeof count) && count < (1u << 20))
      best = std::max(best, static_cast<int64_t>(count));
  }
  return best;
}

std::vector<std::string> SfmRun::ModelDirs() const {
  std::vector<std::pair<int, std::string>> dirs;
  std::error_code ec;
  for (const auto& ent : fs::directory_iterator(P("sparse"), ec)) {
    const std::string n = ent.path().filename().string();
    if (n.empty() || !std::all_of(n.begin(), n.end(), ::isdigit)) continue;
    bool complete = true;
    for (const char* f : {"cameras.bin", "images.bin", "points3D.bin"}) {
      if (!PathExists(ent.path().string() + "/" + f)) complete = false;
    }
    if (complete) dirs.emplace_back(std::stoi(n), n);
  }
  std::sort(dirs.begin(), dirs.end());
  std::vector<std::string> out;
  out.reserve(dirs.size());
  for (auto& d : dirs) out.push_back(d.second);
  return out;
}

Status SfmRun::CheckMapper() {
  if (ModelDirs().empty()) {
    return MakeError(
        ErrorClass::kCorrupt,
        "COLMAP mapper reconstructed no model from " + std::to_string(verified_pairs_) +
            " matched pairs: no initial pair with enough inliers and triangulation angle; use "
            "low-texture SIFT, fix the intrinsics from the rig calibration, or match more "
            "neighbours; "
            "see " +
            P("logs/mapper.log"),
        TailOfFile(P("logs/mapper.log"), 4));
  }
  return OkStatus();
}

Status SfmRun::CheckConverted() {
  for (const auto& k : ModelDirs()) {
    for (const char* f : {"cameras.txt", "images.txt", "points3D.txt"}) {
      if (!PathExists(P("model_txt/" + k + "/" + f))) {
        return MakeError(ErrorClass::kCorrupt, "COLMAP model_converter wrote no " + std::string(f) +
                                                   " for model " + k + "; see " +
                                                   P("logs/model_converter.log"));
      }
    }
  }
  return OkStatus();
}

Result<SfmResult> SfmRun::Run() {
  if (auto problems = o_.Check(); !problems.empty()) {
    std::string all;
    for (const auto& p : problems) all += (all.empty() ? "" : "; ") + p;
    return MakeError(ErrorClass::kInvalidArgument, "invalid SfM options: " + all);
  }
  if (::access(o_.colmap_binary.c_str(), X_OK) != 0 &&
      o_.colmap_binary.find('/') != std::string::npos) {
    return MakeError(ErrorClass::kNotFound,
                     "COLMAP not found at " + o_.colmap_binary +
                         ": install Debian's colmap package (scripts/install-deps.sh) or set the "
                         "colmap binary path",
                     std::strerror(errno));
  }
  if (auto st = PrepareWorkspace(); !st) return st.error();
  if (auto st = ResolveCamera(); !st) return st.error();
  const int n = static_cast<int>(o_.images.size());
  const int t = o_.num_threads;

  // --- feature extraction
  nlohmann::json inputs = nlohmann::json::array();
  for (int i = 0; i < n; ++i) {
    const auto s = Stamp(o_.images[i]);
    nlohmann::json j{{"name", names_[i]}, {"size", s.size}, {"mtime_ns", s.mtime_ns}};
    if (!o_.masks.empty()) {
      const auto m = Stamp(o_.masks[i]);
      j["mask_size"] = m.size;
      j["mask_mtime_ns"] = m.mtime_ns;
    }
    inputs.push_back(std::move(j));
  }
  const auto& s = o_.sift;
  nlohmann::json fp_extract{{"images", inputs},
                            {"camera_model", camera_model_},
                            {"camera_params", camera_params_},
                            {"crop", {crop_.x, crop_.y, crop_.width, crop_.height}},
                            {"max_image_size", s.max_image_size},
                            {"max_num_features", s.max_num_features},
                            {"peak_threshold", s.peak_threshold},
                            {"edge_threshold", s.edge_threshold},
                            {"affine", s.estimate_affine_shape},
                            {"dsp", s.domain_size_pooling}};
  auto st = Stage(
      "feature_extractor", fp_extract,
      [&]() -> Status {
        std::error_code ec;
        for (const char* f :
             {"database.db", "database.db-journal", "database.db-wal", "database.db-shm"}) {
          fs::remove(P(f), ec);
        }
        return OkStatus();
      },
      [&](double* wall) {
        std::vector<std::string> a = {"--database_path",
                                      P("database.db"),
                                      "--image_path",
                                      P("images"),
                                      "--ImageReader.single_camera",
                                      "1",
                                      "--ImageReader.camera_model",
                                      camera_model_,
                                      "--SiftExtraction.use_gpu",
                                      "0",  // no OpenGL context on the rig
                                      "--SiftExtraction.num_threads",
                                      std::to_string(t),
                                      "--SiftExtraction.max_image_size",
                                      std::to_string(s.max_image_size),
                                      "--SiftExtraction.max_num_features",
                                      std::to_string(s.max_num_features),
                                      "--SiftExtraction.peak_threshold",
                                      Fmt("%.9g", s.peak_threshold),
                                      "--SiftExtraction.edge_threshold",
                                      Fmt("%.9g", s.edge_threshold),
                                      "--SiftExtraction.estimate_affine_shape",
                                      s.estimate_affine_shape ? "1" : "0",
                                      "--SiftExtraction.domain_size_pooling",
                                      s.domain_size_pooling ? "1" : "0"};
        if (!camera_params_.empty())
          a.insert(a.end(), {"--ImageReader.camera_params", camera_params_});
        if (!o_.masks.empty()) a.insert(a.end(), {"--ImageReader.mask_path", P("masks")});
        return Colmap("feature_extractor", "feature_extractor", a, wall);
      },
      [&] { return CheckExtraction(); });
  if (!st) return st.error();

  // --- matching
  const auto& mo = o_.matching;
  // A turntable capture's pairs follow its angles (views of one angle on
  // different turns matched too); without angles, capture order.
  std::vector<std::pair<int, int>> pair_list;
  if (mo.mode == SfmMatching::kCircular) {
    pair_list = AnglePairs(o_.angles_deg, mo.circular_neighbours);
    if (pair_list.empty()) pair_list = CircularPairs(n, mo.circular_neighbours);
  }
  nlohmann::json fp_match{{"extract", fp_extract},
                          {"mode", mo.mode == SfmMatching::kCircular ? "circular" : "exhaustive"},
                          {"pairs", pair_list.size()},
                          {"k", mo.circular_neighbours},
                          {"max_ratio", mo.max_ratio},
                          {"max_distance", mo.max_distance},
                          {"guided", mo.guided_matching},
                          {"min_num_inliers", mo.min_num_inliers}};
  st = Stage(
      "matcher", fp_match,
      [&]() -> Status {  // matchers skip pairs already in the database
        auto db = ColmapDb::Open(P("database.db"), true);
        if (!db) return db.error();
        return db->Exec("DELETE FROM matches; DELETE FROM two_view_geometries;");
      },
      [&](double* wall) -> Status {
        std::vector<std::string> a = {"--database_path",
                                      P("database.db"),
                                      "--SiftMatching.use_gpu",
                                      "0",
                                      "--SiftMatching.num_threads",
                                      std::to_string(t),
                                      "--SiftMatching.max_ratio",
                                      Fmt("%.9g", mo.max_ratio),
                                      "--SiftMatching.max_distance",
                                      Fmt("%.9g", mo.max_distance),
                                      "--SiftMatching.guided_matching",
                                      mo.guided_matching ? "1" : "0",
                                      "--SiftMatching.min_num_inliers",
                                      std::to_string(mo.min_num_inliers)};
        if (mo.mode == SfmMatching::kExhaustive)
          return Colmap("exhaustive_matcher", "matcher", a, wall);
        std::string pairs;
        for (const auto& [i, j] : pair_list) pairs += names_[i] + " " + names_[j] + "\n";
        if (auto w = WriteFileAtomic(P("pairs.txt"), pairs); !w) return w;
        a.insert(a.end(), {"--match_list_path", P("pairs.txt"), "--match_type", "pairs"});
        return Colmap("matches_importer", "matcher", a, wall);
      },
      [&] { return CheckMatching(); });
  if (!st) return st.error();

  // --- mapping
  const bool fixed = o_.fixed_camera.has_value();
  // A focal hint is held, when asked, while the ring grows: with the rock alone in the
  // masks the focal length and distortion are barely observable, and
  // refining them from the first pair on sent the focal astray (sim seed 1,
  // 12 views: the third view never registered; with the hint held, all 12
  // at 0.27 px). COLMAP's final refinement of them drifted 1.3 % off the true
  // focal, so the hint stays as given.
  const bool hold = fixed || (o_.hold_focal_hint && o_.expected_focal_px.has_value());
  const auto& mp = o_.mapper;
  nlohmann::json fp_map{{"match", fp_match},
                        {"fixed", fixed},
                        {"hold_focal_hint", hold},
                        {"min_num_matches", mp.min_num_matches},
                        {"init_min_tri_angle", mp.init_min_tri_angle_deg},
                        {"init_min_num_inliers", mp.init_min_num_inliers},
                        {"abs_pose_min_num_inliers", mp.abs_pose_min_num_inliers},
                        {"multiple_models", mp.multiple_models},
                        {"min_model_size", mp.min_model_size},
                        {"retry_abs_pose_min_num_inliers", mp.retry_abs_pose_min_num_inliers}};
  st = Stage(
      "mapper", fp_map,
      [&]() -> Status {
        std::error_code ec;
        fs::remove_all(P("sparse"), ec);
        return MakeDirsDurable(P("sparse"));
      },
      [&](double* wall) -> Status {
        auto args = [&](const std::string& out, int abs_pose_min_num_inliers) {
          return std::vector<std::string>{
              "--database_path", P("database.db"), "--image_path", P("images"), "--output_path",
              out, "--Mapper.num_threads", std::to_string(t), "--Mapper.min_num_matches",
              std::to_string(mp.min_num_matches), "--Mapper.init_min_tri_angle",
              Fmt("%.9g", mp.init_min_tri_angle_deg), "--Mapper.init_min_num_inliers",
              std::to_string(mp.init_min_num_inliers), "--Mapper.abs_pose_min_num_inliers",
              std::to_string(abs_pose_min_num_inliers), "--Mapper.multiple_models",
              mp.multiple_models ? "1" : "0", "--Mapper.min_model_size",
              std::to_string(mp.min_model_size),
              // Known intrinsics and a focal hint stay fixed; otherwise COLMAP refines focal
              // and distortion (its default).
              "--Mapper.ba_refine_focal_length", hold ? "0" : "1",
              "--Mapper.ba_refine_principal_point", "0", "--Mapper.ba_refine_extra_params",
              hold ? "0" : "1"};
        };
        // COLMAP's mapper exits 1 when it finds no initial pair: report that as
        // "no model" with what to do, not as a crash.
        auto failed_empty = [&](Status st) -> Status {
          if (st.ok() || st.error().cls != ErrorClass::kIo || !ModelDirs().empty()) return st;
          Error e = CheckMapper().error();
          e.detail = st.error().detail;
          return e;
        };
        Status first = failed_empty(
            Colmap("mapper", "mapper", args(P("sparse"), mp.abs_pose_min_num_inliers), wall));
        if (!first) return first;
        // A ring that stalled part-way round from both ends: the view past its
        // weak link sees a few of the model's points, fewer than asked. Once
        // more with a lower bar, the larger model kept; the checks judge it.
        const int64_t got = LargestModelViews(P("sparse"));
        if (mp.retry_abs_pose_min_num_inliers <= 0 ||
            mp.retry_abs_pose_min_num_inliers >= mp.abs_pose_min_num_inliers ||
            got >= static_cast<int64_t>(o_.images.size())) {
          return first;
        }
        std::error_code ec;
        fs::remove_all(P("sparse_retry"), ec);
        if (Status d = MakeDirsDurable(P("sparse_retry")); !d) return d;
        double w2 = 0;
        Status again = Colmap("mapper", "mapper_retry",
                              args(P("sparse_retry"), mp.retry_abs_pose_min_num_inliers), &w2);
        *wall += w2;
        const int64_t other = again.ok() ? LargestModelViews(P("sparse_retry")) : 0;
        AGG_LOGI(
            kLog,
            "mapper: largest model %lld of %zu views; again with abs_pose_min_num_inliers %d: %lld",
            static_cast<long long>(got), o_.images.size(), mp.retry_abs_pose_min_num_inliers,
            static_cast<long long>(other));
        if (other > got) {
          fs::remove_all(P("sparse"), ec);
          fs::rename(P("sparse_retry"), P("sparse"), ec);
          if (ec)
            return MakeError(ErrorClass::kIo, "cannot keep the mapper's second model",
                             ec.message());
        } else {
          fs::remove_all(P("sparse_retry"), ec);
        }
        return OkStatus();
      },
      [&] { return CheckMapper(); });
  if (!st) return st.error();
  if (verified_pairs_ == 0) (void)CheckMatching();  // stage reused: still report the pair count

  // --- text export of every sub-model
  st = Stage(
      "model_converter", fp_map,
      [&]() -> Status {
        std::error_code ec;
        fs::remove_all(P("model_txt"), ec);
        return OkStatus();
      },
      [&](double* wall) -> Status {
        *wall = 0;
        for (const auto& k : ModelDirs()) {
          if (auto m = MakeDirsDurable(P("model_txt/" + k)); !m) return m;
          double w = 0;
          if (auto r = Colmap("model_converter", "model_converter",
                              {"--input_path", P("sparse/" + k), "--output_path",
                               P("model_txt/" + k), "--output_type", "TXT"},
                              &w);
              !r) {
            return r;
          }
          *wall += w;
        }
        return OkStatus();
      },
      [&] { return CheckConverted(); });
  if (!st) return st.error();

  // --- parse, choose the largest sub-model, check it
  const auto tp = std::chrono::steady_clock::now();
  SfmResult res;
  res.num_input_images = n;
  res.num_verified_pairs = verified_pairs_;
  std::map<std::string, int> index;
  for (int i = 0; i < n; ++i) index[names_[i]] = i;
  std::vector<std::pair<std::string, SfmModel>> models;
  for (const auto& k : ModelDirs()) {
    auto m = ReadColmapTextModel(P("model_txt/" + k));
    if (!m) return m.error();
    models.emplace_back(k, std::move(*m));
  }
  size_t best = 0;
  for (size_t i = 1; i < models.size(); ++i) {
    const auto& a = models[i].second;
    const auto& b = models[best].second;
    if (a.images.size() > b.images.size() ||
        (a.images.size() == b.images.size() && a.points.size() > b.points.size())) {
      best = i;
    }
  }
  for (size_t i = 0; i < models.size(); ++i) {
    if (i != best)
      res.other_models_registered.push_back(static_cast<int>(models[i].second.images.size()));
  }
  res.model = std::move(models[best].second);
  Uncrop(&res.model);
  if (!crop_.empty()) res.window = {crop_.x, crop_.y, crop_.width, crop_.height};
  res.model_index = std::stoi(models[best].first);
  res.model_dir = P("model_txt/" + models[best].first);
  for (auto& im : res.model.images) {
    auto it = index.find(im.name);
    im.input_index = it == index.end() ? -1 : it->second;
  }
  res.num_registered = static_cast<int>(res.model.images.size());
  for (int i = 0; i < n; ++i) {
    if (!res.model.FindImageByName(names_[i])) res.unregistered.push_back(names_[i]);
  }
  res.mean_reprojection_px = MeanReprojectionErrorPx(res.model);
  SfmExpectations ex;
  ex.num_input_images = n;
  if (o_.fixed_camera) {
    auto cam = OpenCvCameraFromColmap(fixed_colmap_);
    if (cam) ex.fixed_camera = *cam;
  }
  ex.expected_focal_px = o_.expected_focal_px;
  ex.ring = o_.expect_ring;
  ex.angles_deg = o_.angles_deg;
  res.checks = CheckSfmModel(res.model, ex, o_.checks);
  timings_.push_back({"parse_check",
                      std::chrono::duration<double>(std::chrono::steady_clock::now() - tp).count(),
                      false});
  res.timings = timings_;

  nlohmann::json summary{{"accepted", res.checks.ok()},
                         {"num_input_images", n},
                         {"num_registered", res.num_registered},
                         {"num_points", res.model.points.size()},
                         {"mean_reprojection_px", res.mean_reprojection_px},
                         {"model_dir", res.model_dir},
                         {"other_models_registered", res.other_models_registered},
                         {"unregistered", res.unregistered},
                         {"num_verified_pairs", res.num_verified_pairs},
                         {"checks", res.checks.ToJson()}};
  nlohmann::json tj = nlohmann::json::array();
  for (const auto& tm : res.timings)
    tj.push_back({{"step", tm.step}, {"wall_s", tm.wall_s}, {"skipped", tm.skipped}});
  summary["timings"] = tj;
  if (!res.model.cameras.empty()) {
    const auto& c = res.model.cameras[0];
    summary["camera"] = {
        {"model", c.model}, {"width", c.width}, {"height", c.height}, {"params", c.params}};
  }
  if (auto w = WriteFileAtomic(P("result.json"), summary.dump(1)); !w) return w.error();
  AGG_LOGI(kLog, "model %d: %d/%d views, %zu points, reprojection %.3f px, %zu other sub-models",
           res.model_index, res.num_registered, n, res.model.points.size(),
           res.mean_reprojection_px, res.other_models_registered.size());
  if (!res.checks.ok()) return res.checks.ToError();
  return res;
}

}  // namespace

Result<SfmResult> RunColmapSfm(const ColmapSfmOptions& opts) { return SfmRun(opts).Run(); }

}  // namespace aggscan
