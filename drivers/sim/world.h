// The simulated world shared by the sim camera and the sim turntable: the rock
// (procedural from a seed, or a mesh file), its painted object markers, its
// stable rest poses per side, the turntable with its four colour labels (and
// the ArUco scale markers when configured), the white table, the light and the camera. Everything
// the renderer draws and everything a test needs as ground truth lives here; nothing here changes
// after construction, so one world is shared read-only between threads.
//
// Frames (all right-handed, millimetres):
//   rock       the mesh's own coordinates (procedural: origin at the centre of
//              mass, x/y/z along the longest/middle/shortest extent).
//   turntable  origin at the disc centre on its top surface, z up; rotates
//              with the platter. The rock's rest pose per side maps rock ->
//              turntable.
//   world      the turntable frame at platter angle 0 (fixed to the room);
//              world = Rz(platter_deg) * turntable.
//   camera     OpenCV convention: x right, y down, z forward (optical axis).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/mesh.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "drivers/sim/board.h"

namespace aggscan::sim {

struct Vec3 {
  double x = 0.0, y = 0.0, z = 0.0;
};
inline Vec3 operator+(const Vec3& a, const Vec3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(const Vec3& a, const Vec3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator-(const Vec3& a) { return {-a.x, -a.y, -a.z}; }
inline Vec3 operator*(const Vec3& a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline Vec3 operator*(double s, const Vec3& a) { return a * s; }
inline double Dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 Cross(const Vec3& a, const Vec3& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double Norm(const Vec3& a) { return std::sqrt(Dot(a, a)); }
inline Vec3 Normalized(const Vec3& a) {
  const double n = Norm(a);
  return n > 0 ? a * (1.0 / n) : Vec3{0, 0, 0};
}
inline Vec3 ToVec3(const std::array<double, 3>& a) { return {a[0], a[1], a[2]}; }

/// Rigid transform p' = R p + t (R row-major).
struct Rigid {
  std::array<double, 9> R{1, 0, 0, 0, 1, 0, 0, 0, 1};
  Vec3 t;

  Vec3 Rotate(const Vec3& p) const {
    return {R[0] * p.x + R[1] * p.y + R[2] * p.z, R[3] * p.x + R[4] * p.y + R[5] * p.z,
            R[6] * p.x + R[7] * p.y + R[8] * p.z};
  }
  Vec3 Apply(const Vec3& p) const { return Rotate(p) + t; }
  Rigid Inverse() const;
  /// Composition: (a * b).Apply(p) == a.Apply(b.Apply(p)).
  friend Rigid operator*(const Rigid& a, const Rigid& b);
  /// Row-major homogeneous 4x4 matrix.
  std::array<double, 16> Matrix4() const;
  /// Rotation about +z by `deg` (counter-clockwise seen from above).
  static Rigid RotZ(double deg);
};

/// Pinhole camera with Brown radial distortion on normalized coordinates:
/// x_d = x_u * (1 + k1 r^2 + k2 r^4), r^2 = x_u^2 + y_u^2; pixel = f * x_d + c.
/// Pixel centres are at integer coordinates (OpenCV convention).
struct Intrinsics {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  double k1 = 0, k2 = 0;

  /// Projects a camera-frame point; false when it is behind the camera.
  bool Project(const Vec3& p_cam, double* u, double* v) const;
};

/// A head-tail object marker painted on the rock (the study's purple and red
/// markers used to stitch the two sides): along `axis` from the start, a short
/// head segment, a gap, then a long tail segment, `width` wide.
struct ObjectMarker {
  std::string color;     // "purple" | "red"
  Vec3 head;             // centre of the head segment, on the surface (rock frame, mm)
  Vec3 tail;             // centre of the tail segment, on the surface (rock frame, mm)
  Vec3 origin;           // surface point at the middle of the pattern
  Vec3 axis;             // unit, head -> tail direction (tangent to the surface)
  Vec3 normal;           // unit, outward surface normal at origin
  double head_mm = 8.0;  // segment lengths along axis
  double gap_mm = 4.0;
  double tail_mm = 25.0;
  double width_mm = 4.0;
  std::array<float, 3> albedo{};  // linear RGB paint colour
};

/// One stable rest of the rock on the turntable (a convex-hull face whose
/// triangle contains the projection of the centre of mass).
struct RestPose {
  Rigid rock_to_turntable;
  Vec3 down_rock;                // unit outward normal of the resting hull face, rock frame
  double com_height_mm = 0;      // height of the centre of mass above the disc
  double support_margin_mm = 0;  // distance from the COM projection to the support edge
};

/// Options not in the config file.
struct SimWorldOptions {
  int rock_faces = 20000;  // procedural rock face count (about; up to ~100k)
};

/// Ambient + directional key light, linear units (1.0 = white at albedo 1).
struct Lighting {
  Vec3 to_light;          // unit direction towards the key light, world frame
  double key = 0.72;      // directional intensity
  double ambient = 0.30;  // uniform ambient intensity
};

// Rig geometry that the config does not carry.
inline constexpr double kDiscThicknessMm = 15.0;  // the table top is this far below the disc top
inline constexpr double kAimHeightMm = 40.0;      // camera aims this far above the disc centre

/// Procedural angular riprap: hull of random points on a stretched ellipsoid,
/// cut by planar chips, with smooth dents and fine roughness; sampled as a
/// geodesic sphere pushed radially onto that surface, so it is a closed,
/// outward-oriented manifold of about `target_faces` faces. Centred on its
/// centre of mass, longest extent along x equal to `size_mm` (0: random
/// 70..200 mm), axis-aligned extents ratio max/min in [1.25, 2.9].
Mesh MakeProceduralRock(uint64_t seed, double size_mm, int target_faces);

/// Linear RGB of a label colour name (red/green/blue/yellow/purple); false if unknown.
bool ColorAlbedo(const std::string& name, std::array<float, 3>* rgb);

class SimWorld {
 public:
  /// Builds the world; throws std::runtime_error when the rock mesh cannot be
  /// loaded or has no stable rest (start-up only; prefer Create()).
  explicit SimWorld(const Config& config, const SimWorldOptions& options = {});
  static Result<std::shared_ptr<SimWorld>> Create(const Config& config,
                                                  const SimWorldOptions& options = {});

  const Config& config() const { return config_; }

  // --- rock ---
  /// Rock mesh in the rock frame (mm).
  const Mesh& rock() const { return rock_; }
  /// Outward unit normal per face, rock frame.
  const std::vector<Vec3>& face_normals() const { return face_normals_; }
  Vec3 center_of_mass() const { return com_; }
  double volume_mm3() const { return volume_mm3_; }
  /// Object markers (purple first, then red), rock frame.
  const std::vector<ObjectMarker>& object_markers() const { return markers_; }
  /// Linear RGB albedo of the rock surface at p (rock frame) on a face with
  /// outward normal n: the procedural stone texture, or marker paint.
  std::array<float, 3> RockAlbedo(const Vec3& p, const Vec3& n) const;

  // --- poses ---
  /// Number of distinct stable rests found (>= 1).
  int num_poses() const { return static_cast<int>(poses_.size()); }
  /// Rest pose for a 1-based side; sides beyond num_poses() wrap around.
  const RestPose& pose(int side) const;

  // --- rig, light, camera ---
  const Lighting& lighting() const { return lighting_; }
  /// Intrinsics for the configured resolution (camera.width/height).
  Intrinsics intrinsics() const {
    return IntrinsicsFor(config_.camera.width, config_.camera.height);
  }
  /// Intrinsics for another resolution (same field of view and distortion).
  Intrinsics IntrinsicsFor(int width, int height) const;
  /// World -> camera (camera fixed in the room).
  const Rigid& world_to_camera() const { return world_to_camera_; }
  /// Turntable -> world for a platter angle.
  static Rigid TurntableToWorld(double platter_deg) { return Rigid::RotZ(platter_deg); }
  /// The rig calibration this world was built with (exact intrinsics and
  /// camera pose), for tests that need perfect knowledge; method "sim-truth".
  RigCalibration TruthCalibration(int width, int height) const;
  /// Rock -> world / camera for a 1-based side and platter angle.
  Rigid RockToWorld(int side, double platter_deg) const;
  Rigid RockToCamera(int side, double platter_deg) const;
  /// Pixel of a turntable-frame point (e.g. a label centre) at a platter angle,
  /// distortion applied; false when behind the camera.
  bool ProjectTurntablePoint(const Vec3& p_tt, double platter_deg, const Intrinsics& intr,
                             double* u, double* v) const;
  /// The calibration board lying on the disc in the "charuco" scene (no rock
  /// is drawn then); null in the "rock" scene.
  const SimBoard* board() const { return board_.empty() ? nullptr : &board_.front(); }
  /// The ArUco scale markers of rig.aruco_markers lying on the disc (any
  /// scene); empty when none are configured.
  const std::vector<SimArucoMarker>& aruco_markers() const { return aruco_; }

  /// Reference exposure (exposure_us * gain of the configured default): a
  /// frame taken with this product has nominal brightness.
  double reference_exposure() const { return reference_exposure_; }

 private:
  void BuildRock();
  void ComputePoses();
  void PlaceMarkers();

  Config config_;
  SimWorldOptions options_;
  Mesh rock_;
  std::vector<Vec3> face_normals_;
  Vec3 com_;
  double volume_mm3_ = 0;
  double longest_mm_ = 0;
  std::vector<RestPose> poses_;
  std::vector<ObjectMarker> markers_;
  Lighting lighting_;
  Rigid world_to_camera_;
  double reference_exposure_ = 8000.0;
  uint32_t texture_seed_ = 0;
  std::array<float, 3> tint_{1, 1, 1};
  std::vector<SimBoard> board_;  // one in the "charuco" scene
  std::vector<SimArucoMarker> aruco_;
};

}  // namespace aggscan::sim
