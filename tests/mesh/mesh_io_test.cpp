// Mesh readers: a cube written by the test in every supported format and
// variant, error cases, the PLY writer, and the shared public meshes (skipped
// when ../shared/data is absent).
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "common/mesh.h"
#include "common/mesh_props.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

// Side-2 cube, outward counter-clockwise quads.
const std::vector<std::array<double, 3>> kCubeV = {{0, 0, 0}, {2, 0, 0}, {2, 2, 0}, {0, 2, 0},
                                                   {0, 0, 2}, {2, 0, 2}, {2, 2, 2}, {0, 2, 2}};
const std::vector<std::array<int, 4>> kCubeQuads = {{0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4},
                                                    {2, 3, 7, 6}, {0, 4, 7, 3}, {1, 2, 6, 5}};

class MeshIoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ =
        fs::path(::testing::TempDir()) /
        ("mesh_io_" + std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  std::string Write(const std::string& name, const std::string& bytes) {
    const std::string p = (dir_ / name).string();
    std::ofstream(p, std::ios::binary) << bytes;
    return p;
  }

  fs::path dir_;
};

template <typename T>
void Put(std::string* s, T v, bool big_endian = false) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  if (big_endian != (std::endian::native == std::endian::big)) std::reverse(b, b + sizeof(T));
  s->append(b, sizeof(T));
}

void ExpectCube(const Result<Mesh>& r, double scale = 1.0) {
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->vertices.size(), 8u);
  EXPECT_EQ(r->faces.size(), 12u);
  EXPECT_NEAR(SignedVolume(*r), 8.0 * scale * scale * scale, 1e-9);
  EXPECT_NEAR(SurfaceArea(*r), 24.0 * scale * scale, 1e-9);
}

std::string AsciiPlyCube() {
  std::string s =
      "ply\r\nformat ascii 1.0\r\ncomment made by the test\r\nelement vertex 8\r\nproperty float "
      "x\r\n"
      "property float y\r\nproperty float z\r\nproperty float nx\r\nproperty uchar red\r\n"
      "element face 6\r\nproperty list uchar int vertex_indices\r\nproperty int flags\r\n"
      "element edge 1\r\nproperty int vertex1\r\nproperty int vertex2\r\nend_header\r\n";
  for (const auto& v : kCubeV)
    s += std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) +
         " 0.5 255\n";
  for (const auto& q : kCubeQuads)
    s += "4 " + std::to_string(q[0]) + " " + std::to_string(q[1]) + " " + std::to_string(q[2]) +
         " " + std::to_string(q[3]) + " 7\n";
  s += "0 1\n";
  return s;
}

TEST_F(MeshIoTest, PlyAsciiWithExtraPropertiesAndQuads) {
  ExpectCube(LoadMesh(Write("cube.ply", AsciiPlyCube()), "mm"));
}

TEST_F(MeshIoTest, PlyBinaryLittleEndianDoubleUintWithTrailingElement) {
  std::string s =
      "ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty double x\nproperty double "
      "y\n"
      "property double z\nproperty double nx\nproperty uchar red\nelement face 12\n"
      "property list uchar uint vertex_indices\nelement material 1\nproperty uchar "
      "ambient\nend_header\n";
  for (const auto& v : kCubeV) {
    for (double c : v) Put<double>(&s, c);
    Put<double>(&s, 0.25);
    Put<uint8_t>(&s, 9);
  }
  for (const auto& q : kCubeQuads) {
    for (auto t : {std::array<int, 3>{q[0], q[1], q[2]}, std::array<int, 3>{q[0], q[2], q[3]}}) {
      Put<uint8_t>(&s, 3);
      for (int i : t) Put<uint32_t>(&s, static_cast<uint32_t>(i));
    }
  }
  Put<uint8_t>(&s, 1);
  ExpectCube(LoadMesh(Write("cube.PLY", s), "mm"));
}

