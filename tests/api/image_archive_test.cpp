// A sample's images as one ZIP (GET /api/v1/samples/{id}/images.zip): made
// while the client reads it (daemon/archive_stream.h), checked by an
// independent reader (Python's zipfile) byte for byte against the files.
#include <gtest/gtest.h>
#include <httplib.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <random>
#include <string>

#include "common/fsutil.h"
#include "daemon/archive_stream.h"
#include "daemon/http_api.h"
#include "tests/api/fake_control.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using testing::FakeControl;

// Random bytes (nothing a compressor could shrink, like a JPEG).
std::string Noise(size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::string s(n, '\0');
  for (char& c : s) c = static_cast<char>(rng() & 0xff);
  return s;
}

void Write(const std::string& path, const std::string& bytes) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  std::ofstream(path, std::ios::binary) << bytes;
}

// What Python's zipfile reads from `zip`: {"bad": testzip(), "members":
// {name: {"size", "sha256", "stored"}}}; null when Python is unusable.
json ReadWithZipfile(const std::string& zip, const std::string& scratch) {
  const std::string script = scratch + "/read_zip.py";
  Write(
      script,
      "import hashlib, json, sys, zipfile\n"
      "z = zipfile.ZipFile(sys.argv[1])\n"
      "out = {'bad': z.testzip(), 'members': {}}\n"
      "for i in z.infolist():\n"
      "    d = z.read(i)\n"
      "    out['members'][i.filename] = {'size': len(d), 'sha256': hashlib.sha256(d).hexdigest(),\n"
      "        'stored': i.compress_type == zipfile.ZIP_STORED}\n"
      "print(json.dumps(out))\n");
  const std::string out = scratch + "/zipfile.json";
  const std::string cmd = "/usr/bin/python3 " + script + " " + zip + " > " + out;
  if (std::system(cmd.c_str()) != 0) return json();
  Result<std::string> text = ReadFile(out);
  return text ? json::parse(*text, nullptr, false) : json();
}

std::string Sha256(const std::string& path, const std::string& scratch) {
  const std::string out = scratch + "/sum.txt";
  const std::string cmd = "sha256sum " + path + " > " + out;
  if (std::system(cmd.c_str()) != 0) return "";
  Result<std::string> text = ReadFile(out);
  return text ? text->substr(0, 64) : "";
}

class ImageArchive : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = tmp_.path() + "/rock-9";
    // Two 3 MB "views" (several blocks each), small sidecars, an empty file.
    for (int v = 0; v < 2; ++v) {
      const std::string stem = dir_ + "/side1/view_00" + std::to_string(v);
      Write(stem + ".jpg", Noise(3 * 1024 * 1024 + 17 * v, 10 + v));
      Write(stem + ".json", "{\"view\": " + std::to_string(v) + "}");
      members_.push_back({stem + ".jpg", "side1/view_00" + std::to_string(v) + ".jpg"});
      members_.push_back({stem + ".json", "side1/view_00" + std::to_string(v) + ".json"});
    }
    Write(dir_ + "/side1/manifest.json", "");
    members_.push_back({dir_ + "/side1/manifest.json", "side1/manifest.json"});
    Write(dir_ + "/sample.json", "{\"id\": \"rock-9\"}");
    members_.insert(members_.begin(), {dir_ + "/sample.json", "sample.json"});
  }

  // Every member read back by zipfile is the file on disk.
  void ExpectSameFiles(const std::string& zip) {
    const json z = ReadWithZipfile(zip, tmp_.path());
    ASSERT_TRUE(z.is_object()) << "Python's zipfile could not read " << zip;
    EXPECT_TRUE(z["bad"].is_null()) << "CRC mismatch in " << z["bad"];
    ASSERT_EQ(z["members"].size(), members_.size());
    for (const ArchiveMember& m : members_) {
      ASSERT_TRUE(z["members"].contains(m.name)) << m.name;
      const json& got = z["members"][m.name];
      EXPECT_EQ(got["size"].get<int64_t>(),
                static_cast<int64_t>(std::filesystem::file_size(m.path)))
          << m.name;
      EXPECT_EQ(got["sha256"].get<std::string>(), Sha256(m.path, tmp_.path())) << m.name;
      EXPECT_TRUE(got["stored"].get<bool>()) << m.name << " was compressed";
    }
  }

  test::TempDir tmp_;
  std::string dir_;
  std::vector<ArchiveMember> members_;
};

