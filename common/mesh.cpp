// Mesh file readers (PLY, OBJ, STL) and the binary PLY writer.
//
// Files are read whole into memory (scanned rocks are a few MB); every read
// from the byte buffer is bounds-checked so a truncated file is an error that
// names the file and where it ended, never a crash.
#include "common/mesh.h"

#include <algorithm>
#include <bit>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <optional>
#include <string_view>
#include <unordered_map>

#include "common/fsutil.h"

namespace aggscan {
namespace {

// Scanned rocks are a few MB; the file is read whole.
constexpr uint64_t kMaxMeshFileBytes = 1ULL << 30;
// Beyond this a coordinate is no rock's (mm; 10 km), and cubing it for the
// volume would lose every digit of the result.
constexpr double kMaxMeshCoordinateMm = 1e7;

// std::byteswap is C++23.
template <typename U>
U ByteSwap(U v) {
  unsigned char b[sizeof(U)];
  std::memcpy(b, &v, sizeof(U));
  std::reverse(b, b + sizeof(U));
  std::memcpy(&v, b, sizeof(U));
  return v;
}

Error Corrupt(const std::string& path, const std::string& what) {
  return MakeError(ErrorClass::kCorrupt, "mesh file " + path + ": " + what);
}

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

// Splits on ASCII whitespace.
std::vector<std::string_view> Tokens(std::string_view line) {
  std::vector<std::string_view> out;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    size_t j = i;
    while (j < line.size() && !std::isspace(static_cast<unsigned char>(line[j]))) ++j;
    if (j > i) out.push_back(line.substr(i, j - i));
    i = j;
  }
  return out;
}

bool ParseDouble(std::string_view s, double* out) {
  if (!s.empty() && s.front() == '+') s.remove_prefix(1);
  auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), *out);
  return ec == std::errc() && p == s.data() + s.size();
}

bool ParseInt64(std::string_view s, int64_t* out) {
  if (!s.empty() && s.front() == '+') s.remove_prefix(1);
  auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), *out);
  return ec == std::errc() && p == s.data() + s.size();
}

// Appends the fan triangulation of polygon `poly` (already 0-based, checked).
void AddPolygon(const std::vector<int>& poly, Mesh* m) {
  for (size_t k = 1; k + 1 < poly.size(); ++k) m->faces.push_back({poly[0], poly[k], poly[k + 1]});
}

// ---------------------------------------------------------------- PLY

enum class PlyType { kI8, kU8, kI16, kU16, kI32, kU32, kF32, kF64 };

std::optional<PlyType> ParsePlyType(std::string_view s) {
  static const std::map<std::string_view, PlyType> kTypes = {
      {"char", PlyType::kI8},    {"int8", PlyType::kI8},     {"uchar", PlyType::kU8},
      {"uint8", PlyType::kU8},   {"short", PlyType::kI16},   {"int16", PlyType::kI16},
      {"ushort", PlyType::kU16}, {"uint16", PlyType::kU16},  {"int", PlyType::kI32},
      {"int32", PlyType::kI32},  {"uint", PlyType::kU32},    {"uint32", PlyType::kU32},
      {"float", PlyType::kF32},  {"float32", PlyType::kF32}, {"double", PlyType::kF64},
      {"float64", PlyType::kF64}};
  auto it = kTypes.find(s);
  if (it == kTypes.end()) return std::nullopt;
  return it->second;
}

size_t PlyTypeSize(PlyType t) {
  switch (t) {
    case PlyType::kI8:
    case PlyType::kU8:
      return 1;
    case PlyType::kI16:
    case PlyType::kU16:
      return 2;
    case PlyType::kI32:
    case PlyType::kU32:
    case PlyType::kF32:
      return 4;
    case PlyType::kF64:
      return 8;
  }
  return 1;
}

struct PlyProperty {
  std::string name;
  bool is_list = false;
  PlyType count_type = PlyType::kU8;  // lists only
  PlyType type = PlyType::kF32;       // value (or list item) type
};

