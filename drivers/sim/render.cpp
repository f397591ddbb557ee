#include "drivers/sim/render.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace aggscan::sim {

namespace {

constexpr float kNoKey = -std::numeric_limits<float>::infinity();
constexpr int kSubPixelBits = 4;  // rasterizer fixed point: 1/16 pixel
constexpr int kSub = 1 << kSubPixelBits;
constexpr double kShadowTexelMm = 0.5;
constexpr int kBlurRadius = 7;  // texels; three box passes ~ Gaussian sigma 7 texels (3.5 mm)
constexpr int kBlurPasses = 3;
constexpr float kShadowBiasMm = 0.3f;
constexpr int kLutSize = 2048;

inline int64_t FloorDiv(int64_t a, int64_t b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

struct RasterTarget {
  int w = 0, h = 0;
  float* key = nullptr;   // largest key wins
  int32_t* id = nullptr;  // optional triangle id
};

// Draws the triangles whose signed area (x right, y down) is negative: the
// camera's front faces, or the light's back faces (see the callers). Integer
// edge functions at pixel centres, so neighbouring triangles leave no gaps.
void Rasterize(const std::vector<std::array<int, 3>>& faces, const int32_t* xs, const int32_t* ys,
               const float* keys, const uint8_t* valid, const RasterTarget& t) {
  const int nf = static_cast<int>(faces.size());
  for (int f = 0; f < nf; ++f) {
    int i0 = faces[f][0], i1 = faces[f][1], i2 = faces[f][2];
    if (!(valid[i0] & valid[i1] & valid[i2])) continue;
    int64_t x0 = xs[i0], y0 = ys[i0], x1 = xs[i1], y1 = ys[i1], x2 = xs[i2], y2 = ys[i2];
    int64_t area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0);
    if (area >= 0) continue;
    std::swap(i1, i2);
    std::swap(x1, x2);
    std::swap(y1, y2);
    area = -area;
    const int64_t minx = std::max<int64_t>(0, FloorDiv(std::min({x0, x1, x2}) + kSub - 1, kSub));
    const int64_t maxx = std::min<int64_t>(t.w - 1, FloorDiv(std::max({x0, x1, x2}), kSub));
    const int64_t miny = std::max<int64_t>(0, FloorDiv(std::min({y0, y1, y2}) + kSub - 1, kSub));
    const int64_t maxy = std::min<int64_t>(t.h - 1, FloorDiv(std::max({y0, y1, y2}), kSub));
    if (minx > maxx || miny > maxy) continue;
    // E_ab(P) = (xb - xa)(Py - ya) - (yb - ya)(Px - xa): >= 0 inside for all three edges.
    const int64_t ax0 = -(y2 - y1) * kSub, ay0 = (x2 - x1) * kSub;
    const int64_t ax1 = -(y0 - y2) * kSub, ay1 = (x0 - x2) * kSub;
    const int64_t ax2 = -(y1 - y0) * kSub, ay2 = (x1 - x0) * kSub;
    const int64_t px = minx * kSub, py = miny * kSub;
    int64_t w0r = (x2 - x1) * (py - y1) - (y2 - y1) * (px - x1);
    int64_t w1r = (x0 - x2) * (py - y2) - (y0 - y2) * (px - x2);
    int64_t w2r = (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0);
    const double k0 = keys[i0], k1 = keys[i1], k2 = keys[i2];
    const double inv_area = 1.0 / static_cast<double>(area);
    const float kdx = static_cast<float>((ax0 * k0 + ax1 * k1 + ax2 * k2) * inv_area);
    const double kdy = (ay0 * k0 + ay1 * k1 + ay2 * k2) * inv_area;
    double krow = (w0r * k0 + w1r * k1 + w2r * k2) * inv_area;
    for (int64_t y = miny; y <= maxy; ++y) {
      int64_t w0 = w0r, w1 = w1r, w2 = w2r;
      float k = static_cast<float>(krow);
      float* key_row = t.key + y * t.w;
      int32_t* id_row = t.id ? t.id + y * t.w : nullptr;
      for (int64_t x = minx; x <= maxx; ++x) {
        if ((w0 | w1 | w2) >= 0 && k > key_row[x]) {
          key_row[x] = k;
          if (id_row) id_row[x] = f;
        }
        w0 += ax0, w1 += ax1, w2 += ax2;
        k += kdx;
      }
      w0r += ay0, w1r += ay1, w2r += ay2;
      krow += kdy;
    }
  }
}

// In-place box blur along rows (stride 1) or columns, zero outside.
void BoxBlur(float* data, int w, int h, int r, bool rows, std::vector<float>* tmp) {
  const int n = rows ? w : h, lines = rows ? h : w;
  const ptrdiff_t step = rows ? 1 : w, line_step = rows ? w : 1;
  tmp->resize(n);
  const float norm = 1.0f / static_cast<float>(2 * r + 1);
  for (int l = 0; l < lines; ++l) {
    float* p = data + l * line_step;
    for (int i = 0; i < n; ++i) (*tmp)[i] = p[i * step];
    float sum = 0;
    for (int i = 0; i <= std::min(r, n - 1); ++i) sum += (*tmp)[i];
    for (int i = 0; i < n; ++i) {
      p[i * step] = sum * norm;
      if (i + r + 1 < n) sum += (*tmp)[i + r + 1];
      if (i - r >= 0) sum -= (*tmp)[i - r];
    }
  }
}

// Inverse standard normal CDF by bisection (only for building a table).
double InverseNormal(double p) {
  double lo = -10, hi = 10;
  for (int i = 0; i < 100; ++i) {
    const double mid = 0.5 * (lo + hi);
    const double c = 0.5 * std::erfc(-mid / std::sqrt(2.0));
    (c < p ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

struct Label {
  float x0, x1, y0, y1;
  std::array<float, 3> albedo;
};

// An ArUco scale marker on its paper: albedo texture of the whole paper
// square (marker and white margin), prefiltered, and its pose on the platter.
struct ArucoPaper {
  std::vector<float> tex;
  int tw = 0;                         // texture side, texels
  double x = 0, y = 0, c = 1, s = 0;  // centre (turntable frame, mm), cos/sin of the yaw
  double half = 0;                    // half side of the paper, mm
  double tex_per_mm = 0;
};

// Bilinear sample of a W x H texture at texel coordinates (tu, tv), clamped.
float Bilinear(const std::vector<float>& tex, int W, int H, double tu, double tv) {
  const double cu = std::clamp(tu, 0.0, W - 1.001), cv = std::clamp(tv, 0.0, H - 1.001);
  const int i = static_cast<int>(cu), j = static_cast<int>(cv);
  const float fu = static_cast<float>(cu - i), fv = static_cast<float>(cv - j);
  const int i1 = std::min(i + 1, W - 1), j1 = std::min(j + 1, H - 1);
  const float* r0 = &tex[static_cast<size_t>(j) * W];
  const float* r1 = &tex[static_cast<size_t>(j1) * W];
  return (r0[i] * (1 - fu) + r0[i1] * fu) * (1 - fv) + (r1[i] * (1 - fu) + r1[i1] * fu) * fv;
}

// Separable Gaussian blur of a W x H texture (sigma in texels), clamped at the
// edges: the lens and sensor blur of a sharp print, so that point-sampling it
// once per pixel does not alias.
void BlurTexture(std::vector<float>* tex, int W, int H, double sigma) {
  if (sigma < 0.3) return;
  const int r = static_cast<int>(std::ceil(3 * sigma));
  std::vector<float> w(2 * r + 1);
  float sum = 0;
  for (int k = -r; k <= r; ++k)
    sum += w[k + r] = std::exp(-0.5f * k * k / static_cast<float>(sigma * sigma));
  for (float& x : w) x /= sum;
  std::vector<float> tmp(tex->size());
  for (int y = 0; y < H; ++y) {
    const float* src = &(*tex)[static_cast<size_t>(y) * W];
    float* dst = &tmp[static_cast<size_t>(y) * W];
    for (int x = 0; x < W; ++x) {
      float acc = 0;
      for (int k = -r; k <= r; ++k) acc += w[k + r] * src[std::clamp(x + k, 0, W - 1)];
      dst[x] = acc;
    }
  }
  for (int y = 0; y < H; ++y) {
    float* dst = &(*tex)[static_cast<size_t>(y) * W];
    for (int x = 0; x < W; ++x) {
      float acc = 0;
      for (int k = -r; k <= r; ++k)
        acc += w[k + r] * tmp[static_cast<size_t>(std::clamp(y + k, 0, H - 1)) * W + x];
      dst[x] = acc;
    }
  }
}

// What one frame's per-pixel shading needs.
struct FrameState {
  bool dynamic = true;           // false: static background only (no rock, rock shadow, labels)
  float M[9] = {};               // camera -> rock rotation
  float ox = 0, oy = 0, oz = 0;  // camera centre in the rock frame
  Vec3 Lr, up_r;                 // light direction and world up in the rock frame
  Vec3 au, av, ak;               // rock frame -> light-map coordinates (linear part)
  double bu = 0, bv = 0, bk = 0;
  Rigid to_platter;  // world -> turntable frame
};

// Bounding box of output pixels.
struct Box {
  double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300;
  // Adds the pixel of undistorted normalized coordinates (x, y).
  void Extend(const Intrinsics& k, double x, double y) {
    const double r2 = x * x + y * y, s = 1 + k.k1 * r2 + k.k2 * r2 * r2;
    const double u = k.fx * x * s + k.cx, v = k.fy * y * s + k.cy;
    u0 = std::min(u0, u), u1 = std::max(u1, u), v0 = std::min(v0, v), v1 = std::max(v1, v);
  }
};

}  // namespace

struct Renderer::Impl {
  // Radial undistortion table: s(r_d^2) = r_u / r_d.
  std::vector<float> lut;
  float lut_scale = 0;
  // Undistorted pixel rectangle the output image sees.
  int ub_x0 = 0, ub_y0 = 0, ub_x1 = 0, ub_y1 = 0;
  // Visibility buffer over the rock's screen rectangle (this frame).
  int roi_x0 = 0, roi_y0 = 0, roi_w = 0, roi_h = 0;
  std::vector<float> invz;
  std::vector<int32_t> tri;
  // Per-vertex scratch.
  std::vector<int32_t> xi, yi;
  std::vector<float> key;
  std::vector<uint8_t> valid;
  std::vector<double> fu, fv;
  // Rock faces: planes in the rock frame.
  std::vector<float> fn;  // 3 per face
  std::vector<float> fd;
  // With gloss: smooth (area-weighted) vertex normals for the highlight, which
  // on the flat faces alone would light whole chips at once.
  std::vector<Vec3> vn;
  // Shadow map in light coordinates (e1, e2, key along the light).
  Vec3 e1, e2;
  int sm_w = 0, sm_h = 0;
  double sm_u0 = 0, sm_v0 = 0, sm_texel = kShadowTexelMm;
  std::vector<float> sm_key, sm_cov, blur_tmp;
  // Tone and noise.
  std::vector<float> srgb;  // 4096 entries, linear [0,1] -> 8-bit value
  std::vector<Label> labels;
  // Calibration board (scene "charuco"): albedo texture of the squares area,
  // prefiltered to the camera's footprint, and the board's pose on the platter.
  bool has_board = false;
  std::vector<float> board_tex;
  int board_tw = 0, board_th = 0;
  double board_x = 0, board_y = 0, board_cos = 1, board_sin = 0;
  double board_hw = 0, board_hh = 0;  // half width / height of the squares area, mm
  double board_tex_per_mm_x = 0, board_tex_per_mm_y = 0;
  // ArUco scale markers (rig.aruco_markers), drawn in every scene.
  std::vector<ArucoPaper> aruco;

  const SimWorld* world = nullptr;
  Intrinsics intr;
  float disc_r = 0, disc_r2 = 0;
  Lighting light;
  float gloss = 0, shininess = 60;  // [sim] rock_gloss, rock_shininess
  Rigid cam_to_world;
  // Cached static background (8-bit, before noise) and the gains it was made with.
  std::vector<uint8_t> base;
  std::array<float, 3> base_gains{};
  bool base_valid = false;
  double noise_sigma = -1;
  std::vector<int16_t> noise;  // 1024 quantiles of N(0, sigma), rounded
  float r2_corner = 1;

  bool Shade(const FrameState& fs, int u, int v, float rgb[3], float* r2_out) const;
  void ToneMap(const float rgb[3], float r2, const std::array<float, 3>& gains,
               uint8_t* out) const {
    // Lens vignetting, ~12% at the corners; then exposure and the sRGB curve.
    const float vig = 1.0f - 0.12f * r2 / r2_corner;
    for (int k = 0; k < 3; ++k) {
      const float x = rgb[k] * vig * gains[k];
      // srgb holds [0, 255]: non-negative, so +0.5 and truncation round half up.
      // NOLINTNEXTLINE(bugprone-incorrect-roundings): operand never negative; hot per-pixel path
      out[k] = static_cast<uint8_t>(srgb[static_cast<int>(std::min(x, 4095.0f))] + 0.5f);
    }
  }

  float Undistort(float r2) const {
    float x = r2 * lut_scale;
    if (x >= kLutSize) x = kLutSize - 1e-3f;
    const int i = static_cast<int>(x);
    const float fr = x - static_cast<float>(i);
    return lut[i] + (lut[i + 1] - lut[i]) * fr;
  }
  // Bilinear sample of the board texture at board-frame (x, y) mm (board.h).
  float BoardAlbedo(double x, double y) const {
    return Bilinear(board_tex, board_tw, board_th, (x + board_hw) * board_tex_per_mm_x - 0.5,
                    (board_hh - y) * board_tex_per_mm_y - 0.5);
  }
  // Fraction of the ground point's light ray that passes the rock.
  float GroundVis(const FrameState& fs, const Vec3& p) const {
    if (!fs.dynamic) return 1.0f;
    const double x = (Dot(p, e1) - sm_u0) / sm_texel, y = (Dot(p, e2) - sm_v0) / sm_texel;
    if (x < 0 || y < 0 || x >= sm_w - 1 || y >= sm_h - 1) return 1.0f;
    const int i = static_cast<int>(x), j = static_cast<int>(y);
    const float fx = static_cast<float>(x - i), fy = static_cast<float>(y - j);
    const float* c = &sm_cov[j * sm_w + i];
    const float cov =
        (c[0] * (1 - fx) + c[1] * fx) * (1 - fy) + (c[sm_w] * (1 - fx) + c[sm_w + 1] * fx) * fy;
    return 1.0f - cov;
  }
};

bool Renderer::Impl::Shade(const FrameState& fs, int u, int v, float rgb[3], float* r2_out) const {
  const float fx = static_cast<float>(intr.fx), fy = static_cast<float>(intr.fy);
  const float cx = static_cast<float>(intr.cx), cy = static_cast<float>(intr.cy);
  const float xd = (static_cast<float>(u) - cx) / fx, yd = (static_cast<float>(v) - cy) / fy;
  const float r2 = xd * xd + yd * yd;
  *r2_out = r2;
  const float s = Undistort(r2);
  const float xu = xd * s, yu = yd * s;
  const Vec3& L = light.to_light;
  const float key_i = static_cast<float>(light.key), amb_i = static_cast<float>(light.ambient);
  if (fs.dynamic) {
    const int iu = static_cast<int>(std::floor(xu * fx + cx + 0.5f)) - roi_x0;
    const int iv = static_cast<int>(std::floor(yu * fy + cy + 0.5f)) - roi_y0;
    const size_t vis_idx = static_cast<size_t>(iv) * roi_w + iu;
    const int32_t t = (iu >= 0 && iv >= 0 && iu < roi_w && iv < roi_h) ? tri[vis_idx] : -1;
    if (t >= 0) {
      // Rock: exact ray / triangle-plane intersection in the rock frame.
      const float* M = fs.M;
      const float dx = M[0] * xu + M[1] * yu + M[2], dy = M[3] * xu + M[4] * yu + M[5],
                  dz = M[6] * xu + M[7] * yu + M[8];
      const size_t f3 = 3 * static_cast<size_t>(t);
      const float nx = fn[f3], ny = fn[f3 + 1], nz = fn[f3 + 2];
      const float den = nx * dx + ny * dy + nz * dz;
      const float zbuf = 1.0f / invz[vis_idx];
      float tt = den < -1e-4f ? (fd[t] - (nx * fs.ox + ny * fs.oy + nz * fs.oz)) / den : zbuf;
      if (!(tt > 0.8f * zbuf && tt < 1.25f * zbuf)) tt = zbuf;  // grazing: trust the buffer
      const Vec3 p{fs.ox + tt * dx, fs.oy + tt * dy, fs.oz + tt * dz};
      const Vec3 n{nx, ny, nz};
      const std::array<float, 3> alb = world->RockAlbedo(p, n);
      float lit = static_cast<float>(Dot(n, fs.Lr));
      float key_vis = lit > 0 ? 1.0f : 0.0f;  // the key light reaches p (for the highlight)
      if (lit > 0) {
        // Self-shadow: bilinear percentage-closer test on the light depth map.
        const double su = (Dot(fs.au, p) + fs.bu - sm_u0) / sm_texel;
        const double sv = (Dot(fs.av, p) + fs.bv - sm_v0) / sm_texel;
        const float pk = static_cast<float>(Dot(fs.ak, p) + fs.bk) + kShadowBiasMm;
        const int i = static_cast<int>(su), j = static_cast<int>(sv);
        if (i >= 0 && j >= 0 && i < sm_w - 1 && j < sm_h - 1) {
          const float fu = static_cast<float>(su - i), fv = static_cast<float>(sv - j);
          const float* k = &sm_key[static_cast<size_t>(j) * sm_w + i];
          const float vis = ((pk >= k[0]) * (1 - fu) + (pk >= k[1]) * fu) * (1 - fv) +
                            ((pk >= k[sm_w]) * (1 - fu) + (pk >= k[sm_w + 1]) * fu) * fv;
          lit *= vis;
          key_vis = vis;
        }
      } else {
        lit = 0;
      }
      const float amb = amb_i * (0.8f + 0.2f * static_cast<float>(Dot(n, fs.up_r)));
      const float e = key_i * lit + amb;
      // A wet stone's highlight (Blinn-Phong, white: the coat reflects the
      // light's colour). The light stands still while the rock turns, so the
      // highlight slides over the stone from view to view.
      float spec = 0;
      if (gloss > 0 && key_vis > 0 && !vn.empty()) {
        // The vertex normals interpolated at p (barycentric in the face).
        const auto& f = world->rock().faces[t];
        const Vec3 a = ToVec3(world->rock().vertices[f[0]]);
        const Vec3 e1f = ToVec3(world->rock().vertices[f[1]]) - a;
        const Vec3 e2f = ToVec3(world->rock().vertices[f[2]]) - a;
        const Vec3 q = p - a;
        const double d00 = Dot(e1f, e1f), d01 = Dot(e1f, e2f), d11 = Dot(e2f, e2f);
        const double det = d00 * d11 - d01 * d01;
        double bu = 0, bv = 0;
        if (det > 1e-12) {
          const double q0 = Dot(q, e1f), q1 = Dot(q, e2f);
          bu = std::clamp((d11 * q0 - d01 * q1) / det, 0.0, 1.0);
          bv = std::clamp((d00 * q1 - d01 * q0) / det, 0.0, 1.0 - bu);
        }
        const Vec3 ns = Normalized(vn[f[0]] * (1 - bu - bv) + vn[f[1]] * bu + vn[f[2]] * bv);
        const Vec3 to_cam = Normalized(Vec3{fs.ox, fs.oy, fs.oz} - p);
        const float nh = static_cast<float>(Dot(ns, Normalized(fs.Lr + to_cam)));
        if (nh > 0) spec = gloss * key_i * key_vis * std::pow(nh, shininess);
      }
      rgb[0] = alb[0] * e + spec, rgb[1] = alb[1] * e + spec, rgb[2] = alb[2] * e + spec;
      return true;
    }
  }
  // Background: ray-cast the disc top, its rim and the table.
  constexpr float kDisc = 0.74f, kRim = 0.40f, kTable = 0.90f;  // albedos
  const Vec3 d = cam_to_world.Rotate({xu, yu, 1.0});
  const Vec3& C = cam_to_world.t;
  float albedo[3] = {kTable, kTable, kTable};
  float direct = 0, vis = 1;
  if (d.z < -1e-9) {
    const Vec3 p = C + d * (-C.z / d.z);
    if (p.x * p.x + p.y * p.y <= disc_r2) {
      albedo[0] = albedo[1] = albedo[2] = kDisc;
      if (fs.dynamic) {
        const Vec3 q = fs.to_platter.Rotate(p);
        const float qx = static_cast<float>(q.x), qy = static_cast<float>(q.y);
        for (const Label& lb : labels) {
          if (qx >= lb.x0 && qx <= lb.x1 && qy >= lb.y0 && qy <= lb.y1) {
            albedo[0] = lb.albedo[0], albedo[1] = lb.albedo[1], albedo[2] = lb.albedo[2];
            break;
          }
        }
        for (const ArucoPaper& a : aruco) {
          // The paper lies on top of the disc and its labels.
          const double dx = q.x - a.x, dy = q.y - a.y;
          const double bx = a.c * dx + a.s * dy, by = -a.s * dx + a.c * dy;
          if (std::abs(bx) <= a.half && std::abs(by) <= a.half) {
            const float al = Bilinear(a.tex, a.tw, a.tw, (bx + a.half) * a.tex_per_mm - 0.5,
                                      (a.half - by) * a.tex_per_mm - 0.5);
            albedo[0] = albedo[1] = albedo[2] = al;
            break;
          }
        }
        if (has_board) {
          // The paper lies on top of the disc and its labels.
          const double dx = q.x - board_x, dy = q.y - board_y;
          const double bx = board_cos * dx + board_sin * dy, by = -board_sin * dx + board_cos * dy;
          if (std::abs(bx) <= board_hw + kBoardPaperMarginMm &&
              std::abs(by) <= board_hh + kBoardPaperMarginMm) {
            float a = kPaperAlbedo;
            if (std::abs(bx) < board_hw && std::abs(by) < board_hh) a = BoardAlbedo(bx, by);
            albedo[0] = albedo[1] = albedo[2] = a;
          }
        }
      }
      direct = static_cast<float>(L.z);
      vis = GroundVis(fs, p);
    } else {
      // Entering the disc's cylinder below its top: the rim.
      const double a = d.x * d.x + d.y * d.y, b = 2 * (C.x * d.x + C.y * d.y);
      const double c = C.x * C.x + C.y * C.y - static_cast<double>(disc_r2);
      const double disc = b * b - 4 * a * c;
      double zr = 1;
      Vec3 pr;
      if (disc > 0) {
        pr = C + d * ((-b - std::sqrt(disc)) / (2 * a));
        zr = pr.z;
      }
      if (zr <= 0 && zr >= -kDiscThicknessMm) {
        albedo[0] = albedo[1] = albedo[2] = kRim;
        const Vec3 nr{pr.x / disc_r, pr.y / disc_r, 0};
        direct = static_cast<float>(std::max(0.0, Dot(nr, L)));
        vis = GroundVis(fs, pr);
      } else {
        const Vec3 pt = C + d * ((-kDiscThicknessMm - C.z) / d.z);
        direct = static_cast<float>(L.z);
        vis = GroundVis(fs, pt);
        // The disc's own soft shadow on the table.
        const Vec3 ps = pt + L * (kDiscThicknessMm / L.z);
        const double rs = std::sqrt(ps.x * ps.x + ps.y * ps.y);
        vis *= static_cast<float>(std::clamp((rs - disc_r) / 4.0 + 0.5, 0.0, 1.0));
      }
    }
  } else {
    direct = 0.5f;  // above the horizon: the lit white backdrop
  }
  const float e = key_i * direct * vis + amb_i;
  rgb[0] = albedo[0] * e, rgb[1] = albedo[1] * e, rgb[2] = albedo[2] * e;
  return false;
}

Renderer::Renderer(const SimWorld& world, int width, int height)
    : world_(world), intr_(world.IntrinsicsFor(width, height)), impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  // Undistortion table over the image's largest distorted radius (corners).
  const double xr = std::max(intr_.cx, width - 1 - intr_.cx) / intr_.fx + 2.0 / intr_.fx;
  const double yr = std::max(intr_.cy, height - 1 - intr_.cy) / intr_.fy + 2.0 / intr_.fy;
  const double r2max = xr * xr + yr * yr;
  m.lut.resize(kLutSize + 2);
  m.lut_scale = static_cast<float>(kLutSize / r2max);
  for (int i = 0; i < kLutSize + 2; ++i) {
    const double rd = std::sqrt(i * r2max / kLutSize);
    double ru = rd;
    for (int it = 0; it < 30; ++it) {  // Newton on ru (1 + k1 ru^2 + k2 ru^4) = rd
      const double r2 = ru * ru;
      const double f = ru * (1 + intr_.k1 * r2 + intr_.k2 * r2 * r2) - rd;
      const double df = 1 + 3 * intr_.k1 * r2 + 5 * intr_.k2 * r2 * r2;
      ru -= f / df;
    }
    m.lut[i] = rd > 1e-12 ? static_cast<float>(ru / rd) : 1.0f;
  }
  // Undistorted rectangle: map the output border.
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  auto visit = [&](double u, double v) {
    const double xd = (u - intr_.cx) / intr_.fx, yd = (v - intr_.cy) / intr_.fy;
    const double s = m.Undistort(static_cast<float>(xd * xd + yd * yd));
    const double ub = xd * s * intr_.fx + intr_.cx, vb = yd * s * intr_.fy + intr_.cy;
    x0 = std::min(x0, ub), x1 = std::max(x1, ub), y0 = std::min(y0, vb), y1 = std::max(y1, vb);
  };
  for (int u = 0; u < width; ++u) visit(u, 0), visit(u, height - 1);
  for (int v = 0; v < height; ++v) visit(0, v), visit(width - 1, v);
  m.ub_x0 = static_cast<int>(std::floor(x0)) - 2;
  m.ub_x1 = static_cast<int>(std::ceil(x1)) + 2;
  m.ub_y0 = static_cast<int>(std::floor(y0)) - 2;
  m.ub_y1 = static_cast<int>(std::ceil(y1)) + 2;

  const Mesh& rock = world.rock();
  m.fn.resize(rock.faces.size() * 3);
  m.fd.resize(rock.faces.size());
  for (size_t f = 0; f < rock.faces.size(); ++f) {
    const Vec3 n = world.face_normals()[f];
    m.fn[3 * f] = static_cast<float>(n.x), m.fn[3 * f + 1] = static_cast<float>(n.y);
    m.fn[3 * f + 2] = static_cast<float>(n.z);
    m.fd[f] = static_cast<float>(Dot(n, ToVec3(rock.vertices[rock.faces[f][0]])));
  }
  const size_t nv = rock.vertices.size();
  if (world.config().sim.rock_gloss > 0) {
    m.vn.assign(nv, Vec3{0, 0, 0});
    for (const auto& f : rock.faces) {
      const Vec3 a = ToVec3(rock.vertices[f[0]]), b = ToVec3(rock.vertices[f[1]]),
                 c = ToVec3(rock.vertices[f[2]]);
      const Vec3 w = Cross(b - a, c - a);  // area-weighted
      for (int k = 0; k < 3; ++k) m.vn[f[k]] = m.vn[f[k]] + w;
    }
    for (Vec3& n : m.vn) n = Normalized(n);
  }
  m.xi.resize(nv), m.yi.resize(nv), m.key.resize(nv), m.valid.resize(nv), m.fu.resize(nv),
      m.fv.resize(nv);

  const Vec3 l = world.lighting().to_light;
  m.e1 = Normalized(Cross(Vec3{0, 0, 1}, l));
  if (Norm(m.e1) < 0.5) m.e1 = {1, 0, 0};
  m.e2 = Cross(l, m.e1);  // (e1, e2, l) right-handed

  m.srgb.resize(4096);
  for (int i = 0; i < 4096; ++i) {
    const double v = i / 4095.0;
    const double s = v <= 0.0031308 ? 12.92 * v : 1.055 * std::pow(v, 1 / 2.4) - 0.055;
    m.srgb[i] = static_cast<float>(255.0 * s);
  }
  m.world = &world;
  w2c_ = world.world_to_camera();
  m.cam_to_world = w2c_.Inverse();
  m.intr = intr_;
  m.light = world.lighting();
  m.gloss = static_cast<float>(world.config().sim.rock_gloss);
  m.shininess = static_cast<float>(world.config().sim.rock_shininess);
  m.disc_r = static_cast<float>(world.config().rig.turntable_diameter_mm / 2);
  m.disc_r2 = m.disc_r * m.disc_r;
  m.r2_corner =
      static_cast<float>((intr_.cx * intr_.cx + intr_.cy * intr_.cy) / (intr_.fx * intr_.fx));

  const RigConfig& rig = world.config().rig;
  const float half = static_cast<float>(rig.marker_size_mm / 2);
  for (const RigMarker& mk : rig.markers) {
    Label lb{static_cast<float>(mk.x_mm) - half,
             static_cast<float>(mk.x_mm) + half,
             static_cast<float>(mk.y_mm) - half,
             static_cast<float>(mk.y_mm) + half,
             {0.5f, 0.5f, 0.5f}};
    ColorAlbedo(mk.color, &lb.albedo);
    m.labels.push_back(lb);
  }
  if (const SimBoard* b = world.board()) BuildBoardTexture(*b);
  for (const SimArucoMarker& a : world.aruco_markers()) BuildArucoTexture(a);
}

void Renderer::BuildArucoTexture(const SimArucoMarker& a) {
  Impl& m = *impl_;
  ArucoPaper p;
  const int side = a.image.width;
  const int margin = static_cast<int>(std::lround(kArucoPaperMarginFrac * side));
  p.tw = side + 2 * margin;
  p.tex_per_mm = side / a.size_mm;
  p.half = 0.5 * p.tw / p.tex_per_mm;
  p.x = a.x_mm;
  p.y = a.y_mm;
  p.c = std::cos(a.yaw_deg * M_PI / 180.0);
  p.s = std::sin(a.yaw_deg * M_PI / 180.0);
  p.tex.assign(static_cast<size_t>(p.tw) * p.tw, kPaperAlbedo);
  for (int r = 0; r < side; ++r) {
    for (int c = 0; c < side; ++c) {
      p.tex[static_cast<size_t>(r + margin) * p.tw + c + margin] =
          kInkAlbedo + (kPaperAlbedo - kInkAlbedo) *
                           (a.image.pixels[static_cast<size_t>(r) * side + c] / 255.0f);
    }
  }
  // The lens and sensor blur: half a pixel's footprint on the disc, which is
  // longer along the viewing direction by 1 / sin(elevation).
  const double mm_per_px = Norm(m.cam_to_world.t) / intr_.fx;
  const double elev =
      std::clamp(world_.config().sim.camera_elevation_deg, 10.0, 90.0) * M_PI / 180.0;
  BlurTexture(&p.tex, p.tw, p.tw, 0.5 * mm_per_px / std::sin(elev) * p.tex_per_mm);
  m.aruco.push_back(std::move(p));
}

void Renderer::BuildBoardTexture(const SimBoard& b) {
  Impl& m = *impl_;
  m.has_board = true;
  m.board_tw = b.image.width;
  m.board_th = b.image.height;
  m.board_hw = b.width_mm / 2;
  m.board_hh = b.height_mm / 2;
  m.board_tex_per_mm_x = b.image.width / b.width_mm;
  m.board_tex_per_mm_y = b.image.height / b.height_mm;
  m.board_x = b.x_mm;
  m.board_y = b.y_mm;
  m.board_cos = std::cos(b.yaw_deg * M_PI / 180.0);
  m.board_sin = std::sin(b.yaw_deg * M_PI / 180.0);
  const size_t n = static_cast<size_t>(m.board_tw) * m.board_th;
  m.board_tex.resize(n);
  for (size_t i = 0; i < n; ++i) {
    m.board_tex[i] = kInkAlbedo + (kPaperAlbedo - kInkAlbedo) * (b.image.pixels[i] / 255.0f);
  }
  // Point-sampling a sharp print would alias; a real lens and sensor blur it
  // by about half a pixel. Gaussian prefilter of that footprint (mm per pixel
  // at the disc centre).
  const double mm_per_px = Norm(m.cam_to_world.t) / intr_.fx;
  BlurTexture(&m.board_tex, m.board_tw, m.board_th,
              0.5 * mm_per_px * std::max(m.board_tex_per_mm_x, m.board_tex_per_mm_y));
}

Renderer::~Renderer() = default;

RenderedImage Renderer::Render(int side, double platter_deg, const RenderOptions& options) {
  RenderedImage out;
  RenderInto(side, platter_deg, options, &out);
  return out;
}

void Renderer::RenderInto(int side, double platter_deg, const RenderOptions& options,
                          RenderedImage* out) {
  Impl& m = *impl_;
  const Mesh& rock = world_.rock();
  const int nv = static_cast<int>(rock.vertices.size());
  const int W = intr_.width, H = intr_.height;
  const Lighting& light = world_.lighting();

  // ---- 1. visibility buffer of the rock (undistorted pixel space) ----
  // The "charuco" scene has no rock: no visibility buffer, no shadow map.
  const bool draw_rock = !m.has_board;
  const Rigid rock_to_cam = w2c_ * world_.RockToWorld(side, platter_deg);
  double bx0 = 1e300, bx1 = -1e300, by0 = 1e300, by1 = -1e300;
  for (int i = 0; i < (draw_rock ? nv : 0); ++i) {
    const Vec3 p = rock_to_cam.Apply(ToVec3(rock.vertices[i]));
    m.valid[i] = p.z > 1.0 ? 1 : 0;
    if (!m.valid[i]) continue;
    const double iz = 1.0 / p.z;
    m.fu[i] = intr_.fx * p.x * iz + intr_.cx;
    m.fv[i] = intr_.fy * p.y * iz + intr_.cy;
    m.key[i] = static_cast<float>(iz);
    bx0 = std::min(bx0, m.fu[i]), bx1 = std::max(bx1, m.fu[i]);
    by0 = std::min(by0, m.fv[i]), by1 = std::max(by1, m.fv[i]);
  }
  m.roi_x0 = std::max(m.ub_x0, static_cast<int>(std::floor(bx0)) - 1);
  m.roi_y0 = std::max(m.ub_y0, static_cast<int>(std::floor(by0)) - 1);
  m.roi_w = std::max(0, std::min(m.ub_x1, static_cast<int>(std::ceil(bx1)) + 1) - m.roi_x0 + 1);
  m.roi_h = std::max(0, std::min(m.ub_y1, static_cast<int>(std::ceil(by1)) + 1) - m.roi_y0 + 1);
  if (bx0 > bx1) m.roi_w = m.roi_h = 0;
  const size_t roi_n = static_cast<size_t>(m.roi_w) * m.roi_h;
  m.invz.assign(roi_n, 0.0f);
  m.tri.assign(roi_n, -1);
  if (roi_n > 0) {
    for (int i = 0; i < nv; ++i) {
      if (!m.valid[i]) continue;
      const double x = (m.fu[i] - m.roi_x0) * kSub, y = (m.fv[i] - m.roi_y0) * kSub;
      if (std::abs(x) > 1e9 || std::abs(y) > 1e9) {
        m.valid[i] = 0;
        continue;
      }
      m.xi[i] = static_cast<int32_t>(std::lround(x));
      m.yi[i] = static_cast<int32_t>(std::lround(y));
    }
    Rasterize(rock.faces, m.xi.data(), m.yi.data(), m.key.data(), m.valid.data(),
              {m.roi_w, m.roi_h, m.invz.data(), m.tri.data()});
  }

  // ---- 2. shadow map from the key light ----
  const Rigid rock_to_world = world_.RockToWorld(side, platter_deg);
  const Vec3 L = light.to_light;
  if (draw_rock) {
    double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300;
    for (int i = 0; i < nv; ++i) {
      const Vec3 p = rock_to_world.Apply(ToVec3(rock.vertices[i]));
      m.fu[i] = Dot(p, m.e1);
      m.fv[i] = Dot(p, m.e2);
      m.key[i] = static_cast<float>(Dot(p, L));
      u0 = std::min(u0, m.fu[i]), u1 = std::max(u1, m.fu[i]);
      v0 = std::min(v0, m.fv[i]), v1 = std::max(v1, m.fv[i]);
    }
    m.sm_texel = std::max(kShadowTexelMm, std::max(u1 - u0, v1 - v0) / 1200.0);
    const double margin = (kBlurRadius * kBlurPasses + 3) * m.sm_texel;
    m.sm_u0 = u0 - margin, m.sm_v0 = v0 - margin;
    m.sm_w = static_cast<int>(std::ceil((u1 - u0 + 2 * margin) / m.sm_texel)) + 1;
    m.sm_h = static_cast<int>(std::ceil((v1 - v0 + 2 * margin) / m.sm_texel)) + 1;
    m.sm_key.assign(static_cast<size_t>(m.sm_w) * m.sm_h, kNoKey);
    for (int i = 0; i < nv; ++i) {
      m.valid[i] = 1;
      m.xi[i] = static_cast<int32_t>(std::lround((m.fu[i] - m.sm_u0) / m.sm_texel * kSub));
      m.yi[i] = static_cast<int32_t>(std::lround((m.fv[i] - m.sm_v0) / m.sm_texel * kSub));
    }
    // Faces turned away from the light (negative area in (e1, e2)): the depth of
    // the far side of the first solid along each light ray, so lit surfaces are
    // never self-shadowed by rounding.
    Rasterize(rock.faces, m.xi.data(), m.yi.data(), m.key.data(), m.valid.data(),
              {m.sm_w, m.sm_h, m.sm_key.data(), nullptr});
    m.sm_cov.resize(m.sm_key.size());
    for (size_t i = 0; i < m.sm_key.size(); ++i) m.sm_cov[i] = m.sm_key[i] > kNoKey ? 1.0f : 0.0f;
    for (int pass = 0; pass < kBlurPasses; ++pass) {
      BoxBlur(m.sm_cov.data(), m.sm_w, m.sm_h, kBlurRadius, true, &m.blur_tmp);
      BoxBlur(m.sm_cov.data(), m.sm_w, m.sm_h, kBlurRadius, false, &m.blur_tmp);
    }
  } else {
    m.sm_w = m.sm_h = 0;  // GroundVis: everything lit
    m.sm_u0 = m.sm_v0 = 0;
    m.sm_texel = 1;
  }

  // ---- 3. per-pixel shading ----
  const Rigid cam_to_rock = rock_to_cam.Inverse();
  const Rigid world_to_rock = rock_to_world.Inverse();
  FrameState fs;
  for (int k = 0; k < 9; ++k) fs.M[k] = static_cast<float>(cam_to_rock.R[k]);
  fs.ox = static_cast<float>(cam_to_rock.t.x);
  fs.oy = static_cast<float>(cam_to_rock.t.y);
  fs.oz = static_cast<float>(cam_to_rock.t.z);
  fs.Lr = world_to_rock.Rotate(L);
  fs.up_r = world_to_rock.Rotate({0, 0, 1});
  // Light-map coordinates as affine functions of rock-frame points.
  fs.au = world_to_rock.Rotate(m.e1);
  fs.av = world_to_rock.Rotate(m.e2);
  fs.ak = fs.Lr;
  fs.bu = Dot(m.e1, rock_to_world.t);
  fs.bv = Dot(m.e2, rock_to_world.t);
  fs.bk = Dot(L, rock_to_world.t);
  fs.to_platter = Rigid::RotZ(-platter_deg);

  const double expo =
      options.exposure.exposure_us * options.exposure.gain / world_.reference_exposure();
  const std::array<float, 3> gains{static_cast<float>(expo * options.exposure.wb_red) * 4095.0f,
                                   static_cast<float>(expo) * 4095.0f,
                                   static_cast<float>(expo * options.exposure.wb_blue) * 4095.0f};
  // The static background (disc without labels, rim, table, no rock or rock
  // shadow) is shaded once per exposure setting and copied; only the regions
  // the rock, its shadow and the labels can touch are shaded per frame.
  if (!m.base_valid || m.base_gains != gains) {
    FrameState empty = fs;
    empty.dynamic = false;
    m.base.resize(static_cast<size_t>(W) * H * 3);
    float rgb[3];
    for (int v = 0; v < H; ++v) {
      for (int u = 0; u < W; ++u) {
        float r2;
        m.Shade(empty, u, v, rgb, &r2);
        m.ToneMap(rgb, r2, gains, &m.base[(static_cast<size_t>(v) * W + u) * 3]);
      }
    }
    m.base_valid = true;
    m.base_gains = gains;
  }
  out->width = W;
  out->height = H;
  out->rgb.assign(m.base.begin(), m.base.end());
  if (options.want_mask) {
    out->mask.assign(static_cast<size_t>(W) * H, 0);
  } else {
    out->mask.clear();
  }

  // Output-pixel boxes of everything that changes per frame, found by
  // distorting sampled outlines (distortion bends straight edges).
  std::vector<Box> boxes;
  const Rigid& w2c = w2c_;
  auto box_of_world_quad = [&](const std::array<Vec3, 4>& q) {
    Box b;
    for (int e = 0; e < 4; ++e)
      for (int i = 0; i <= 16; ++i) {
        const Vec3 p = w2c.Apply(q[e] + (q[(e + 1) % 4] - q[e]) * (i / 16.0));
        if (p.z <= 1e-6) continue;
        b.Extend(intr_, p.x / p.z, p.y / p.z);
      }
    boxes.push_back(b);
  };
  if (m.roi_w > 0 && m.roi_h > 0) {
    Box b;
    const double x0 = (m.roi_x0 - 1 - intr_.cx) / intr_.fx,
                 x1 = (m.roi_x0 + m.roi_w - intr_.cx) / intr_.fx;
    const double y0 = (m.roi_y0 - 1 - intr_.cy) / intr_.fy,
                 y1 = (m.roi_y0 + m.roi_h - intr_.cy) / intr_.fy;
    for (int i = 0; i <= 32; ++i) {
      const double a = i / 32.0;
      b.Extend(intr_, x0 + (x1 - x0) * a, y0), b.Extend(intr_, x0 + (x1 - x0) * a, y1);
      b.Extend(intr_, x0, y0 + (y1 - y0) * a), b.Extend(intr_, x1, y0 + (y1 - y0) * a);
    }
    boxes.push_back(b);
  }
  if (draw_rock) {
    // The shadow map's footprint on the disc top and on the table (the rim lies between).
    const double su1 = m.sm_u0 + m.sm_w * m.sm_texel, sv1 = m.sm_v0 + m.sm_h * m.sm_texel;
    for (double z0 : {0.0, -kDiscThicknessMm}) {
      std::array<Vec3, 4> q;
      const double cu[4] = {m.sm_u0, su1, su1, m.sm_u0}, cv[4] = {m.sm_v0, m.sm_v0, sv1, sv1};
      for (int i = 0; i < 4; ++i) {
        const Vec3 p = m.e1 * cu[i] + m.e2 * cv[i];
        q[i] = p + L * ((z0 - p.z) / L.z);
      }
      box_of_world_quad(q);
    }
  }
  const Rigid platter = Rigid::RotZ(platter_deg);
  for (const Label& lb : m.labels) {
    box_of_world_quad({platter.Apply({lb.x0, lb.y0, 0}), platter.Apply({lb.x1, lb.y0, 0}),
                       platter.Apply({lb.x1, lb.y1, 0}), platter.Apply({lb.x0, lb.y1, 0})});
  }
  for (const ArucoPaper& a : m.aruco) {
    std::array<Vec3, 4> q;
    const double cx[4] = {-a.half, a.half, a.half, -a.half},
                 cy[4] = {-a.half, -a.half, a.half, a.half};
    for (int i = 0; i < 4; ++i) {
      q[i] = platter.Apply({a.x + a.c * cx[i] - a.s * cy[i], a.y + a.s * cx[i] + a.c * cy[i], 0});
    }
    box_of_world_quad(q);
  }
  if (m.has_board) {
    // The paper sheet (squares area plus margin).
    const double hw = m.board_hw + kBoardPaperMarginMm, hh = m.board_hh + kBoardPaperMarginMm;
    std::array<Vec3, 4> q;
    const double cx[4] = {-hw, hw, hw, -hw}, cy[4] = {-hh, -hh, hh, hh};
    for (int i = 0; i < 4; ++i) {
      q[i] = platter.Apply({m.board_x + m.board_cos * cx[i] - m.board_sin * cy[i],
                            m.board_y + m.board_sin * cx[i] + m.board_cos * cy[i], 0});
    }
    box_of_world_quad(q);
  }
  std::vector<std::pair<int, int>> spans;
  float rgb[3];
  for (int v = 0; v < H; ++v) {
    spans.clear();
    for (const Box& b : boxes) {
      if (v < b.v0 - 3 || v > b.v1 + 3) continue;
      spans.push_back(
          {std::max(0, static_cast<int>(b.u0) - 3), std::min(W - 1, static_cast<int>(b.u1) + 3)});
    }
    std::sort(spans.begin(), spans.end());
    int done_to = -1;
    for (auto [a, b] : spans) {
      for (int u = std::max(a, done_to + 1); u <= b; ++u) {
        float r2;
        const bool rock = m.Shade(fs, u, v, rgb, &r2);
        const size_t i = static_cast<size_t>(v) * W + u;
        m.ToneMap(rgb, r2, gains, &out->rgb[i * 3]);
        if (rock && options.want_mask) out->mask[i] = 255;
      }
      done_to = std::max(done_to, b);
    }
  }

  // ---- 4. sensor noise ----
  const double sigma = world_.config().sim.noise_sigma;
  if (sigma > 0) {
    if (m.noise_sigma != sigma) {
      m.noise_sigma = sigma;
      m.noise.resize(1024);
      for (int i = 0; i < 1024; ++i) {
        m.noise[i] = static_cast<int16_t>(std::lround(sigma * InverseNormal((i + 0.5) / 1024.0)));
      }
    }
    uint64_t rng = options.noise_seed * 0x9E3779B97F4A7C15ull + 0x632BE59BD9B4E019ull;
    if (rng == 0) rng = 1;
    uint8_t* px = out->rgb.data();
    const size_t n = out->rgb.size();
    size_t i = 0;
    while (i < n) {
      rng ^= rng >> 12, rng ^= rng << 25, rng ^= rng >> 27;
      uint64_t bits = rng * 0x2545F4914F6CDD1Dull;
      for (int k = 0; k < 6 && i < n; ++k, ++i) {
        const int val = px[i] + m.noise[bits & 1023];
        px[i] = static_cast<uint8_t>(val < 0 ? 0 : (val > 255 ? 255 : val));
        bits >>= 10;
      }
    }
  }
}

void Renderer::SetCamera(const Rigid& world_to_camera) {
  w2c_ = world_to_camera;
  impl_->cam_to_world = w2c_.Inverse();
  impl_->base_valid = false;
}

RenderedImage Render(const SimWorld& world, int side, double platter_deg,
                     const ExposureSettings& exposure, uint64_t noise_seed, bool want_mask) {
  Renderer r(world, world.config().camera.width, world.config().camera.height);
  RenderOptions o;
  o.exposure = exposure;
  o.noise_seed = noise_seed;
  o.want_mask = want_mask;
  return r.Render(side, platter_deg, o);
}

}  // namespace aggscan::sim