TEST_F(ImageArchive, StreamedInSmallReadsIsTheFilesAndNeverWholeInMemory) {
  auto zip = ZipStream::Open(members_);
  ASSERT_TRUE(zip) << zip.error().ToString();
  std::string bytes;
  char buf[1000];  // smaller than any block: many reads per piece
  for (;;) {
    const ssize_t n = (*zip)->Read(buf, sizeof buf);
    ASSERT_GE(n, 0) << (*zip)->error();
    if (n == 0) break;
    bytes.append(buf, static_cast<size_t>(n));
  }
  EXPECT_EQ((*zip)->Read(buf, sizeof buf), 0) << "the end stays the end";
  uint64_t total = 0;
  for (const ArchiveMember& m : members_) total += std::filesystem::file_size(m.path);
  EXPECT_EQ((*zip)->data_bytes(), total);
  EXPECT_GT(bytes.size(), 6u * 1024 * 1024);
  // One block of data and a member header at most, not the 6 MB archive.
  EXPECT_LE((*zip)->peak_buffered(), ZipStream::kBlockBytes + 4096);
  Write(tmp_.path() + "/out.zip", bytes);
  ExpectSameFiles(tmp_.path() + "/out.zip");
}

TEST_F(ImageArchive, BadMembersAreRefusedBeforeAnyByteAndAFileThatShrinksCutsTheStream) {
  auto missing = members_;
  missing.push_back({dir_ + "/side1/view_009.jpg", "side1/view_009.jpg"});
  auto r = ZipStream::Open(missing);
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(r.error().message.find("view_009.jpg"), std::string::npos) << r.error().message;
  for (const std::string bad : {"../etc/passwd", "/abs.jpg", "", "sample.json"}) {
    auto named = members_;
    named.push_back({dir_ + "/sample.json", bad});
    r = ZipStream::Open(named);
    ASSERT_FALSE(r) << bad;
    EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument) << bad;
  }
  // A view cut short after the check (a disk error, a person with a shell):
  // the stream ends with an error, never with a member of the wrong size.
  auto zip = ZipStream::Open(members_);
  ASSERT_TRUE(zip);
  std::filesystem::resize_file(members_[1].path, 1000);
  char buf[4096];
  ssize_t n = 0;
  while ((n = (*zip)->Read(buf, sizeof buf)) > 0) {
  }
  EXPECT_EQ(n, -1);
  EXPECT_NE((*zip)->error().find("view_000.jpg"), std::string::npos) << (*zip)->error();
}

TEST_F(ImageArchive, ServedOverHttpAsAnAttachment) {
  FakeControl fake;
  fake.archives["rock-9"] = members_;
  HttpApi api(fake, "127.0.0.1", 0);
  ASSERT_TRUE(api.Start().ok());
  httplib::Client client("127.0.0.1", api.port());
  client.set_read_timeout(10, 0);
  auto res = client.Get("/api/v1/samples/rock-9/images.zip");
  ASSERT_TRUE(res);
  ASSERT_EQ(res->status, 200) << res->body;
  EXPECT_EQ(res->get_header_value("Content-Type"), "application/zip");
  EXPECT_EQ(res->get_header_value("Content-Disposition"),
            "attachment; filename=\"rock-9_images.zip\"");
  EXPECT_EQ(res->get_header_value("Transfer-Encoding"), "chunked");
  Write(tmp_.path() + "/http.zip", res->body);
  ExpectSameFiles(tmp_.path() + "/http.zip");

  // No such sample, a bad id, a sample whose file vanished: JSON errors.
  res = client.Get("/api/v1/samples/rock-10/images.zip");
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 404);
  EXPECT_NE(res->body.find("no sample rock-10"), std::string::npos) << res->body;
  res = client.Get("/api/v1/samples/..%2Fx/images.zip");
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 400);
  std::filesystem::remove(members_.back().path);
  res = client.Get("/api/v1/samples/rock-9/images.zip");
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 404);
  EXPECT_NE(res->body.find("manifest.json"), std::string::npos) << res->body;
  res = client.Post("/api/v1/samples/rock-9/images.zip", "", "application/json");
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 405);
  api.Stop();
}

}  // namespace
}  // namespace aggscan