struct PlyElement {
  std::string name;
  int64_t count = 0;
  std::vector<PlyProperty> props;
};

enum class PlyFormat { kAscii, kBinaryLe, kBinaryBe };

// Vertex indices are ints; a rock's mesh has ~50k vertices.
constexpr int64_t kMaxMeshElements = 100'000'000;

// Reads PLY body values one at a time, ASCII tokens or binary scalars.
class PlyReader {
 public:
  PlyReader(std::string_view body, PlyFormat fmt) : body_(body), fmt_(fmt) {}

  // False at end of data (truncated) or on a malformed ASCII token.
  bool Read(PlyType t, double* out) {
    if (fmt_ == PlyFormat::kAscii) return ReadAscii(out);
    const size_t n = PlyTypeSize(t);
    if (pos_ + n > body_.size()) return false;
    unsigned char b[8];
    std::memcpy(b, body_.data() + pos_, n);
    pos_ += n;
    const bool swap = (fmt_ == PlyFormat::kBinaryBe) != (std::endian::native == std::endian::big);
    if (swap) std::reverse(b, b + n);
    switch (t) {
      case PlyType::kI8: {
        int8_t v;
        std::memcpy(&v, b, 1);
        *out = v;
        break;
      }
      case PlyType::kU8: {
        *out = b[0];
        break;
      }
      case PlyType::kI16: {
        int16_t v;
        std::memcpy(&v, b, 2);
        *out = v;
        break;
      }
      case PlyType::kU16: {
        uint16_t v;
        std::memcpy(&v, b, 2);
        *out = v;
        break;
      }
      case PlyType::kI32: {
        int32_t v;
        std::memcpy(&v, b, 4);
        *out = v;
        break;
      }
      case PlyType::kU32: {
        uint32_t v;
        std::memcpy(&v, b, 4);
        *out = v;
        break;
      }
      case PlyType::kF32: {
        float v;
        std::memcpy(&v, b, 4);
        *out = v;
        break;
      }
      case PlyType::kF64: {
        double v;
        std::memcpy(&v, b, 8);
        *out = v;
        break;
      }
    }
    return true;
  }

  // Binary: skips n scalars of type t without decoding.
  bool Skip(PlyType t, int64_t n) {
    if (fmt_ == PlyFormat::kAscii) {
      double d;
      for (int64_t i = 0; i < n; ++i)
        if (!Read(t, &d)) return false;
      return true;
    }
    const size_t bytes = PlyTypeSize(t) * static_cast<size_t>(n);
    if (pos_ + bytes > body_.size()) return false;
    pos_ += bytes;
    return true;
  }

  bool bad_token() const { return bad_token_; }

 private:
  bool ReadAscii(double* out) {
    while (pos_ < body_.size() && std::isspace(static_cast<unsigned char>(body_[pos_]))) ++pos_;
    if (pos_ >= body_.size()) return false;
    size_t e = pos_;
    while (e < body_.size() && !std::isspace(static_cast<unsigned char>(body_[e]))) ++e;
    std::string_view tok = body_.substr(pos_, e - pos_);
    pos_ = e;
    if (!ParseDouble(tok, out)) {
      bad_token_ = true;
      return false;
    }
    return true;
  }

  std::string_view body_;
  PlyFormat fmt_;
  size_t pos_ = 0;
  bool bad_token_ = false;
};

// The fewest bytes one row of `el` can take in the body: binary, every
// scalar's size and every list's count (an empty list); ASCII, one digit and
// one separator per scalar or list count.
uint64_t PlyMinRowBytes(const PlyElement& el, PlyFormat fmt) {
  uint64_t n = 0;
  for (const PlyProperty& p : el.props) {
    n += fmt == PlyFormat::kAscii ? 2 : PlyTypeSize(p.is_list ? p.count_type : p.type);
  }
  return n;
}

