// Hostile and damaged input files: meshes whose headers claim absurd element
// counts or whose coordinates are not finite, images of absurd or useless
// sizes, truncated and bit-flipped JPEGs. Each is a clear error with exit
// code != 0 from the real `aggscan morph` / `aggscan morph2d`, never an abort,
// and an image header is judged before anything is allocated for it.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/resource.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "pipeline/core/image_io.h"
#include "tests/util/synth_scene.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

struct CliRun {
  int rc = -1;
  long max_rss_kb = 0;
  std::string out, err;
};

std::string Slurp(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// The largest peak RSS of any run since it was last reset (kB).
long g_peak_rss_kb = 0;

// Runs the real binary (arguments split on spaces); rc is its exit code, or
// 128 + the signal that ended it; max_rss_kb its own peak resident size.
CliRun Aggscan(const std::string& args, const std::string& dir) {
  std::vector<std::string> argv_s = {std::string(AGGSCAN_BINARY_DIR) + "/cli/aggscan"};
  std::istringstream in(args);
  for (std::string a; in >> a;) argv_s.push_back(a);
  std::vector<char*> argv;
  for (auto& a : argv_s) argv.push_back(a.data());
  argv.push_back(nullptr);
  const std::string out_path = dir + "/out.txt", err_path = dir + "/err.txt";
  const pid_t pid = fork();
  if (pid == 0) {
    const int o = open(out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    const int e = open(err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    dup2(o, 1);
    dup2(e, 2);
    execv(argv[0], argv.data());
    _exit(127);
  }
  int st = 0;
  rusage ru{};
  wait4(pid, &st, 0, &ru);
  CliRun r;
  r.rc = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + (WIFSIGNALED(st) ? WTERMSIG(st) : 0);
  r.max_rss_kb = ru.ru_maxrss;
  g_peak_rss_kb = std::max(g_peak_rss_kb, r.max_rss_kb);
  r.out = Slurp(out_path);
  r.err = Slurp(err_path);
  return r;
}

std::string Write(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary) << bytes;
  return path;
}

void PutF32(std::string* s, float v) { s->append(reinterpret_cast<const char*>(&v), 4); }
void PutI32(std::string* s, int32_t v) { s->append(reinterpret_cast<const char*>(&v), 4); }

// A binary little-endian PLY of one triangle whose header claims `vertices`
// vertices and `faces` faces.
std::string TrianglePly(const std::string& vertices, const std::string& faces) {
  std::string s = "ply\nformat binary_little_endian 1.0\nelement vertex " + vertices +
                  "\nproperty float x\nproperty float y\nproperty float z\nelement face " + faces +
                  "\nproperty list uchar int vertex_indices\nend_header\n";
  for (float v : {0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 1.f, 0.f}) PutF32(&s, v);
  s.push_back(3);
  for (int i : {0, 1, 2}) PutI32(&s, i);
  return s;
}

// A closed tetrahedron as ASCII PLY with vertex 3's x set to `x3`.
std::string TetraPly(const std::string& x3) {
  return "ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty "
         "double z\n"
         "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n10 0 0\n0 10 0\n" +
         x3 + " 0 10\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 2 0 3\n";
}

long MaxRssKb(int who) {
  rusage ru{};
  getrusage(who, &ru);
  return ru.ru_maxrss;
}

TEST(BadMeshFiles, AbsurdPlyCountsAreRefusedNamingElementCountAndSize) {
  test::TempDir tmp;
  const long rss0 = MaxRssKb(RUSAGE_SELF);
  // The binary's own footprint: a refusal of a missing file.
  const long base_kb = Aggscan("morph " + tmp.path() + "/missing.ply", tmp.path()).max_rss_kb;
  g_peak_rss_kb = 0;
  for (const std::string n : {"2147483647", "4294967295", "9223372036854775807"}) {
    const std::string p = Write(tmp.path() + "/v" + n + ".ply", TrianglePly(n, "1"));
    const CliRun r = Aggscan("morph " + p, tmp.path());
    EXPECT_EQ(r.rc, 2) << r.err;
    EXPECT_NE(r.err.find("element vertex has " + n + " rows"), std::string::npos) << r.err;
    EXPECT_NE(r.err.find("holds only 49 bytes"), std::string::npos) << r.err;
    // The same through the faces.
    const std::string pf = Write(tmp.path() + "/f" + n + ".ply", TrianglePly("3", n));
    const CliRun rf = Aggscan("morph " + pf, tmp.path());
    EXPECT_EQ(rf.rc, 2) << rf.err;
    EXPECT_NE(rf.err.find("element face has " + n + " rows"), std::string::npos) << rf.err;
  }
  // A count beyond int64 is not a count.
  const std::string huge =
      Write(tmp.path() + "/huge.ply", TrianglePly("18446744073709551615", "1"));
  CliRun r = Aggscan("morph " + huge, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("element vertex has count \"18446744073709551615\""), std::string::npos)
      << r.err;
  // The header says a little more than the file holds.
  const std::string more = Write(tmp.path() + "/more.ply", TrianglePly("3", "2"));
  r = Aggscan("morph " + more, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("truncated in face 1"), std::string::npos) << r.err;
  const std::string more2 = Write(tmp.path() + "/more2.ply", TrianglePly("5", "1"));
  r = Aggscan("morph " + more2, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(
      r.err.find(
          "element vertex has 5 rows of at least 12 bytes each, but the file holds only 49 bytes"),
      std::string::npos)
      << r.err;
  // ASCII: at least two bytes a value.
  const std::string ascii =
      Write(tmp.path() + "/ascii.ply",
            "ply\nformat ascii 1.0\nelement vertex 2147483647\nproperty float x\nproperty "
            "float y\nproperty float z\nelement face 1\nproperty list uchar int "
            "vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
  r = Aggscan("morph " + ascii, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("element vertex has 2147483647 rows of at least 6 bytes each (ASCII)"),
            std::string::npos)
      << r.err;
  // Binary STL claiming 2^32-1 triangles with one stored.
  std::string stl(80, ' ');
  PutI32(&stl, -1);
  stl.append(50, '\0');
  const std::string pstl = Write(tmp.path() + "/big.stl", stl);
  r = Aggscan("morph " + pstl, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("header says 4294967295 triangles"), std::string::npos) << r.err;
  // Each run was refused before allocating for the counts: its peak is the
  // binary's own; nothing here ran in this process.
  EXPECT_LT(g_peak_rss_kb - base_kb, 100 * 1024) << "a refused run's peak RSS growth (kB)";
  std::printf("aggscan morph refusals: peak RSS at most %ld kB above the binary's own %ld kB\n",
              g_peak_rss_kb - base_kb, base_kb);
  EXPECT_LT(MaxRssKb(RUSAGE_SELF) - rss0, 100 * 1024);
}

TEST(BadMeshFiles, NonFiniteAndHugeCoordinatesAreRefusedNamingTheVertex) {
  test::TempDir tmp;
  // The tetrahedron itself is fine.
  CliRun r = Aggscan("morph --json " + Write(tmp.path() + "/ok.ply", TetraPly("0")), tmp.path());
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("\"volume_mm3\""), std::string::npos);
  for (const std::string bad : {"1e308", "nan", "inf", "-1e12"}) {
    r = Aggscan("morph --json " + Write(tmp.path() + "/c.ply", TetraPly(bad)), tmp.path());
    EXPECT_EQ(r.rc, 2) << bad << ": " << r.out;
    EXPECT_NE(r.err.find("vertex 3 has coordinate"), std::string::npos) << r.err;
    EXPECT_EQ(r.out.find("nan"), std::string::npos) << r.out;
  }
  // 1e5 m is finite but 1e8 mm once converted.
  r = Aggscan("morph --unit m " + Write(tmp.path() + "/m.ply", TetraPly("1e5")), tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("farther than 10 km"), std::string::npos) << r.err;
  r = Aggscan("morph " + Write(tmp.path() + "/c.obj",
                               "v 0 0 0\nv 1 0 0\nv 0 1e308 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\n"
                               "f 2 3 4\nf 3 1 4\n"),
              tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("vertex 2 has coordinate 1e+308"), std::string::npos) << r.err;
}

// ---------------------------------------------------------------- images

std::string Be16(int v) { return {static_cast<char>(v >> 8), static_cast<char>(v & 0xFF)}; }

// A JPEG header (SOI, SOF0 of three components, SOS) of any size with a few
// bytes of scan data: what a corrupt or hostile file looks like to a decoder.
std::string JpegHeaderOnly(int w, int h) {
  std::string s = "\xFF\xD8";
  s += "\xFF\xC0" + Be16(17) + "\x08" + Be16(h) + Be16(w) + "\x03";
  for (int c = 1; c <= 3; ++c) s += std::string{static_cast<char>(c), '\x11', '\x00'};
  s += "\xFF\xDA" + Be16(12) + "\x03" + std::string("\x01\x00\x02\x11\x03\x11\x00\x3F\x00", 9);
  s += std::string(64, '\x55') + "\xFF\xD9";
  return s;
}

std::string PngHeaderOnly(uint32_t w, uint32_t h) {
  std::string s("\x89PNG\r\n\x1a\n\0\0\0\x0dIHDR", 16);
  for (uint32_t v : {w, h}) {
    for (int sh = 24; sh >= 0; sh -= 8) s.push_back(static_cast<char>((v >> sh) & 0xFF));
  }
  s += std::string("\x08\x02\0\0\0", 5) + "CRC!" + std::string("\0\0\0\x10IDAT", 8) +
       std::string(20, 'x');
  return s;
}

std::string Photo(int w, int h) {
  testing::SceneParams sp;
  sp.size = {w, h};
  const auto sc = testing::MakeScene(sp);
  return std::string(sc.jpeg.begin(), sc.jpeg.end());
}

TEST(BadImageFiles, HeadersAreJudgedBeforeDecoding) {
  test::TempDir tmp;
  const std::string photo = Photo(640, 480);
  auto hdr = ReadImageHeader(photo, "photo");
  ASSERT_TRUE(hdr) << hdr.error().ToString();
  EXPECT_EQ(hdr->format, "jpeg");
  EXPECT_EQ(hdr->width, 640);
  EXPECT_EQ(hdr->height, 480);
  EXPECT_EQ(hdr->channels, 3);
  auto img = DecodeImage(photo, ImageMode::kColor, "photo");
  ASSERT_TRUE(img) << img.error().ToString();
  EXPECT_EQ(img->size(), cv::Size(640, 480));
  EXPECT_EQ(img->type(), CV_8UC3);
  auto half = DecodeImage(photo, ImageMode::kGrayHalf, "photo");
  ASSERT_TRUE(half);
  EXPECT_EQ(half->size(), cv::Size(320, 240));
  // The same pixels as OpenCV's decoder (both are libjpeg-turbo).
  const std::vector<unsigned char> buf(photo.begin(), photo.end());
  const cv::Mat ref = cv::imdecode(buf, cv::IMREAD_COLOR);
  EXPECT_EQ(cv::norm(ref, *img, cv::NORM_INF), 0.0);

  const long rss0 = MaxRssKb(RUSAGE_SELF);
  for (const std::string& big : {JpegHeaderOnly(40000, 20000), PngHeaderOnly(40000, 20000)}) {
    auto r = DecodeImage(big, ImageMode::kColor, "big");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("is 40000x20000 (800.0 MP, more than the 100.0 MP limit)"),
              std::string::npos)
        << r.error().message;
  }
  EXPECT_LT(MaxRssKb(RUSAGE_SELF) - rss0, 100 * 1024) << "peak RSS growth (kB)";
  std::printf("peak RSS growth over two 40000x20000 headers: %ld kB\n",
              MaxRssKb(RUSAGE_SELF) - rss0);
  // A larger limit lets a 12 MP header through to the decoder, whose failure
  // on the fake scan data is an error too.
  ImageLimits wide;
  wide.max_pixels = 20'000'000;
  auto r12 = DecodeImage(JpegHeaderOnly(4000, 3000), ImageMode::kColor, "fake", wide);
  ASSERT_FALSE(r12);
  EXPECT_EQ(r12.error().cls, ErrorClass::kCorrupt);

  for (auto [w, h, what] : {std::tuple{1, 1, "is 1x1: too small to measure"},
                            std::tuple{65500, 1, "is 65500x1: too small to measure"},
                            std::tuple{4000, 100, "is 4000x100: a strip, not a photo"}}) {
    cv::Mat m(h, w, CV_8UC1, cv::Scalar(255));
    std::vector<unsigned char> png;
    ASSERT_TRUE(cv::imencode(".png", m, png));
    auto r = DecodeImage(std::string(png.begin(), png.end()), ImageMode::kGray, "m.png");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find(what), std::string::npos) << r.error().message;
  }
  auto e = DecodeImage("GIF89a......", ImageMode::kColor, "x.gif");
  ASSERT_FALSE(e);
  EXPECT_NE(e.error().message.find("not a JPEG, PNG, PNM or BMP file"), std::string::npos);
  auto t = DecodeImage(photo.substr(0, 100), ImageMode::kColor, "short.jpg");
  ASSERT_FALSE(t);
}

// Flips `n` bytes at pseudo-random positions inside the entropy-coded data
// (after the start-of-scan header, before the end marker): same size.
std::string FlipScanBytes(std::string jpeg, int n, uint32_t seed) {
  const size_t sos = jpeg.find("\xFF\xDA");
  const size_t start = sos + 2 +
                       ((static_cast<unsigned char>(jpeg[sos + 2]) << 8) |
                        static_cast<unsigned char>(jpeg[sos + 3]));
  const size_t end = jpeg.size() - 2;
  std::mt19937 rng(seed);
  // A run in the first half of the scan, where the rock is (rows decode top
  // to bottom).
  const size_t at = start + (end - start) / 3;
  for (int i = 0; i < n; ++i) {
    const size_t k = at + static_cast<size_t>(i) * 3;
    jpeg[k] = static_cast<char>(jpeg[k] ^ (1u + rng() % 255u));
  }
  return jpeg;
}

TEST(BadImageFiles, DamagedJpegsAreErrorsNotGreyPhotos) {
  test::TempDir tmp;
  const std::string photo = Photo(640, 480);
  // Truncated: libjpeg would warn and fill the rest with grey.
  auto tr = DecodeImage(photo.substr(0, photo.size() * 6 / 10), ImageMode::kColor, "cut.jpg");
  ASSERT_FALSE(tr);
  EXPECT_NE(tr.error().message.find("damaged JPEG data (libjpeg: Premature end of JPEG file)"),
            std::string::npos)
      << tr.error().message;
  const std::string flipped = FlipScanBytes(photo, 200, 1);
  ASSERT_EQ(flipped.size(), photo.size());
  auto fl = DecodeImage(flipped, ImageMode::kColor, "flipped.jpg");
  ASSERT_FALSE(fl);
  EXPECT_NE(fl.error().message.find("damaged JPEG data"), std::string::npos) << fl.error().message;
  EXPECT_NE(fl.error().detail.find("Corrupt JPEG data"), std::string::npos) << fl.error().detail;
  // Plain OpenCV decodes it without a word.
  const std::vector<unsigned char> buf(flipped.begin(), flipped.end());
  EXPECT_FALSE(cv::imdecode(buf, cv::IMREAD_COLOR).empty());
}

TEST(BadImageFiles, Morph2dRefusesThemWithExitCode2) {
  test::TempDir tmp;
  const std::string photo = Photo(640, 480);
  auto png = [&](int w, int h) {
    cv::Mat m(h, w, CV_8UC1, cv::Scalar(255));
    const std::string p = tmp.path() + "/m" + std::to_string(w) + "x" + std::to_string(h) + ".png";
    EXPECT_TRUE(cv::imwrite(p, m));
    return p;
  };
  struct Case {
    std::string path, what;
  };
  const std::vector<Case> cases = {
      {png(1, 1), "is 1x1: too small to measure"},
      {png(65500, 1), "is 65500x1: too small to measure"},
      {Write(tmp.path() + "/big.jpg", JpegHeaderOnly(40000, 20000)), "is 40000x20000 (800.0 MP"},
      {Write(tmp.path() + "/big.png", PngHeaderOnly(40000, 20000)), "is 40000x20000 (800.0 MP"},
      {Write(tmp.path() + "/cut.jpg", photo.substr(0, photo.size() / 2)),
       "Premature end of JPEG file"},
      {Write(tmp.path() + "/flip.jpg", FlipScanBytes(photo, 200, 1)), "damaged JPEG data"},
      {Write(tmp.path() + "/empty.jpg", ""), "the file is empty"},
  };
  // The binary's own footprint: a refusal of an empty file.
  const long base_kb = Aggscan("morph2d " + tmp.path() + "/empty.jpg", tmp.path()).max_rss_kb;
  long worst_kb = 0;
  for (const Case& c : cases) {
    const CliRun r = Aggscan("morph2d " + c.path, tmp.path());
    worst_kb = std::max(worst_kb, r.max_rss_kb - base_kb);
    EXPECT_LT(r.max_rss_kb - base_kb, 100 * 1024) << c.path << ": peak RSS growth (kB)";
    EXPECT_EQ(r.rc, 2) << c.path << ": " << r.err;
    EXPECT_NE(r.err.find(c.what), std::string::npos) << c.path << ": " << r.err;
    EXPECT_NE(r.err.find(c.path), std::string::npos) << r.err;
  }
  std::printf("aggscan morph2d refusals: peak RSS at most %ld kB above the binary's own %ld kB\n",
              worst_kb, base_kb);
  // The undamaged photo is measured; a lower limit refuses it.
  const std::string good = Write(tmp.path() + "/good.jpg", photo);
  CliRun r = Aggscan("morph2d " + good, tmp.path());
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("\"fer_2d\""), std::string::npos);
  r = Aggscan("morph2d --max-megapixels 0.1 " + good, tmp.path());
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("is 640x480 (0.3 MP, more than the 0.1 MP limit)"), std::string::npos)
      << r.err;
}

}  // namespace
}  // namespace aggscan
