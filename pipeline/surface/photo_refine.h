// Photo-consistency refinement of a visual hull: moves the hull's vertices
// inward where the photos say the surface lies deeper (concavities, which no
// silhouette can see). The hull is an upper bound of the object, so vertices
// only ever move inward, along the hull's (smoothed) normal.
//
// Method:
//  1. Per view, a depth map of the current mesh at reduced resolution (z-buffer
//     of the projected triangles): a vertex is visible in a view when its depth
//     is within a tolerance of the map's, and the view sees it frontally
//     (normal . direction to the camera >= min_cos).
//  2. Per vertex, the `views_per_vertex` most frontal visible views at least
//     min_baseline_deg apart (repeated angles add no depth signal); the most
//     frontal is the reference. Hypotheses p - d n for d in [0, max_depth_mm]:
//     a square patch at each hypothesis, its grid spaced about one reference
//     pixel, shaped like the hull around p (a quadric fitted to the hull's
//     vertices within the patch's reach; a tangent-plane patch fits best
//     inside a convex surface), is projected into every chosen view (with
//     lens distortion) and sampled bilinearly from grey images; the score is
//     the mean NCC of the reference patch against each other view's, each
//     over the samples on the rock in both views when masks are given.
//  3. A vertex's move is kept only when it is confident: the best score is at
//     least min_ncc and, for a peak deeper than near_hull_mm, beats the score
//     at the hull (d = 0) by min_gain. Confident vertices whose best depth is
//     the hull keep 0 as data. The search starts outside_mm outside the hull,
//     so that a peak at or near the hull gets its sub-step position, noise
//     included on both sides: clamping each vertex's data at the hull would
//     bias the surface outward. With highlight_depth_ratio, a deep peak
//     under a strongly convex part of the hull is taken for a glossy stone's
//     highlight, not the surface, and gives no data.
//  4. The displacement field is regularised: a data-weighted Laplacian
//     smoothing fills in vertices without data from their neighbours and
//     smooths the rest; data farther than outlier_mm from that field are
//     dropped and the smoothing repeated; the field is kept in
//     [0, max_depth_mm] (no vertex leaves the hull outward).
//  5. Vertices are moved, each along the hull's normal smoothed over about
//     its move's depth (a deep move behind a convex edge would otherwise
//     converge with its neighbours' and collapse the faces there); a face
//     whose normal turns by more than max_face_turn_deg (inverted) is
//     undone where it is: its vertices move to the centroid of their
//     neighbours' moved positions (up to untangle_passes), and only what
//     remains is pulled back towards the hull (halving, then all the way).
//     The moved region is then Taubin-smoothed (no shrinkage), except where
//     that would invert a face.
//     Topology is untouched, so a closed manifold hull stays closed and
//     manifold.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

#include "common/error.h"
#include "common/mesh.h"
#include "common/rig_calibration.h"