// Refuses element counts the body cannot hold before anything is allocated
// for them: a header claiming 2^31 vertices in a small file is corrupt (or
// hostile), and reserving for it would exhaust memory. Vertex and face counts
// beyond what an int index addresses are refused too.
Status CheckPlyCounts(const std::string& path, const std::vector<PlyElement>& elements,
                      PlyFormat fmt, size_t body_bytes) {
  uint64_t need = 0;
  // ASCII: the last value needs no separator after it.
  const uint64_t avail = body_bytes + (fmt == PlyFormat::kAscii ? 1 : 0);
  for (const PlyElement& el : elements) {
    const uint64_t row = PlyMinRowBytes(el, fmt);
    if (row == 0) continue;
    const uint64_t count = static_cast<uint64_t>(el.count);
    const uint64_t left = avail > need ? avail - need : 0;
    if (count > left / row) {
      return Corrupt(
          path, "header says element " + el.name + " has " + std::to_string(el.count) +
                    " rows of at least " + std::to_string(row) + " bytes each" +
                    (fmt == PlyFormat::kAscii ? " (ASCII)" : "") + ", but the file holds only " +
                    std::to_string(body_bytes) + " bytes after its header (" +
                    std::to_string(left / row) +
                    " such rows at most): the header is corrupt or the file is truncated");
    }
    if ((el.name == "vertex" || el.name == "face") && el.count > kMaxMeshElements) {
      return Corrupt(path, "element " + el.name + " has " + std::to_string(el.count) +
                               " rows, more than the " + std::to_string(kMaxMeshElements) +
                               " a mesh may have");
    }
    need += count * row;
  }
  return OkStatus();
}

