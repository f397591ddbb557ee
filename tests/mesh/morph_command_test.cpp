// `aggscan morph`: the 3D morphology command on analytic and real meshes, and
// the refusal of open / non-manifold meshes with the defect named.
#include "cli/morph_command.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "common/mesh_check.h"
#include "drivers/sim/world.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

const std::string kData = AGGSCAN_SHARED_DATA;

struct MorphRun {
  int rc;
  std::string out, err;
};

MorphRun Morph(const std::string& path, const std::string& unit = "mm") {
  std::ostringstream out, err;
  const int rc = RunMorphCommand(path, unit, /*json=*/true, out, err);
  return {rc, out.str(), err.str()};
}

Mesh Cube() {
  Mesh m;
  m.vertices = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0},
                {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
  m.faces = {{0, 2, 1}, {0, 3, 2}, {4, 5, 6}, {4, 6, 7}, {0, 1, 5}, {0, 5, 4},
             {1, 2, 6}, {1, 6, 5}, {2, 3, 7}, {2, 7, 6}, {3, 0, 4}, {3, 4, 7}};
  return m;
}

TEST(MeshTopology, ClosedCubeIsClean) {
  const MeshTopology t = AnalyzeTopology(Cube());
  EXPECT_TRUE(t.ClosedManifold()) << t.Defects();
  EXPECT_EQ(t.components, 1u);
  EXPECT_TRUE(CheckClosedManifold(Cube(), "cube").ok());
}

TEST(MeshTopology, EachDefectIsCountedAndNamed) {
  Mesh hole = Cube();
  hole.faces.pop_back();  // one triangle missing: 3 boundary edges
  MeshTopology t = AnalyzeTopology(hole);
  EXPECT_EQ(t.boundary_edges, 3u);
  EXPECT_NE(t.Defects().find("3 boundary edges (holes)"), std::string::npos);

  Mesh flipped = Cube();
  std::swap(flipped.faces[0][1], flipped.faces[0][2]);  // one face turned over: its 3 edges
  t = AnalyzeTopology(flipped);
  EXPECT_EQ(t.misoriented_edges, 3u);
  EXPECT_EQ(t.boundary_edges, 0u);

  Mesh fin = Cube();
  fin.vertices.push_back({0.5, 0.5, -1});
  fin.faces.push_back({0, 2, 8});  // a third face on the diagonal edge 0-2
  t = AnalyzeTopology(fin);
  EXPECT_EQ(t.nonmanifold_edges, 1u);

  Mesh degenerate = Cube();
  degenerate.faces.push_back({1, 1, 2});
  EXPECT_EQ(AnalyzeTopology(degenerate).degenerate_faces, 1u);

  // Two cubes touching at one corner: the shared vertex is pinched.
  Mesh two = Cube();
  for (auto v : Cube().vertices) two.vertices.push_back({v[0] + 1, v[1] + 1, v[2] + 1});
  for (auto f : Cube().faces) {
    std::array<int, 3> g{f[0] + 8, f[1] + 8, f[2] + 8};
    for (int& i : g) i = (i == 8) ? 6 : i;  // second cube's corner 0 is the first's corner 6
    two.faces.push_back(g);
  }
  t = AnalyzeTopology(two);
  EXPECT_EQ(t.nonmanifold_vertices, 1u);
  EXPECT_EQ(t.boundary_edges, 0u);
  Status s = CheckClosedManifold(two, "two-cubes.ply");
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(s.error().message.find("two-cubes.ply"), std::string::npos);
  EXPECT_NE(s.error().message.find("pinched"), std::string::npos);
}

struct Analytic {
  const char* name;
  double v, a, sphericity;
  double box[3];  // expected a, b, c (0 = not checked)
};

class ShapeToolboxMorph : public ::testing::TestWithParam<Analytic> {};

TEST_P(ShapeToolboxMorph, WithinStatedTolerances) {
  const Analytic& e = GetParam();
  const std::string path = kData + "/meshes/shape_toolbox/" + e.name + ".stl";
  if (!fs::exists(path)) GTEST_SKIP() << "shared test data absent: " << path;
  // Read in cm: the unit-size solids become cm-sized, figures in mm.
  MorphRun r = Morph(path, "cm");
  ASSERT_EQ(r.rc, 0) << r.err;
  json j = json::parse(r.out);
  EXPECT_TRUE(j["watertight"].get<bool>());
  // Tessellated curved solids sit 0.05-0.1 % below the analytic V and A: 0.2 %.
  EXPECT_NEAR(j["volume_mm3"].get<double>() / 1000.0, e.v, e.v * 0.002);
  EXPECT_NEAR(j["surface_area_mm2"].get<double>() / 100.0, e.a, e.a * 0.002);
  EXPECT_NEAR(j["sphericity"].get<double>(), e.sphericity, 0.002);
  if (e.box[0] > 0) {
    const char* keys[3] = {"a_mm", "b_mm", "c_mm"};
    for (int i = 0; i < 3; ++i)
      EXPECT_NEAR(j[keys[i]].get<double>() / 10.0, e.box[i], e.box[i] * 0.005) << keys[i];
    EXPECT_NEAR(j["fer_3d"].get<double>(), e.box[2] / e.box[0], 0.01 * e.box[2] / e.box[0]);
    // Every box near the minimum of these solids has the same sides: a, b, c
    // are well-conditioned (compare seed 17 in min_box_sim_test).
    EXPECT_FALSE(j["box_ill_conditioned"].get<bool>()) << j["second_box"].dump();
  }
}