namespace aggscan {

struct PhotoView {
  cv::Mat image;       // CV_8UC1 grey or CV_8UC3 BGR, at camera.width x camera.height
  CameraModel camera;  // lens for that resolution
  Eigen::Isometry3d cam_from_object = Eigen::Isometry3d::Identity();  // mm
  // Optional CV_8UC1 rock mask (255 rock, 0 background) of the image's
  // aspect, at its size or the full resolution it was reduced from; it is
  // brought to the working scale here. Given, a patch's samples off the rock
  // in either view are left out of that pair's NCC.
  cv::Mat mask;
};

struct PhotoRefineOptions {
  // Deepest inward move searched (and the cap on moves). The hull stands
  // 10+ mm proud of a scanned stone's hollows: at 6 mm, validate at 2016 x
  // 1512 left EPFL 073ac15d / low_res_0 / E22 and ashlar 846 at +3.18 /
  // +5.20 / +1.75 / +7.26 % volume; at 15 mm +0.86 / +1.47 / +0.33 / +2.84 %,
  // while convex sim rocks (seeds 1, 5, 9, 17) moved by 0.00 to -0.06 %.
  double max_depth_mm = 15.0;
  double step_mm = 0.2;  // spacing of the depth hypotheses
  // Hypotheses scored first (every this many steps, the hull's among them),
  // then every step around the best until the best stays put; 1: every step.
  int depth_search_stride = 2;
  int views_per_vertex = 4;       // reference + up to 3 others, most frontal first
  double min_baseline_deg = 5.0;  // chosen views at least this far apart as seen from the vertex
  double min_cos = 0.35;          // a view must see the vertex at most ~70 deg off its normal
  int patch_radius = 4;           // patch is (2r+1)^2 samples
  bool curved_patches = true;  // patches follow the hull's local quadric (false: its tangent plane)
  // With the views' masks, the NCC of a pair of views covers only the patch's
  // samples on the rock in both (at least min_on_rock of them): a patch
  // straddling the silhouette compares the backdrop, which does not turn
  // with the rock, and so scored best once pushed inside, off the rim.
  bool masked_patches = true;
  double min_on_rock = 0.6;
  double patch_spacing_px = 1.0;  // sample spacing in reference pixels
  double image_scale = 1.0;    // images are resized by this first (0.5 halves 2016x1512 for speed)
  double blur_sigma_px = 0.8;  // Gaussian pre-blur against sensor noise and JPEG blocks (scaled px)
  int depth_map_downscale = 4;      // depth maps at image size / this
  double depth_tolerance_mm = 1.5;  // a vertex within this of a depth map's surface is visible
  // near_hull_mm, outside_mm, untangle_passes and smooth_lambda were set
  // together on validate's 2016x1512 captures. Before (0, 0, none: moves
  // halved over whole fold regions, lambda 10): 20 sim rocks volume MPE
  // +0.71 %, a/b/c within 2 % on 18; 6 EPFL stones MPE +1.43 %, a +3.5 % on
  // E34 (its top held up by the halving). After: -0.18 % (MAPE 0.24 %), 18
  // of 20; EPFL MPE +0.37 %, E34 a -0.4 %; sphericity error max 0.017.
  // Curved patches then (same captures): +0.08 % (MAPE 0.19 %), 19 of 20,
  // area MPE -0.43 % (-0.81); real stones 8 of 8 (7), V MPE +0.65 % (+0.49).
  // Masked patches and move_reach then (new captures, 20 + 8): dims within
  // 2 % on 20 (18) and 8 (8), worst 1.49 % (2.03); V MPE +0.01 % (-0.02) and
  // +0.65 % (+0.64); E34's a -0.17 % (+1.81: the collapsed faces' ridge).
  double min_ncc = 0.6;       // confident: best mean NCC at least this
  double min_gain = 0.1;      // ... and at least this above the NCC at the hull,
  double near_hull_mm = 0.5;  // ... for a peak deeper than this (shallower: the peak alone)
  double outside_mm = 0.6;    // hypotheses start this far outside the hull (0: at the hull)
  // A wet or polished stone's highlights are no texture of its surface. On a
  // turntable the light turns with the camera round the rock, so a highlight
  // stays where the surface faces halfway between light and camera: on a
  // patch curved like a sphere of radius R it moves with the sphere's centre,
  // and patches that match it across views find a depth R/2 to R inside
  // (R when the light is at the camera). A peak deeper than
  // highlight_depth_ratio x R, R = 1 / the hull's largest convex curvature
  // over highlight_reach_mm, is then no data (0: off). Off by default: most
  // hollows lie under flat or gently curved hull, where R is large, but a
  // scanned stone's hollow under a sharp hull edge is refused too, and on
  // matte stones that cost more volume than wet ones gained
  // (docs/validation.md; 0.3 suits glossy stones).
  double highlight_depth_ratio = 0.0;
  double highlight_reach_mm = 8.0;
  int sample_rings =
      1;  // score one vertex per this many rings (0: every vertex); the rest are filled in
  double outlier_mm =
      1.5;  // data this far from the smoothed field are dropped before the second pass
  int smooth_iterations = 100;  // Laplacian smoothing passes of the displacement field
  double smooth_lambda = 3.0;   // neighbour weight relative to a confident vertex's data weight
  double max_face_turn_deg =
      150.0;  // a face turning more than this is inverted and undone
              // (not less: the hull's sliver faces turn a lot and are harmless)
  // Vertices move along the hull's normals smoothed over about their move's
  // depth (reach = move_reach x depth), not over 3 rings: behind a convex
  // edge the 3-ring normals converge, and a move deeper than the edge's
  // radius collapses the faces there (an inward offset past the edge). 0:
  // every vertex moves along the 3-ring normal it was scored along.
  double move_reach = 1.0;
  int untangle_passes = 20;  // centroid passes over folding vertices before pulling them back
  int surface_smooth_iterations = 30;  // Taubin passes over the moved vertices' positions (0: none)
  int threads = 2;

  /// Empty when usable; otherwise every problem found.
  std::vector<std::string> Check() const;
};

struct PhotoRefineResult {
  Mesh mesh;
  int64_t vertices = 0;         // of the mesh
  int64_t vertices_scored = 0;  // with at least two views to compare
  int64_t vertices_confident = 0;
  int64_t vertices_highlight = 0;   // scored, their peak refused as a highlight (no data)
  int64_t vertices_moved = 0;       // final displacement > 0.05 mm
  double mean_displacement_mm = 0;  // over moved vertices
  double max_displacement_mm = 0;
  int max_direction_passes = 0;  // most smoothing passes a move direction took (move_reach)
  int64_t faces_folded = 0;  // faces that turned too far with the smoothed moves, before undoing
  int fold_passes = 0;       // passes pulling folding vertices back towards the hull
  int untangle_passes = 0;   // centroid passes over folding vertices
  double seconds = 0;
};

/// Refines `hull` (closed, consistently oriented, counter-clockwise from
/// outside) against the photos. Errors: bad options, no views, an image of the
/// wrong size or type.
Result<PhotoRefineResult> RefineByPhotoConsistency(const Mesh& hull,
                                                   const std::vector<PhotoView>& views,
                                                   const PhotoRefineOptions& opts = {});

}  // namespace aggscan