Result<Mesh> LoadPly(const std::string& path, const std::string& data) {
  // Header: lines up to "end_header". Line ends are LF, CRLF or (Rhino
  // exports) a bare CR; the first line's ending is used throughout so that
  // the binary body after end_header is not eaten.
  std::string eol = "\n";
  if (data.compare(0, 5, "ply\r\n") == 0)
    eol = "\r\n";
  else if (data.compare(0, 4, "ply\r") == 0)
    eol = "\r";
  size_t pos = 0;
  auto next_line = [&](std::string_view* line) {
    if (pos >= data.size()) return false;
    size_t e = data.find(eol, pos);
    if (e == std::string::npos) e = data.size();
    *line = std::string_view(data).substr(pos, e - pos);
    pos = std::min(data.size(), e + eol.size());
    return true;
  };
  std::string_view line;
  if (!next_line(&line) || line != "ply")
    return Corrupt(path, "not a PLY file (first line is not \"ply\")");
  std::optional<PlyFormat> fmt;
  std::vector<PlyElement> elements;
  bool ended = false;
  int line_no = 1;
  while (next_line(&line)) {
    ++line_no;
    auto tok = Tokens(line);
    if (tok.empty() || tok[0] == "comment" || tok[0] == "obj_info") continue;
    const std::string where = "header line " + std::to_string(line_no);
    if (tok[0] == "end_header") {
      ended = true;
      break;
    } else if (tok[0] == "format") {
      if (tok.size() < 2) return Corrupt(path, where + ": format without a value");
      if (tok[1] == "ascii")
        fmt = PlyFormat::kAscii;
      else if (tok[1] == "binary_little_endian")
        fmt = PlyFormat::kBinaryLe;
      else if (tok[1] == "binary_big_endian")
        fmt = PlyFormat::kBinaryBe;
      else
        return Corrupt(path, where + ": unknown format \"" + std::string(tok[1]) + "\"");
    } else if (tok[0] == "element") {
      int64_t n = 0;
      if (tok.size() != 3) return Corrupt(path, where + ": malformed element line");
      if (!ParseInt64(tok[2], &n) || n < 0)
        return Corrupt(path, where + ": element " + std::string(tok[1]) + " has count \"" +
                                 std::string(tok[2]) + "\", not a count from 0 to " +
                                 std::to_string(INT64_MAX));
      elements.push_back({std::string(tok[1]), n, {}});
    } else if (tok[0] == "property") {
      if (elements.empty()) return Corrupt(path, where + ": property before any element");
      PlyProperty p;
      if (tok.size() == 5 && tok[1] == "list") {
        auto ct = ParsePlyType(tok[2]);
        auto it = ParsePlyType(tok[3]);
        if (!ct || !it) return Corrupt(path, where + ": unknown property type");
        if (*ct == PlyType::kF32 || *ct == PlyType::kF64)
          return Corrupt(path, where + ": list count must be an integer type");
        p.is_list = true;
        p.count_type = *ct;
        p.type = *it;
        p.name = std::string(tok[4]);
      } else if (tok.size() == 3) {
        auto t = ParsePlyType(tok[1]);
        if (!t)
          return Corrupt(path, where + ": unknown property type \"" + std::string(tok[1]) + "\"");
        p.type = *t;
        p.name = std::string(tok[2]);
      } else {
        return Corrupt(path, where + ": malformed property line");
      }
      elements.back().props.push_back(std::move(p));
    } else {
      return Corrupt(path, where + ": unknown header keyword \"" + std::string(tok[0]) + "\"");
    }
  }
  if (!ended) return Corrupt(path, "truncated header (no end_header)");
  if (!fmt) return Corrupt(path, "header has no format line");

  const size_t body_bytes = data.size() - pos;
  if (Status s = CheckPlyCounts(path, elements, *fmt, body_bytes); !s) return s.error();

  PlyReader rd(std::string_view(data).substr(pos), *fmt);
  Mesh m;
  bool have_vertices = false, have_faces = false;
  for (const PlyElement& el : elements) {
    const bool is_vertex = el.name == "vertex";
    const bool is_face = el.name == "face";
    int ix = -1, iy = -1, iz = -1, ilist = -1;
    for (size_t k = 0; k < el.props.size(); ++k) {
      const auto& p = el.props[k];
      if (is_vertex && !p.is_list) {
        if (p.name == "x") ix = static_cast<int>(k);
        if (p.name == "y") iy = static_cast<int>(k);
        if (p.name == "z") iz = static_cast<int>(k);
      }
      if (is_face && p.is_list &&
          (p.name == "vertex_indices" || p.name == "vertex_index" || ilist < 0))
        ilist = static_cast<int>(k);
    }
    if (is_vertex) {
      if (ix < 0 || iy < 0 || iz < 0) return Corrupt(path, "vertex element lacks x, y or z");
      have_vertices = true;
      m.vertices.reserve(static_cast<size_t>(el.count));
    }
    if (is_face) {
      if (ilist < 0) return Corrupt(path, "face element has no vertex_indices list");
      have_faces = true;
      m.faces.reserve(static_cast<size_t>(el.count));
    }
    // An element without properties holds no bytes; nothing to read.
    if (el.props.empty()) continue;
    std::vector<int> poly;
    for (int64_t r = 0; r < el.count; ++r) {
      std::array<double, 3> v{};
      for (size_t k = 0; k < el.props.size(); ++k) {
        const auto& p = el.props[k];
        auto truncated = [&]() {
          return Corrupt(path, std::string(rd.bad_token() ? "malformed number" : "truncated") +
                                   " in " + el.name + " " + std::to_string(r) + " (property " +
                                   p.name + ")");
        };
        if (p.is_list) {
          double cnt_d;
          if (!rd.Read(p.count_type, &cnt_d)) return truncated();
          // A count beyond what the rest of the file could hold is caught by
          // the reads; this keeps the conversion to an integer defined.
          if (!(cnt_d >= 0 && cnt_d <= 4294967295.0))
            return Corrupt(path, "bad list count in " + el.name + " " + std::to_string(r));
          const int64_t cnt = static_cast<int64_t>(cnt_d);
          if (cnt_d != static_cast<double>(cnt))
            return Corrupt(path, "bad list count in " + el.name + " " + std::to_string(r));
          if (is_face && static_cast<int>(k) == ilist) {
            poly.clear();
            for (int64_t q = 0; q < cnt; ++q) {
              double idx;
              if (!rd.Read(p.type, &idx)) return truncated();
              poly.push_back(idx >= 0 ? static_cast<int>(std::min(idx, 2147483647.0)) : -1);
            }
          } else if (!rd.Skip(p.type, cnt)) {
            return truncated();
          }
        } else if (is_vertex && (static_cast<int>(k) == ix || static_cast<int>(k) == iy ||
                                 static_cast<int>(k) == iz)) {
          double d;
          if (!rd.Read(p.type, &d)) return truncated();
          v[static_cast<int>(k) == ix ? 0 : static_cast<int>(k) == iy ? 1 : 2] = d;
        } else if (!rd.Skip(p.type, 1)) {
          return truncated();
        }
      }
      if (is_vertex) m.vertices.push_back(v);
      if (is_face) {
        for (int idx : poly) {
          if (idx < 0 || idx >= static_cast<int>(m.vertices.size()))
            return Corrupt(path, "face " + std::to_string(r) + " has vertex index " +
                                     std::to_string(idx) + " out of range (" +
                                     std::to_string(m.vertices.size()) + " vertices)");
        }
        AddPolygon(poly, &m);
      }
    }
  }
  if (!have_vertices) return Corrupt(path, "no vertex element");
  if (!have_faces) return Corrupt(path, "no face element (point clouds are not meshes)");
  return m;
}

