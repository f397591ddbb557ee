// `aggscan import`: photos from any camera (a phone, a DSLR) made into a
// sample directory that the worker processes like a rig's capture.
//
//   aggscan import DIR --id ID [--out SAMPLE_DIR] [--config FILE]
//                  [--calibration FILE] [--focal-mm F --sensor-mm W]
//                  [--gap SECONDS] [--min-views N] [--no-scale] [--skip-bad]
//
// Sides: one per sub-folder of DIR (in name order), else the photos of DIR
// in the order they were taken (EXIF time, then name), split where the time
// between two photos is longer than --gap (default: 30 s and five times the
// usual interval). Each photo is turned upright by its EXIF orientation and
// stored as the side's next view with a sidecar of what its EXIF says; the
// focal length comes from --focal-mm and --sensor-mm, else the 35 mm
// equivalent, else the focal length and the focal plane resolution. With
// --calibration (a rig calibration of this camera at this size) the fast
// turntable path measures the views' angles from the disc's labels; without,
// the worker poses them by SfM.
//
// Refused before anything is written, each with what to do: a side with too
// few views, photos out of focus or over- or under-exposed (--skip-bad leaves
// them out instead), mixed cameras or sizes without a calibration, a
// calibration of another size, no scale reference (the disc's labels or the
// [rig] ArUco markers) in enough views of a side (--no-scale imports anyway:
// the worker can pose such views, but stops before measuring, having no size).
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

int RunImportCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);
void PrintImportUsage(std::ostream& o);

}  // namespace aggscan
