// A reconstructed sim sample against its truth.json, by the targets the
// product is held to: volume within 1 %, a, b, c within 2 % (against the
// truth's box, or the nearest of its near-minimal boxes where two boxes are
// within 1 % in volume: which is the minimum then turns on less than the
// volume's error; validate's rule, cli/validate_command.h).
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>

#include "cli/validate_command.h"
#include "pipeline/worker/reconstruct.h"

namespace aggscan::test {

/// Each view's true platter angle (deg), by (side, view).
inline std::map<std::pair<int, int>, double> TruePlatterDeg(const nlohmann::json& truth) {
  std::map<std::pair<int, int>, double> out;
  for (const nlohmann::json& t : truth["views"]) {
    out[{t["side"].get<int>(), t["view"].get<int>()}] = t["platter_deg"].get<double>();
  }
  return out;
}

/// Expects `sample`'s morphology within the targets of `truth`; prints the
/// errors under `what`.
inline void ExpectRockMatchesTruth(const std::string& sample, const nlohmann::json& truth,
                                   const char* what) {
  auto m = ReadMorphology(sample);
  ASSERT_TRUE(m) << m.error().ToString();
  const nlohmann::json& d = (*m)["morphology_3d"];
  const double dv = d["volume_mm3"].get<double>() / truth["volume_mm3"].get<double>() - 1.0;
  const DimErrors e = DimsAgainstTruth(RockFiguresFromJson(truth), RockFiguresFromJson(d));
  std::printf("%s: V %+.2f %%, a %+.2f %%, b %+.2f %%, c %+.2f %% (truth box %d, result box %d)\n",
              what, 100 * dv, e.a_pct, e.b_pct, e.c_pct, e.truth_box, e.rec_box);
  EXPECT_LT(std::abs(dv), 0.01) << what;
  EXPECT_LT(e.MaxAbs(), 2.0) << what;
}

}  // namespace aggscan::test