// ---------------------------------------------------------------- OBJ

Result<Mesh> LoadObj(const std::string& path, const std::string& data) {
  Mesh m;
  std::vector<int> poly;
  size_t pos = 0;
  int line_no = 0;
  while (pos < data.size()) {
    size_t e = data.find('\n', pos);
    if (e == std::string::npos) e = data.size();
    std::string_view line = std::string_view(data).substr(pos, e - pos);
    pos = e + 1;
    ++line_no;
    if (line.size() < 2) continue;
    const std::string where = "line " + std::to_string(line_no);
    if (line[0] == 'v' && (line[1] == ' ' || line[1] == '\t')) {
      auto tok = Tokens(line);
      std::array<double, 3> v{};
      if (tok.size() < 4 || !ParseDouble(tok[1], &v[0]) || !ParseDouble(tok[2], &v[1]) ||
          !ParseDouble(tok[3], &v[2]))
        return Corrupt(path, where + ": malformed vertex");
      if (static_cast<int64_t>(m.vertices.size()) >= kMaxMeshElements)
        return Corrupt(path,
                       where + ": more than " + std::to_string(kMaxMeshElements) + " vertices");
      m.vertices.push_back(v);
    } else if (line[0] == 'f' && (line[1] == ' ' || line[1] == '\t')) {
      auto tok = Tokens(line);
      poly.clear();
      for (size_t k = 1; k < tok.size(); ++k) {
        std::string_view t = tok[k];
        const size_t slash = t.find('/');
        if (slash != std::string_view::npos) t = t.substr(0, slash);  // v/vt/vn: keep v
        int64_t idx = 0;
        if (!ParseInt64(t, &idx) || idx == 0)
          return Corrupt(path, where + ": malformed face index \"" + std::string(tok[k]) + "\"");
        // OBJ indices are 1-based; negative ones count back from the last vertex read.
        const int64_t zero_based =
            idx > 0 ? idx - 1 : static_cast<int64_t>(m.vertices.size()) + idx;
        if (zero_based < 0 || zero_based >= static_cast<int64_t>(m.vertices.size()))
          return Corrupt(path, where + ": face index " + std::to_string(idx) + " out of range (" +
                                   std::to_string(m.vertices.size()) + " vertices so far)");
        poly.push_back(static_cast<int>(zero_based));
      }
      if (poly.size() < 3) return Corrupt(path, where + ": face with fewer than 3 vertices");
      if (static_cast<int64_t>(m.faces.size() + poly.size()) > kMaxMeshElements)
        return Corrupt(path, where + ": more than " + std::to_string(kMaxMeshElements) + " faces");
      AddPolygon(poly, &m);
    }
    // vt, vn, g, o, s, usemtl, mtllib, l, comments: not needed for geometry.
  }
  return m;
}

