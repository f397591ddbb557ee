#include "pipeline/worker/options_json.h"

namespace aggscan {

using json = nlohmann::json;

// A field added to a struct changes its size: add the field below, then the
// size here. Thread counts are left out: they do not change a result.
static_assert(sizeof(MaskOptions) == 208, "MaskOptions changed: add the new field to OptionsJson");
static_assert(sizeof(PhotoRefineOptions) == 208,
              "PhotoRefineOptions changed: add the new field to OptionsJson");
static_assert(sizeof(VisualHullOptions) == 40,
              "VisualHullOptions changed: add the new field to OptionsJson");
static_assert(sizeof(BundleAdjustOptions) == 192,
              "BundleAdjustOptions changed: add the new field to OptionsJson");
static_assert(sizeof(SfmPosesOptions) == 112,
              "SfmPosesOptions changed: add the new field to OptionsJson");
static_assert(sizeof(FeatureCloudOptions) == 96,
              "FeatureCloudOptions changed: add the new field to OptionsJson");
static_assert(sizeof(geom::TriangulationOptions) == 32,
              "TriangulationOptions changed: add the new field to OptionsJson");
static_assert(sizeof(ImageLimits) == 24, "ImageLimits changed: add the new field to OptionsJson");
static_assert(sizeof(MaskNetOptions) == 120,
              "MaskNetOptions changed: add the new field to OptionsJson");

json OptionsJson(const MaskOptions& o) {
  return {{"work_long_side", o.work_long_side},
          {"border_fraction", o.border_fraction},
          {"background_clusters", o.background_clusters},
          {"shade_min", o.shade_min},
          {"shade_max", o.shade_max},
          {"color_threshold", o.color_threshold},
          {"noise_levels", o.noise_levels},
          {"color_weak_ratio", o.color_weak_ratio},
          {"color_border_factor", o.color_border_factor},
          {"texture_sigma", o.texture_sigma},
          {"texture_threshold", o.texture_threshold},
          {"texture_border_factor", o.texture_border_factor},
          {"saturated_chroma", o.saturated_chroma},
          {"open_radius", o.open_radius},
          {"close_radius", o.close_radius},
          {"refine", static_cast<int>(o.refine)},
          {"refine_long_side", o.refine_long_side},
          {"graphcut_iterations", o.graphcut_iterations},
          {"graphcut_texture_weight", o.graphcut_texture_weight},
          {"label_thickness", o.label_thickness},
          {"paint_fringe_px", o.paint_fringe_px},
          {"graphcut_band", o.graphcut_band},
          {"band_inner_px", o.band_inner_px},
          {"band_outer_px", o.band_outer_px},
          {"graphcut_band_px", o.graphcut_band_px},
          {"local_sigma_px", o.local_sigma_px},
          {"chroma_weight", o.chroma_weight},
          {"marker_touch_fraction", o.marker_touch_fraction},
          {"reference_shade_max", o.reference_shade_max}};
}

json OptionsJson(const PhotoRefineOptions& o) {
  return {{"max_depth_mm", o.max_depth_mm},
          {"step_mm", o.step_mm},
          {"depth_search_stride", o.depth_search_stride},
          {"views_per_vertex", o.views_per_vertex},
          {"min_baseline_deg", o.min_baseline_deg},
          {"min_cos", o.min_cos},
          {"patch_radius", o.patch_radius},
          {"curved_patches", o.curved_patches},
          {"masked_patches", o.masked_patches},
          {"min_on_rock", o.min_on_rock},
          {"patch_spacing_px", o.patch_spacing_px},
          {"image_scale", o.image_scale},
          {"blur_sigma_px", o.blur_sigma_px},
          {"depth_map_downscale", o.depth_map_downscale},
          {"depth_tolerance_mm", o.depth_tolerance_mm},
          {"min_ncc", o.min_ncc},
          {"min_gain", o.min_gain},
          {"highlight_depth_ratio", o.highlight_depth_ratio},
          {"highlight_reach_mm", o.highlight_reach_mm},
          {"near_hull_mm", o.near_hull_mm},
          {"outside_mm", o.outside_mm},
          {"sample_rings", o.sample_rings},
          {"outlier_mm", o.outlier_mm},
          {"smooth_iterations", o.smooth_iterations},
          {"smooth_lambda", o.smooth_lambda},
          {"max_face_turn_deg", o.max_face_turn_deg},
          {"move_reach", o.move_reach},
          {"untangle_passes", o.untangle_passes},
          {"surface_smooth_iterations", o.surface_smooth_iterations}};
}

json OptionsJson(const VisualHullOptions& o) {
  return {{"coarse_mm", o.coarse_mm},
          {"voxel_mm", o.voxel_mm},
          {"target_faces", o.target_faces},
          {"min_voxel_mm", o.min_voxel_mm}};
}

json OptionsJson(const BundleAdjustOptions& o) {
  return {{"features", OptionsJson(o.features)},  {"sift_max_width", o.sift_max_width},
          {"angle_prior_deg", o.angle_prior_deg}, {"refine_rig", o.refine_rig},
          {"rig_prior_deg", o.rig_prior_deg},     {"rig_prior_mm", o.rig_prior_mm},
          {"refine_lens", o.refine_lens},         {"huber_px", o.huber_px},
          {"outlier_px", o.outlier_px},           {"max_correction_deg", o.max_correction_deg},
          {"min_tracks", o.min_tracks},           {"min_views", o.min_views},
          {"max_iterations", o.max_iterations}};
}

json OptionsJson(const SfmPosesOptions& o) {
  return {{"max_image_size", o.max_image_size},
          {"circular_neighbours", o.circular_neighbours},
          {"free_camera_model", o.free_camera_model},
          {"init_min_num_inliers", o.init_min_num_inliers},
          {"init_min_tri_angle_deg", o.init_min_tri_angle_deg},
          {"abs_pose_min_num_inliers", o.abs_pose_min_num_inliers},
          {"max_scale_residual_mm", o.max_scale_residual_mm},
          {"crop_to_masks", o.crop_to_masks}};
}

json OptionsJson(const FeatureCloudOptions& o) {
  return {{"max_features", o.max_features},
          {"image_scale", o.image_scale},
          {"mask_erode_px", o.mask_erode_px},
          {"ratio", o.ratio},
          {"min_pair_deg", o.min_pair_deg},
          {"max_pair_deg", o.max_pair_deg},
          {"epipolar_px", o.epipolar_px},
          {"triangulation", OptionsJson(o.triangulation)},
          {"distinct_viewpoints_only", o.distinct_viewpoints_only}};
}

json OptionsJson(const geom::TriangulationOptions& o) {
  return {{"inlier_px", o.inlier_px},
          {"min_views", o.min_views},
          {"min_angle_deg", o.min_angle_deg},
          {"robust", o.robust},
          {"refine_iterations", o.refine_iterations}};
}

json OptionsJson(const ImageLimits& o) {
  return {
      {"max_pixels", o.max_pixels}, {"min_side_px", o.min_side_px}, {"max_aspect", o.max_aspect}};
}

json OptionsJson(const MaskNetOptions& o) {
  return {{"input", {o.input_size.width, o.input_size.height}},
          {"mean_rgb", {o.mean_rgb[0], o.mean_rgb[1], o.mean_rgb[2]}},
          {"std_rgb", {o.std_rgb[0], o.std_rgb[1], o.std_rgb[2]}},
          {"logits", o.logits},
          {"threshold", o.threshold}};
}

}  // namespace aggscan