// Values from ../shared/data/README.md (analytic).
INSTANTIATE_TEST_SUITE_P(
    Analytic, ShapeToolboxMorph,
    ::testing::Values(Analytic{"Sphere_R_1", 4.188790, 12.566371, 1.0, {2, 2, 2}},
                      Analytic{"Ellipsoid_R_1_1_2", 8.377580, 21.478435, 0.92874, {2, 2, 4}},
                      Analytic{"Ellipsoid_R_1_2_2", 16.755161, 34.687531, 0.91287, {2, 4, 4}},
                      Analytic{"Ellipsoid_R_1_2_3", 25.132741, 48.8822, 0.84884, {2, 4, 6}},
                      Analytic{"Tetrahedron", 1.0 / 3.0, 3.464102, 0.67114, {0, 0, 0}},
                      Analytic{"Hexahedron", 1.0, 6.0, 0.80600, {1, 1, 1}},
                      Analytic{"Octahedron", 1.0 / 6.0, 1.732051, 0.84558, {0, 0, 0}},
                      Analytic{"Dodecahedron", 0.427051, 3.012171, 0.91045, {0, 0, 0}},
                      Analytic{"Icosahedron", 0.515028, 3.307923, 0.93933, {0, 0, 0}}),
    [](const ::testing::TestParamInfo<Analytic>& i) { return std::string(i.param.name); });

struct Dirty {
  const char* file;
  const char* defect;  // must appear in the message
};

class DirtyMeshes : public ::testing::TestWithParam<Dirty> {};

TEST_P(DirtyMeshes, RefusedWithTheDefectNamed) {
  const std::string path = kData + "/meshes/" + GetParam().file;
  if (!fs::exists(path)) GTEST_SKIP() << "shared test data absent: " << path;
  MorphRun r = Morph(path, "m");
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find(GetParam().defect), std::string::npos) << r.err;
  EXPECT_NE(r.err.find(GetParam().file), std::string::npos) << r.err;
  json j = json::parse(r.out);
  EXPECT_FALSE(j["watertight"].get<bool>());
}

INSTANTIATE_TEST_SUITE_P(
    Data, DirtyMeshes,
    ::testing::Values(Dirty{"classic/stanford-bunny.obj", "223 boundary edges (holes)"},
                      Dirty{"classic/cow.obj", "1 non-manifold vertex (pinched)"},
                      Dirty{"epfl_stones/remeshed_high_res_A13.ply", "non-manifold edges"},
                      Dirty{"epfl_stones/remeshed_high_res_A13.ply", "misoriented edges"}));

TEST(MorphCommand, ScannedStonesAreMeasured) {
  const std::string dir = kData + "/meshes/epfl_stones";
  if (!fs::exists(dir)) GTEST_SKIP() << "shared test data absent: " << dir;
  int measured = 0;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.path().extension() != ".ply" ||
        e.path().filename().string().find("A13") != std::string::npos)
      continue;
    MorphRun r = Morph(e.path().string(), "mm");
    ASSERT_EQ(r.rc, 0) << e.path() << ": " << r.err;
    json j = json::parse(r.out);
    EXPECT_GT(j["volume_mm3"].get<double>(), 0);
    EXPECT_LE(j["a_mm"].get<double>(), j["b_mm"].get<double>());
    EXPECT_LE(j["b_mm"].get<double>(), j["c_mm"].get<double>());
    EXPECT_GT(j["sphericity"].get<double>(), 0.5);
    EXPECT_LT(j["sphericity"].get<double>(), 1.0);
    ++measured;
  }
  EXPECT_EQ(measured, 6);  // the 6 closed stones
}

// Procedural rock 17 has three boxes within 0.7 % of one volume (77.9 x
// 108.4 x 155.4, 82.6 x 118.9 x 133.6, 77.8 x 126.4 x 134.2 mm): the text
// says so and lists them, the JSON carries them.
TEST(MorphCommand, IllConditionedBoxesAreListed) {
  const std::string path = (fs::temp_directory_path() / "aggscan_morph_seed17.ply").string();
  ASSERT_TRUE(SaveMeshPly(sim::MakeProceduralRock(17, 0, 20000), path).ok());
  std::ostringstream text, text_err;
  ASSERT_EQ(RunMorphCommand(path, "mm", false, text, text_err), 0) << text_err.str();
  EXPECT_NE(text.str().find("ill-conditioned"), std::string::npos) << text.str();
  EXPECT_NE(text.str().find("118.9"), std::string::npos) << text.str();
  EXPECT_NE(text.str().find("126.4"), std::string::npos) << text.str();
  std::ostringstream out, err;
  ASSERT_EQ(RunMorphCommand(path, "mm", true, out, err), 0) << err.str();
  const json j = json::parse(out.str());
  EXPECT_TRUE(j["box_ill_conditioned"].get<bool>());
  ASSERT_GE(j["near_minimal_boxes"].size(), 2u);
  for (const json& b : j["near_minimal_boxes"]) EXPECT_LE(b["volume_ratio"].get<double>(), 1.01);
  fs::remove(path);
}

TEST(MorphCommand, BadInputIsAClearError) {
  std::ostringstream out, err;
  EXPECT_EQ(RunMorphCommand("/nonexistent/rock.ply", "mm", false, out, err), 2);
  EXPECT_NE(err.str().find("/nonexistent/rock.ply"), std::string::npos) << err.str();
  std::ostringstream out2, err2;
  EXPECT_EQ(RunMorphCommand("x.ply", "inch", false, out2, err2), 2);
  EXPECT_NE(err2.str().find("mm, cm or m"), std::string::npos);
}

}  // namespace
}  // namespace aggscan