// ---------------------------------------------------------------- STL

// Indexes STL's triangle soup: bit-identical coordinates become one vertex.
class VertexMerger {
 public:
  explicit VertexMerger(Mesh* m) : m_(m) {}
  int Add(double x, double y, double z) {
    // -0.0 and 0.0 are the same point.
    std::array<double, 3> v{x + 0.0, y + 0.0, z + 0.0};
    auto [it, inserted] = index_.try_emplace(v, static_cast<int>(m_->vertices.size()));
    if (inserted) m_->vertices.push_back(v);
    return it->second;
  }

 private:
  struct Hash {
    size_t operator()(const std::array<double, 3>& v) const {
      uint64_t h = 1469598103934665603ULL;
      for (double d : v) {
        h ^= std::bit_cast<uint64_t>(d);
        h *= 1099511628211ULL;
        h ^= h >> 29;
      }
      return static_cast<size_t>(h);
    }
  };
  Mesh* m_;
  std::unordered_map<std::array<double, 3>, int, Hash> index_;
};

Result<Mesh> LoadStlBinary(const std::string& path, const std::string& data) {
  if (data.size() < 84)
    return Corrupt(path, "truncated binary STL (shorter than its 84-byte header)");
  uint32_t n = 0;
  std::memcpy(&n, data.data() + 80, 4);
  if constexpr (std::endian::native == std::endian::big) n = ByteSwap(n);
  if (data.size() < 84 + 50ULL * n)
    return Corrupt(path, "truncated binary STL: header says " + std::to_string(n) +
                             " triangles of 50 bytes, the " + std::to_string(data.size()) +
                             "-byte file holds " + std::to_string((data.size() - 84) / 50));
  if (static_cast<int64_t>(n) > kMaxMeshElements)
    return Corrupt(path, "binary STL has " + std::to_string(n) + " triangles, more than the " +
                             std::to_string(kMaxMeshElements) + " a mesh may have");
  Mesh m;
  m.faces.reserve(n);
  VertexMerger merge(&m);
  for (uint32_t i = 0; i < n; ++i) {
    const char* rec = data.data() + 84 + 50ULL * i + 12;  // skip the facet normal
    std::array<int, 3> f{};
    for (int k = 0; k < 3; ++k) {
      float c[3];
      std::memcpy(c, rec + static_cast<ptrdiff_t>(12 * k), 12);
      if constexpr (std::endian::native == std::endian::big) {
        for (float& x : c) x = ByteSwap(x);
      }
      f[k] = merge.Add(c[0], c[1], c[2]);
    }
    m.faces.push_back(f);
  }
  return m;
}

Result<Mesh> LoadStlAscii(const std::string& path, const std::string& data) {
  Mesh m;
  VertexMerger merge(&m);
  std::vector<int> loop;
  bool in_loop = false;
  size_t pos = 0;
  int line_no = 0;
  while (pos < data.size()) {
    size_t e = data.find('\n', pos);
    if (e == std::string::npos) e = data.size();
    auto tok = Tokens(std::string_view(data).substr(pos, e - pos));
    pos = e + 1;
    ++line_no;
    if (tok.empty()) continue;
    const std::string where = "line " + std::to_string(line_no);
    if (tok[0] == "outer") {
      in_loop = true;
      loop.clear();
    } else if (tok[0] == "vertex") {
      double x, y, z;
      if (!in_loop || tok.size() != 4 || !ParseDouble(tok[1], &x) || !ParseDouble(tok[2], &y) ||
          !ParseDouble(tok[3], &z))
        return Corrupt(path, where + ": malformed vertex");
      loop.push_back(merge.Add(x, y, z));
    } else if (tok[0] == "endloop") {
      if (loop.size() < 3) return Corrupt(path, where + ": facet with fewer than 3 vertices");
      AddPolygon(loop, &m);
      in_loop = false;
    }
  }
  if (in_loop) return Corrupt(path, "truncated ASCII STL (facet not closed)");
  return m;
}

