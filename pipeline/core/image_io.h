// The one way the worker and the offline commands read a photo or a mask.
//
// A file is judged before it is decoded: its header (JPEG SOF, PNG IHDR, PNM,
// BMP) gives the dimensions, and an image too large (a corrupt or hostile
// header would make the decoder allocate gigabytes), too small to measure or
// of a degenerate shape is refused with its size named. JPEG is decoded by
// libjpeg-turbo with warnings treated as errors: libjpeg only warns about a
// truncated file ("Premature end of JPEG file") or damaged entropy-coded data
// ("Corrupt JPEG data") and fills what it could not decode with grey, which
// would give a wrong silhouette without a word. Other formats go to OpenCV.
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <string_view>

#include "common/error.h"

namespace aggscan {

struct ImageLimits {
  int64_t max_pixels = 100'000'000;  // larger images are refused before decoding (100 MP)
  int min_side_px = 64;              // a silhouette in fewer pixels a side cannot be measured
  double max_aspect = 16.0;          // longer side / shorter side: no camera's frame is a strip
};

struct ImageHeader {
  std::string format;  // "jpeg", "png", "pnm", "bmp"
  int width = 0;
  int height = 0;
  int channels = 0;  // as stored (JPEG components, PNG colour type's channels); 0 = unknown
};

enum class ImageMode {
  kColor,     // CV_8UC3, BGR
  kGray,      // CV_8UC1
  kGrayHalf,  // CV_8UC1 at half size (rounded up), decoded at that scale
  kUnchanged  // as stored (JPEG: 1 or 3 channels; PNG: 8 or 16 bit, 1-4 channels)
};

/// Dimensions from the file's header alone; kCorrupt naming `what` when the
/// header is malformed or the format is not one of JPEG, PNG, PNM, BMP.
Result<ImageHeader> ReadImageHeader(std::string_view bytes, const std::string& what);

/// kCorrupt naming `what` and its size when the header's dimensions break `limits`.
Status CheckImageLimits(const ImageHeader& h, const ImageLimits& limits, const std::string& what);

/// Header check, limits, then decode. A JPEG libjpeg warns about is kCorrupt
/// with libjpeg's message as the detail; no decoder exception escapes.
Result<cv::Mat> DecodeImage(std::string_view bytes, ImageMode mode, const std::string& what,
                            const ImageLimits& limits = {});

/// Reads `path` (refusing a file larger than any image within `limits` could
/// be) and decodes it with DecodeImage.
Result<cv::Mat> LoadImage(const std::string& path, ImageMode mode, const ImageLimits& limits = {});

/// For a process that works through many full-size photos (the worker, the
/// offline reconstruction): freed image buffers stay with the allocator for
/// the next photo instead of going back to the kernel. glibc maps every block
/// above its (adaptive) threshold afresh and unmaps it on free, so each
/// 9 MB photo and its float copies cost a page fault per 4 KiB page on every
/// use; on the rig's VM-like kernels that was a fifth of the worker's time.
/// The process's peak memory is unchanged (what is kept is what was in use at
/// the peak). Call once, before the first thread starts.
void KeepFreedImageMemory();

}  // namespace aggscan