TEST_F(MeshIoTest, PlyBinaryBigEndianFloatIntCount) {
  std::string s =
      "ply\nformat binary_big_endian 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
      "property float z\nelement face 6\nproperty list int int vertex_indices\nend_header\n";
  for (const auto& v : kCubeV)
    for (double c : v) Put<float>(&s, static_cast<float>(c), true);
  for (const auto& q : kCubeQuads) {
    Put<int32_t>(&s, 4, true);
    for (int i : q) Put<int32_t>(&s, i, true);
  }
  ExpectCube(LoadMesh(Write("cube.ply", s), "cm"), 10.0);
}

TEST_F(MeshIoTest, ObjAllFaceForms) {
  std::string s = "# cube\nmtllib x.mtl\no cube\n";
  for (const auto& v : kCubeV)
    s += "v " + std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) +
         "\n";
  s += "vt 0 0\nvn 0 0 1\ns off\n";
  // Each quad with a different index form; the last ones with negative indices.
  s += "f 1 4 3 2\n";
  s += "f 5/1 6/1 7/1 8/1\n";
  s += "f 1/1/1 2/1/1 6/1/1 5/1/1\n";
  s += "f 3//1 4//1 8//1 7//1\n";
  s += "f -8 -4 -1 -5\n";          // 1 5 8 4
  s += "f -7/1 -6/1 -2/1 -3/1\n";  // 2 3 7 6
  ExpectCube(LoadMesh(Write("cube.obj", s), "mm"));
}

TEST_F(MeshIoTest, StlAsciiAndBinaryAreIndexed) {
  std::string a = "solid cube\n";
  std::string b(80, ' ');
  Put<uint32_t>(&b, 12);
  for (const auto& q : kCubeQuads) {
    for (auto t : {std::array<int, 3>{q[0], q[1], q[2]}, std::array<int, 3>{q[0], q[2], q[3]}}) {
      a += " facet normal 0 0 0\n  outer loop\n";
      for (int k = 0; k < 3; ++k)
        a += "   vertex " + std::to_string(kCubeV[t[k]][0]) + " " +
             std::to_string(kCubeV[t[k]][1]) + " " + std::to_string(kCubeV[t[k]][2]) + "\n";
      a += "  endloop\n endfacet\n";
      for (int k = 0; k < 3; ++k) Put<float>(&b, 0.0f);
      for (int k = 0; k < 3; ++k)
        for (double c : kCubeV[t[k]]) Put<float>(&b, static_cast<float>(c));
      Put<uint16_t>(&b, 0);
    }
  }
  a += "endsolid cube\n";
  ExpectCube(LoadMesh(Write("cube_ascii.stl", a), "mm"));
  // A binary header that starts with "solid" must still be read as binary.
  b.replace(0, 5, "solid");
  ExpectCube(LoadMesh(Write("cube_bin.stl", b), "m"), 1000.0);
}

TEST_F(MeshIoTest, SaveThenLoadRoundTrip) {
  Mesh m;
  m.vertices = kCubeV;
  for (const auto& q : kCubeQuads) {
    m.faces.push_back({q[0], q[1], q[2]});
    m.faces.push_back({q[0], q[2], q[3]});
  }
  m.vertices[6] = {2.000000001, 2, 2};
  const std::string p = (dir_ / "out.ply").string();
  ASSERT_TRUE(SaveMeshPly(m, p).ok());
  auto r = LoadMesh(p, "mm");
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->vertices, m.vertices);
  EXPECT_EQ(r->faces, m.faces);
}