Result<Mesh> LoadStl(const std::string& path, const std::string& data) {
  // Binary files may also begin with "solid"; the size check decides.
  if (data.size() >= 84) {
    uint32_t n = 0;
    std::memcpy(&n, data.data() + 80, 4);
    if constexpr (std::endian::native == std::endian::big) n = ByteSwap(n);
    if (data.size() == 84 + 50ULL * n) return LoadStlBinary(path, data);
  }
  if (data.compare(0, 5, "solid") == 0 && data.find("facet") != std::string::npos)
    return LoadStlAscii(path, data);
  return LoadStlBinary(path, data);
}

}  // namespace

bool UnitToMm(const std::string& unit, double* factor) {
  if (unit == "mm")
    *factor = 1.0;
  else if (unit == "cm")
    *factor = 10.0;
  else if (unit == "m")
    *factor = 1000.0;
  else
    return false;
  return true;
}

Result<Mesh> LoadMesh(const std::string& path, const std::string& unit) {
  double scale = 1.0;
  if (!UnitToMm(unit, &scale))
    return MakeError(ErrorClass::kInvalidArgument,
                     "mesh unit \"" + unit + "\" is not known; use mm, cm or m");
  const size_t dot = path.find_last_of('.');
  const size_t slash = path.find_last_of('/');
  const std::string ext = (dot == std::string::npos || (slash != std::string::npos && dot < slash))
                              ? ""
                              : Lower(path.substr(dot + 1));
  if (ext != "ply" && ext != "obj" && ext != "stl")
    return MakeError(
        ErrorClass::kInvalidArgument,
        "mesh file " + path + " has unknown extension \"" + ext + "\"; use .ply, .obj or .stl");
  {
    std::error_code ec;
    const auto size = std::filesystem::file_size(path, ec);
    if (!ec && size > kMaxMeshFileBytes) {
      return Corrupt(
          path, "is " + std::to_string(size) + " bytes, more than the " +
                    std::to_string(kMaxMeshFileBytes >> 20) +
                    " MiB a mesh file may have (a rock's mesh is a few MB): decimate it first");
    }
  }
  Result<std::string> data = ReadFile(path);
  if (!data) {
    Error e = data.error();
    e.message = "cannot read mesh file " + path + ": " + e.message;
    return e;
  }
  Result<Mesh> r = ext == "ply"   ? LoadPly(path, *data)
                   : ext == "obj" ? LoadObj(path, *data)
                                  : LoadStl(path, *data);
  if (!r) return r;
  Mesh& m = *r;
  if (m.faces.empty()) return Corrupt(path, "has no faces");
  for (size_t i = 0; i < m.vertices.size(); ++i) {
    for (double& c : m.vertices[i]) {
      const double raw = c;
      c *= scale;
      if (!std::isfinite(c) || std::abs(c) > kMaxMeshCoordinateMm) {
        char v[64];
        std::snprintf(v, sizeof v, "%g", raw);
        return Corrupt(
            path,
            "vertex " + std::to_string(i) + " has coordinate " + v + " " + unit + ": " +
                (std::isfinite(c) ? "farther than 10 km from the origin" : "not a finite number") +
                "; a rock's mesh must have finite coordinates near the origin");
      }
    }
  }
  return r;
}

namespace {

Status CheckForSave(const Mesh& mesh, const std::string& path, const VertexColors* colors) {
  for (const auto& f : mesh.faces) {
    for (int i : f) {
      if (i < 0 || i >= static_cast<int>(mesh.vertices.size())) {
        return MakeError(ErrorClass::kInvalidArgument,
                         "cannot save mesh " + path + ": face index out of range");
      }
    }
  }
  if (colors && colors->size() != mesh.vertices.size()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "cannot save mesh " + path + ": " + std::to_string(colors->size()) +
                         " colours for " + std::to_string(mesh.vertices.size()) + " vertices");
  }
  return OkStatus();
}

