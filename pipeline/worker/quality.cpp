#include "pipeline/worker/quality.h"

#include <cstdio>
#include <string>

namespace aggscan {

namespace {

using nlohmann::json;

double Num(const json& j, const char* key, double fallback) {
  const auto it = j.find(key);
  return it != j.end() && it->is_number() ? it->get<double>() : fallback;
}

void Add(json* flags, const char* code, const std::string& reason) {
  flags->push_back({{"code", code}, {"reason", reason}});
}

}  // namespace

json QualityFlags(const json& quality, const json& stitch, const json& silhouette_iou,
                  const QualityLimits& lim) {
  json flags = json::array();
  char b[512];

  // Masks against the model they built: a mask that takes in a shadow or
  // the background, or loses part of the rock, disagrees with the others.
  const double iou_mean = Num(quality, "silhouette_iou_mean", 1.0);
  const double iou_min = Num(quality, "silhouette_iou_min", 1.0);
  const bool masks_flagged = iou_mean < lim.silhouette_iou_mean || iou_min < lim.silhouette_iou_min;
  if (masks_flagged) {
    std::string worst;
    double w = 2;
    for (const json& v : silhouette_iou) {
      if (!v.is_object()) continue;
      const double iou = Num(v, "iou", 2);
      if (iou < w) {
        w = iou;
        worst = "side " + std::to_string(v.value("side", 0)) + " view " +
                std::to_string(v.value("view", 0));
      }
    }
    std::snprintf(b, sizeof b,
                  "the masks agree poorly with the model's silhouettes: IoU mean %.3f, worst "
                  "%.3f%s%s (needed: mean "
                  ">= %.2f, every view >= %.2f); shadows, the disc's edge or background in the "
                  "masks, or parts of "
                  "the rock missing from them, move the volume: check results/masks",
                  iou_mean, iou_min, worst.empty() ? "" : " at ", worst.c_str(),
                  lim.silhouette_iou_mean, lim.silhouette_iou_min);
    Add(&flags, "mask_consistency", b);
  }

  // The photo refinement moves vertices inward only where the photos agree
  // on a deeper surface. Where the masks are sound, the hull's outline in a
  // view is where the rock touches that view's silhouette cone, so no sound
  // move takes it in; gloss that moves with the view (a wet stone) or faint
  // texture can mislead the depth search all round the rock. Masks that all
  // take in the same contact shadow make a hull whose outline the
  // refinement rightly takes in: those are flagged above, and judged there.
  if (const double loss = Num(quality, "outline_loss_mean", 0);
      !masks_flagged && loss > lim.outline_loss) {
    std::snprintf(b, sizeof b,
                  "the photo refinement took the surface inside the outline the masks agree on: "
                  "it no longer covers %.2f %% of the carved hull's silhouettes on average (worst "
                  "view %.2f %%; limit %.2f %%), so the volume is likely low; gloss or faint "
                  "texture misleads the depth search: check the photos, or reconstruct with the "
                  "hull alone (aggscan reconstruct SAMPLE --surface hull) for an upper bound",
                  100 * loss, 100 * Num(quality, "outline_loss_max", loss), 100 * lim.outline_loss);
    Add(&flags, "outline_loss", b);
  }

  for (const json& s : stitch.value("stitches", json::array())) {
    if (!s.is_object()) continue;
    const int side = s.value("side", 0), onto = s.value("onto_side", 1);
    const std::string source = s.value("source", "");
    const json& sil = s.value("silhouettes", json::object());
    const double deficit = Num(sil, "deficit", -1);
    // What each side's own masks leave uncovered whatever the motion (0 in
    // records written before it was measured).
    const double own = Num(sil, "own_deficit", 0);
    if (sil.value("available", false) && deficit - own > lim.stitch_deficit) {
      std::snprintf(
          b, sizeof b,
          "side %d's stitch onto side %d (by %s) is not confirmed by the silhouettes: the stitched "
          "model leaves %.3f of them uncovered, %.3f more than each side's own masks do (accepted: "
          "%.4f more); the sides may be joined wrongly",
          side, onto, source.c_str(), deficit, deficit - own, lim.stitch_deficit);
      Add(&flags, "stitch_unconfirmed", b);
    }
    // No start from markers or features that the silhouettes accept: the
    // motion was found by searching every orientation for the one the
    // outlines fit, and nothing independent of the masks confirms it.
    // Unique does not mean precise: at 1008 px wide such stitches came out
    // 0.8-1.6 deg off on sim and Blender renders (docs/validation.md).
    if (sil.contains("search")) {
      std::snprintf(b, sizeof b,
                    "side %d's stitch onto side %d rests on the silhouettes alone: no start "
                    "from the object markers or feature matches that the silhouettes accept, so "
                    "the motion was found by searching every orientation (best %.4f uncovered, the "
                    "runner-up %.4f at %.0f deg) and nothing but the masks confirms it; the "
                    "figures may be off by a few per cent: re-shoot side %d with both object "
                    "markers facing the camera in some views",
                    side, onto, deficit, Num(sil.at("search"), "runner_up_deficit", 0),
                    Num(sil.at("search"), "runner_up_deg", 0), side);
      Add(&flags, "stitch_outline_only", b);
    }
    if (!s.value("consistent", true)) {
      std::snprintf(b, sizeof b,
                    "side %d's stitch sources disagree: %.2f deg and %.2f mm between the markers' "
                    "and the features' "
                    "estimates (%s was taken)%s%s",
                    side, Num(s, "disagreement_deg", 0), Num(s, "disagreement_mm", 0),
                    source.c_str(), s.value("warning", "").empty() ? "" : ": ",
                    s.value("warning", "").c_str());
      Add(&flags, "stitch_disagreement", b);
    }
  }
  if (const double rms = Num(stitch, "rms_mm", 0); rms > lim.stitch_rms_mm) {
    std::snprintf(b, sizeof b,
                  "the stitch's points fit with %.2f mm RMS (max %.2f mm; limit %.1f mm RMS): "
                  "markers or features "
                  "located inaccurately",
                  rms, Num(stitch, "max_mm", 0), lim.stitch_rms_mm);
    Add(&flags, "stitch_residual", b);
  }
  if (const double sr = Num(quality, "scale_residual_mm", 0); sr > lim.scale_residual_mm) {
    std::snprintf(b, sizeof b,
                  "the scale references are %.2f mm off their configured distances (limit %.1f "
                  "mm): check the "
                  "labels' positions in the config and the rig calibration",
                  sr, lim.scale_residual_mm);
    Add(&flags, "scale_residual", b);
  }
  if (quality.contains("watertight") && !quality.value("watertight", true)) {
    Add(&flags, "not_watertight",
        "the model is not a closed surface: its volume and sphericity are not defined");
  }
  return flags;
}

}  // namespace aggscan
