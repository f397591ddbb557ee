// [calibration] and the sim's charuco fields: defaults valid, bad values named
// with their line, and the effective config round-trips.
#include <gtest/gtest.h>

#include "config/config.h"

namespace aggscan {
namespace {

std::vector<ConfigProblem> Problems(const std::string& toml) {
  std::vector<ConfigProblem> p;
  (void)LoadConfigString(toml, "t.toml", &p);
  return p;
}

// Exactly one problem, for `key` on `line`, whose message contains `text`.
void ExpectOne(const std::string& toml, const std::string& key, int line, const std::string& text) {
  const auto p = Problems(toml);
  ASSERT_EQ(p.size(), 1u) << toml << (p.empty() ? "" : "\nfirst: " + p[0].ToString());
  EXPECT_EQ(p[0].key, key) << p[0].ToString();
  EXPECT_EQ(p[0].line, line) << p[0].ToString();
  EXPECT_NE(p[0].message.find(text), std::string::npos) << p[0].ToString();
}

TEST(CalibrationConfig, DefaultsFitTheDisc) {
  Config c;
  EXPECT_EQ(c.calibration.dictionary, "DICT_5X5_100");
  EXPECT_EQ(c.calibration.squares_x, 7);
  EXPECT_EQ(c.calibration.squares_y, 5);
  EXPECT_TRUE(Problems("").empty());
  EXPECT_TRUE(
      Problems("[calibration]\nsquares_x = 9\nsquares_y = 6\nsquare_mm = 25.0\nmarker_mm = 18.0\n")
          .empty());
}

TEST(CalibrationConfig, BadValuesAreNamedWithTheirLine) {
  ExpectOne("[calibration]\ndictionary = \"DICT_9X9_1\"\n", "calibration.dictionary", 2,
            "must be one of");
  ExpectOne("[calibration]\nsquares_x = 2\n", "calibration.squares_x", 2, "must be in 3..40");
  ExpectOne("[calibration]\n\nsquare_mm = -3.0\n", "calibration.square_mm", 3, "must be > 0");
  ExpectOne("[calibration]\nmarker_mm = 30.0\n", "calibration.marker_mm", 2,
            "smaller than calibration.square_mm");
  ExpectOne(
      "[calibration]\nsquares_x = 12\nsquares_y = 9\nsquare_mm = 15.0\nmarker_mm = "
      "11.0\ndictionary = \"DICT_4X4_50\"\n",
      "calibration.dictionary", 6, "needs 54");
  ExpectOne("[calibration]\nsquare_mm = 45.0\n", "calibration.square_mm", 2,
            "does not fit on the 305 mm turntable");
  ExpectOne("[calibration]\nsquare_x = 7\n", "calibration.square_x", 2,
            "did you mean calibration.squares_x?");
  ExpectOne("[calibration]\nsquares_y = \"five\"\n", "calibration.squares_y", 2,
            "expected an integer");
}

TEST(CalibrationConfig, CharucoSceneNeedsTheBoardOnTheDisc) {
  ExpectOne("[sim]\nscene = \"charuco\"\n", "sim.board_image", 0, "aggscan calibrate board");
  ExpectOne("[sim]\nscene = \"table\"\n", "sim.scene", 2, "rock | charuco");
  ExpectOne("[sim]\nscene = \"charuco\"\nboard_image = \"b.pgm\"\nboard_x_mm = 40.0\n",
            "sim.board_x_mm", 4, "beyond the disc edge");
  EXPECT_TRUE(Problems("[sim]\nscene = \"charuco\"\nboard_image = \"b.pgm\"\nboard_x_mm = "
                       "6.0\nboard_yaw_deg = 30.0\n")
                  .empty());
}

TEST(CalibrationConfig, EffectiveConfigRoundTrips) {
  Config c;
  c.calibration.squares_x = 8;
  c.calibration.square_mm = 25.5;
  c.calibration.dictionary = "DICT_6X6_250";
  c.sim.scene = "charuco";
  c.sim.board_image = "/tmp/b.pgm";
  c.sim.board_yaw_deg = -20;
  std::vector<ConfigProblem> p;
  auto back = LoadConfigString(ConfigToToml(c), "printed.toml", &p);
  ASSERT_TRUE(back) << (p.empty() ? back.error().ToString() : p[0].ToString());
  EXPECT_EQ(*back, c);
}

}  // namespace
}  // namespace aggscan
