// Quality flags: a sound reconstruction has none; poor masks, a surface
// refined inside the masks' outline, a stitch the silhouettes do not confirm,
// sources that disagree, a loose stitch or scale fit and an open model each
// give a flag whose reason names the figure and the limit. Inputs are shaped as morphology.json's
// quality block, results/stitch.json and surface.json's per-view IoU.
#include "pipeline/worker/quality.h"

#include <gtest/gtest.h>

#include <set>
#include <string>

namespace aggscan {
namespace {

using nlohmann::json;

json SoundQuality() {
  return {{"silhouette_iou_mean", 0.991},
          {"silhouette_iou_min", 0.983},
          {"scale_residual_mm", 0.03},
          {"watertight", true}};
}

json Stitch(double deficit, bool consistent, double rms, double own_deficit = -1) {
  json sil = {{"available", true}, {"deficit", deficit}};
  if (own_deficit >= 0) sil["own_deficit"] = own_deficit;
  return {{"rms_mm", rms},
          {"max_mm", 2 * rms},
          {"stitches",
           {{{"side", 2},
             {"onto_side", 1},
             {"source", "features"},
             {"consistent", consistent},
             {"disagreement_deg", consistent ? 0.1 : 3.4},
             {"disagreement_mm", consistent ? 0.1 : 4.2},
             {"warning", consistent ? "" : "markers and features disagree"},
             {"silhouettes", sil}}}}};
}

std::set<std::string> Codes(const json& flags) {
  std::set<std::string> c;
  for (const json& f : flags) {
    EXPECT_FALSE(f.value("reason", "").empty()) << f.dump();
    c.insert(f.value("code", ""));
  }
  return c;
}

TEST(QualityFlags, SoundReconstructionHasNone) {
  // Figures as the sim rig's own renders give them.
  const json iou = json::array({{{"side", 1}, {"view", 0}, {"iou", 0.99}}});
  EXPECT_TRUE(QualityFlags(SoundQuality(), Stitch(0.0035, true, 0.12), iou).empty());
  // One side: no stitch to judge.
  EXPECT_TRUE(QualityFlags(SoundQuality(), json{{"method", "single-side"}}, iou).empty());
}

TEST(QualityFlags, ShadowedMasksAndAnUnconfirmedStitchAreFlaggedWithTheirFigures) {
  // As measured on a Blender capture whose masks took in the contact shadow.
  json q = SoundQuality();
  q["silhouette_iou_mean"] = 0.876;
  q["silhouette_iou_min"] = 0.773;
  const json iou = json::array(
      {{{"side", 1}, {"view", 3}, {"iou", 0.94}}, {{"side", 2}, {"view", 15}, {"iou", 0.773}}});
  const json flags = QualityFlags(q, Stitch(0.0825, true, 0.39), iou);
  EXPECT_EQ(Codes(flags), (std::set<std::string>{"mask_consistency", "stitch_unconfirmed"}));
  const std::string mask_reason = flags[0]["reason"];
  EXPECT_NE(mask_reason.find("IoU mean 0.876, worst 0.773 at side 2 view 15"), std::string::npos)
      << mask_reason;
  EXPECT_NE(mask_reason.find("results/masks"), std::string::npos) << mask_reason;
  const std::string stitch_reason = flags[1]["reason"];
  EXPECT_NE(stitch_reason.find("by features"), std::string::npos) << stitch_reason;
  EXPECT_NE(stitch_reason.find("0.083 of them uncovered"), std::string::npos) << stitch_reason;
}

TEST(QualityFlags, TheStitchIsJudgedBeyondWhatEachSidesOwnMasksLeaveUncovered) {
  // A Blender capture's figures: shadows in the masks leave 0.027 of them
  // uncovered by each side's own hull; the right stitch leaves 0.035.
  const json iou = json::array({{{"side", 1}, {"view", 0}, {"iou", 0.99}}});
  EXPECT_TRUE(QualityFlags(SoundQuality(), Stitch(0.035, true, 0.46, 0.0265), iou).empty());
  const json flags = QualityFlags(SoundQuality(), Stitch(0.060, true, 0.46, 0.0265), iou);
  EXPECT_EQ(Codes(flags), std::set<std::string>{"stitch_unconfirmed"});
  const std::string reason = flags[0]["reason"];
  EXPECT_NE(reason.find("leaves 0.060 of them uncovered, 0.034 more than each side's own"),
            std::string::npos)
      << reason;
}

TEST(QualityFlags, ARefinementThatTakesInTheOutlineIsFlagged) {
  // Sim captures lose 0.3-0.8 % of the hull's outline to the refinement and
  // the smoothing; a Blender capture of a wet stone lost 2.00 % (worst view
  // 4.29 %) even with its true masks, and came out 1.5 % low in volume.
  json q = SoundQuality();
  q["outline_loss_mean"] = 0.0066;
  q["outline_loss_max"] = 0.0106;
  const json iou = json::array({{{"side", 1}, {"view", 0}, {"iou", 0.99}}});
  EXPECT_TRUE(QualityFlags(q, Stitch(0.0035, true, 0.12), iou).empty());
  q["outline_loss_mean"] = 0.0200;
  q["outline_loss_max"] = 0.0429;
  const json flags = QualityFlags(q, Stitch(0.0035, true, 0.12), iou);
  ASSERT_EQ(flags.size(), 1u) << flags.dump();
  EXPECT_EQ(Codes(flags), std::set<std::string>{"outline_loss"});
  const std::string reason = flags[0]["reason"];
  EXPECT_NE(reason.find("no longer covers 2.00 % of the carved hull's silhouettes on average "
                        "(worst view 4.29 %; limit 1.20 %)"),
            std::string::npos)
      << reason;
  EXPECT_NE(reason.find("--surface hull"), std::string::npos) << reason;
  // Masks that disagree with the model: a Blender capture whose masks took
  // in the contact shadow in every view lost 2.29 % of the hull's outline to
  // a refinement that was right (volume -0.38 %, the hull alone +5.75 %).
  // The masks' flag says what is doubtful; the outline's would mislead.
  json shadowed = q;
  shadowed["silhouette_iou_mean"] = 0.887;
  shadowed["silhouette_iou_min"] = 0.812;
  EXPECT_EQ(Codes(QualityFlags(shadowed, Stitch(0.0035, true, 0.12), iou)),
            std::set<std::string>{"mask_consistency"});
  // A surface without per-view figures (null) or a record written before
  // they were measured (absent): nothing to judge.
  q["outline_loss_mean"] = nullptr;
  q["outline_loss_max"] = nullptr;
  EXPECT_TRUE(QualityFlags(q, Stitch(0.0035, true, 0.12), iou).empty());
  q.erase("outline_loss_mean");
  EXPECT_TRUE(QualityFlags(q, Stitch(0.0035, true, 0.12), iou).empty());
}

TEST(QualityFlags, AStitchFoundBySearchingTheOutlinesAloneIsFlagged) {
  // A Blender capture of a small wet stone: no marker point on both sides,
  // no feature match; the search over every orientation found the motion
  // 1.56 deg off the truth (volume -2.41 %), its masks agreeing with the
  // model, its stitch within the silhouettes' acceptance.
  json stitch = Stitch(0.0086, true, 0.0, 0.0050);
  json& sil = stitch["stitches"][0]["silhouettes"];
  sil["start"] = "search over every orientation";
  sil["search"] = {{"fits", 2}, {"runner_up_deficit", 0.0319}, {"runner_up_deg", 176.4}};
  stitch["stitches"][0]["source"] = "silhouettes";
  const json iou = json::array({{{"side", 1}, {"view", 0}, {"iou", 0.98}}});
  const json flags = QualityFlags(SoundQuality(), stitch, iou);
  ASSERT_EQ(flags.size(), 1u) << flags.dump();
  EXPECT_EQ(Codes(flags), std::set<std::string>{"stitch_outline_only"});
  const std::string reason = flags[0]["reason"];
  EXPECT_NE(reason.find("best 0.0086 uncovered, the runner-up 0.0319 at 176 deg"),
            std::string::npos)
      << reason;
  EXPECT_NE(reason.find("re-shoot side 2"), std::string::npos) << reason;
  // A start from markers or features, refined by the silhouettes: no flag.
  sil.erase("search");
  sil["start"] = "markers";
  EXPECT_TRUE(QualityFlags(SoundQuality(), stitch, iou).empty());
}

TEST(QualityFlags, EachLimitGivesItsOwnFlag) {
  // Only the worst view poor: still flagged.
  json q = SoundQuality();
  q["silhouette_iou_min"] = 0.93;
  EXPECT_EQ(Codes(QualityFlags(q, json::object(), json::array())),
            std::set<std::string>{"mask_consistency"});
  // Sources that disagree.
  json flags = QualityFlags(SoundQuality(), Stitch(0.004, false, 0.3), json::array());
  EXPECT_EQ(Codes(flags), std::set<std::string>{"stitch_disagreement"});
  EXPECT_NE(flags[0]["reason"].get<std::string>().find("3.40 deg and 4.20 mm"), std::string::npos)
      << flags.dump();
  // A loose stitch fit.
  EXPECT_EQ(Codes(QualityFlags(SoundQuality(), Stitch(0.004, true, 1.6), json::array())),
            std::set<std::string>{"stitch_residual"});
  // The scale references off, and an open model.
  q = SoundQuality();
  q["scale_residual_mm"] = 0.9;
  q["watertight"] = false;
  EXPECT_EQ(Codes(QualityFlags(q, json::object(), json::array())),
            (std::set<std::string>{"scale_residual", "not_watertight"}));
  // Limits are the caller's.
  QualityLimits strict;
  strict.silhouette_iou_mean = 0.995;
  EXPECT_EQ(Codes(QualityFlags(SoundQuality(), json::object(), json::array(), strict)),
            std::set<std::string>{"mask_consistency"});
}

}  // namespace
}  // namespace aggscan