TEST_F(MeshIoTest, ColouredPlyObjAndStlRoundTrip) {
  Mesh m;
  m.vertices = kCubeV;
  for (const auto& q : kCubeQuads) {
    m.faces.push_back({q[0], q[1], q[2]});
    m.faces.push_back({q[0], q[2], q[3]});
  }
  VertexColors colors;
  for (size_t i = 0; i < m.vertices.size(); ++i) colors.push_back({uint8_t(i * 30), 7, 255});
  const std::string ply = (dir_ / "c.ply").string(), obj = (dir_ / "c.obj").string(),
                    stl = (dir_ / "c.stl").string();
  ASSERT_TRUE(SaveMeshPly(m, ply, &colors));
  ASSERT_TRUE(SaveMeshObj(m, obj, &colors));
  ASSERT_TRUE(SaveMeshStl(m, stl));
  for (const std::string& p : {ply, obj}) {
    auto r = LoadMesh(p, "mm");
    ASSERT_TRUE(r.ok()) << p << ": " << r.error().ToString();
    EXPECT_EQ(r->faces, m.faces) << p;
    EXPECT_EQ(r->vertices, m.vertices) << p;
  }
  // STL is a triangle soup in float: the loader welds it back to 8 vertices.
  ExpectCube(LoadMesh(stl, "mm"));
  EXPECT_EQ(std::filesystem::file_size(stl), 84u + 12u * 50u);
  // The PLY carries the colours after the coordinates.
  std::ifstream in(ply, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  EXPECT_NE(bytes.find("property uchar red"), std::string::npos);
  const size_t body = bytes.find("end_header\n") + 11;
  EXPECT_EQ(static_cast<uint8_t>(bytes[body + 27 + 24]), 30);  // vertex 1's red
  // Wrong colour count is refused.
  colors.pop_back();
  EXPECT_FALSE(SaveMeshPly(m, ply, &colors));
  EXPECT_FALSE(SaveMeshObj(m, obj, &colors));
}

TEST_F(MeshIoTest, Units) {
  double f = 0;
  EXPECT_TRUE(UnitToMm("mm", &f));
  EXPECT_EQ(f, 1.0);
  EXPECT_TRUE(UnitToMm("cm", &f));
  EXPECT_EQ(f, 10.0);
  EXPECT_TRUE(UnitToMm("m", &f));
  EXPECT_EQ(f, 1000.0);
  EXPECT_FALSE(UnitToMm("furlong", &f));
  auto r = LoadMesh(Write("cube.ply", AsciiPlyCube()), "inch");
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
}

TEST_F(MeshIoTest, ErrorsNameTheFileAndTheDefect) {
  auto expect_err = [](const Result<Mesh>& r, ErrorClass cls, const std::string& path,
                       const std::string& what) {
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().cls, cls) << r.error().ToString();
    EXPECT_NE(r.error().message.find(path), std::string::npos) << r.error().message;
    EXPECT_NE(r.error().message.find(what), std::string::npos) << r.error().message;
  };
  const std::string xyz = Write("rock.xyz", "1 2 3\n");
  expect_err(LoadMesh(xyz, "mm"), ErrorClass::kInvalidArgument, xyz, "unknown extension");

  const std::string missing = (dir_ / "missing.ply").string();
  expect_err(LoadMesh(missing, "mm"), ErrorClass::kNotFound, missing, "cannot read");

  std::string ply = AsciiPlyCube();
  const std::string trunc = Write("trunc.ply", ply.substr(0, ply.size() - 40));
  expect_err(LoadMesh(trunc, "mm"), ErrorClass::kCorrupt, trunc, "truncated");

  std::string bin =
      "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
      "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
  for (int i = 0; i < 9; ++i) Put<float>(&bin, static_cast<float>(i % 3 == 0));
  const std::string bin_trunc = Write("bin_trunc.ply", bin + std::string("\x03\x00\x00", 3));
  expect_err(LoadMesh(bin_trunc, "mm"), ErrorClass::kCorrupt, bin_trunc, "truncated in face 0");
  std::string bad_index = bin;
  Put<uint8_t>(&bad_index, 3);
  for (int i : {0, 1, 3}) Put<int32_t>(&bad_index, i);
  const std::string range = Write("range.ply", bad_index);
  expect_err(LoadMesh(range, "mm"), ErrorClass::kCorrupt, range, "out of range");

  const std::string obj_range = Write("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n");
  expect_err(LoadMesh(obj_range, "mm"), ErrorClass::kCorrupt, obj_range, "out of range");
  const std::string obj_neg = Write("neg.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n");
  expect_err(LoadMesh(obj_neg, "mm"), ErrorClass::kCorrupt, obj_neg, "out of range");
  const std::string no_faces = Write("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n");
  expect_err(LoadMesh(no_faces, "mm"), ErrorClass::kCorrupt, no_faces, "no faces");
  const std::string stl =
      Write("short.stl",
            std::string(80, 'x') + std::string("\x05\x00\x00\x00", 4) + std::string(60, '\0'));
  expect_err(LoadMesh(stl, "mm"), ErrorClass::kCorrupt, stl, "truncated");
  const std::string not_ply = Write("text.ply", "hello\n");
  expect_err(LoadMesh(not_ply, "mm"), ErrorClass::kCorrupt, not_ply, "not a PLY");

  // Counts the file cannot hold are refused before anything is allocated.
  std::string claims = bin;
  claims.replace(claims.find("vertex 3"), 8, "vertex 9223372036854775807");
  const std::string absurd = Write("absurd.ply", claims);
  expect_err(LoadMesh(absurd, "mm"), ErrorClass::kCorrupt, absurd,
             "element vertex has 9223372036854775807 rows of at least 12 bytes each, but the file "
             "holds only 36 "
             "bytes after its header");
  // A binary STL whose one triangle has a NaN corner.
  std::string nan_stl(80, ' ');
  Put<uint32_t>(&nan_stl, 1);
  for (int i = 0; i < 12; ++i)
    Put<float>(&nan_stl, i == 4 ? std::nanf("") : static_cast<float>(i % 3 == 0));
  nan_stl.append(2, '\0');
  const std::string pnan = Write("nan.stl", nan_stl);
  expect_err(LoadMesh(pnan, "mm"), ErrorClass::kCorrupt, pnan,
             "vertex 0 has coordinate nan mm: not a finite number");
}