template <typename T>
void PutLe(char*& p, T v) {
  if constexpr (std::endian::native == std::endian::big) v = ByteSwap(v);
  std::memcpy(p, &v, sizeof(v));
  p += sizeof(v);
}

}  // namespace

Status SaveMeshPly(const Mesh& mesh, const std::string& path, const VertexColors* colors) {
  if (Status s = CheckForSave(mesh, path, colors); !s.ok()) return s;
  std::string out =
      "ply\nformat binary_little_endian 1.0\ncomment aggscan, units: mm\nelement vertex " +
      std::to_string(mesh.vertices.size()) +
      "\nproperty double x\nproperty double y\nproperty double z\n" +
      (colors ? "property uchar red\nproperty uchar green\nproperty uchar blue\n" : "") +
      "element face " + std::to_string(mesh.faces.size()) +
      "\nproperty list uchar int vertex_indices\nend_header\n";
  const size_t header = out.size();
  const size_t vbytes = 24 + (colors ? 3 : 0);
  out.resize(header + mesh.vertices.size() * vbytes + mesh.faces.size() * 13);
  char* p = out.data() + header;
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    for (double c : mesh.vertices[i]) PutLe(p, c);
    if (colors) {
      for (uint8_t c : (*colors)[i]) *p++ = static_cast<char>(c);
    }
  }
  for (const auto& f : mesh.faces) {
    *p++ = 3;
    for (int i : f) PutLe(p, static_cast<int32_t>(i));
  }
  return WriteFileAtomic(path, std::string_view(out));
}

Status SaveMeshObj(const Mesh& mesh, const std::string& path, const VertexColors* colors) {
  if (Status s = CheckForSave(mesh, path, colors); !s.ok()) return s;
  std::string out = "# aggscan mesh, units: mm\n";
  out.reserve(mesh.vertices.size() * 60 + mesh.faces.size() * 24);
  char line[160];
  for (size_t i = 0; i < mesh.vertices.size(); ++i) {
    const auto& v = mesh.vertices[i];
    int n;
    if (colors) {
      const auto& c = (*colors)[i];
      n = std::snprintf(line, sizeof line, "v %.6f %.6f %.6f %.4f %.4f %.4f\n", v[0], v[1], v[2],
                        c[0] / 255.0, c[1] / 255.0, c[2] / 255.0);
    } else {
      n = std::snprintf(line, sizeof line, "v %.6f %.6f %.6f\n", v[0], v[1], v[2]);
    }
    out.append(line, static_cast<size_t>(n));
  }
  for (const auto& f : mesh.faces) {
    const int n = std::snprintf(line, sizeof line, "f %d %d %d\n", f[0] + 1, f[1] + 1, f[2] + 1);
    out.append(line, static_cast<size_t>(n));
  }
  return WriteFileAtomic(path, std::string_view(out));
}

Status SaveMeshStl(const Mesh& mesh, const std::string& path) {
  if (Status s = CheckForSave(mesh, path, nullptr); !s.ok()) return s;
  std::string out(80, ' ');
  const std::string title = "aggscan mesh, units: mm";
  std::memcpy(out.data(), title.data(), title.size());
  out.resize(84 + mesh.faces.size() * 50);
  char* p = out.data() + 80;
  PutLe(p, static_cast<uint32_t>(mesh.faces.size()));
  for (const auto& f : mesh.faces) {
    const auto& a = mesh.vertices[f[0]];
    const auto& b = mesh.vertices[f[1]];
    const auto& c = mesh.vertices[f[2]];
    const double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
    const double w[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    double n[3] = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    for (double& x : n) x = len > 0 ? x / len : 0;
    for (double x : n) PutLe(p, static_cast<float>(x));
    for (const auto* v : {&a, &b, &c})
      for (double x : *v) PutLe(p, static_cast<float>(x));
    PutLe(p, static_cast<uint16_t>(0));
  }
  return WriteFileAtomic(path, std::string_view(out));
}

}  // namespace aggscan