// ---------------------------------------------------------------- shared data

fs::path Meshes() { return fs::path(AGGSCAN_SHARED_DATA) / "meshes"; }

#define SKIP_WITHOUT_SHARED_DATA()                                                     \
  do {                                                                                 \
    if (!fs::is_directory(Meshes())) GTEST_SKIP() << "no shared data at " << Meshes(); \
  } while (0)

struct Expected {
  const char* file;
  const char* unit;
  size_t vertices;  // 0 = do not check
  size_t faces;
};

TEST(MeshSharedData, LoadsEveryPublicMesh) {
  SKIP_WITHOUT_SHARED_DATA();
  const Expected cases[] = {
      {"shape_toolbox/Sphere_R_1.stl", "mm", 10242, 20480},  // indexed by exact merging
      {"shape_toolbox/Tetrahedron.stl", "mm", 0, 256},
      {"shape_toolbox/Hexahedron.stl", "mm", 0, 768},
      {"epfl_stones/low_res_0.ply", "m", 162, 320},
      {"epfl_stones/073ac15d-8ad2-4758-9c8c-5f8339b97edb_Mesh.ply", "mm", 13491, 26978},
      {"epfl_stones/remeshed_high_res_A13.ply", "m", 273, 500},
      {"ashlar_stones/846.obj", "m", 2502, 0},
      {"classic/spot.obj", "mm", 2930, 0},
      {"classic/stanford-bunny.obj", "mm", 35947, 0},
      {"classic/cow.obj", "mm", 2903, 0},
  };
  for (const Expected& c : cases) {
    SCOPED_TRACE(c.file);
    auto r = LoadMesh((Meshes() / c.file).string(), c.unit);
    ASSERT_TRUE(r.ok()) << r.error().ToString();
    if (c.vertices) {
      EXPECT_EQ(r->vertices.size(), c.vertices);
    }
    if (c.faces) {
      EXPECT_EQ(r->faces.size(), c.faces);
    }
    EXPECT_GT(r->faces.size(), 0u);
  }
}

TEST(MeshSharedData, ClosedStonesHavePositiveVolumeInMm) {
  SKIP_WITHOUT_SHARED_DATA();
  for (const char* f :
       {"ashlar_stones/846.obj", "ashlar_stones/923.obj", "ashlar_stones/1050.obj"}) {
    SCOPED_TRACE(f);
    auto r = LoadMesh((Meshes() / f).string(), "m");
    ASSERT_TRUE(r.ok()) << r.error().ToString();
    // ~1 m stones: well over 1e7 mm^3, and under a 2 m cube.
    const double v = std::fabs(SignedVolume(*r));
    EXPECT_GT(v, 1e7);
    EXPECT_LT(v, 8e9);
  }
}

}  // namespace
}  // namespace aggscan
