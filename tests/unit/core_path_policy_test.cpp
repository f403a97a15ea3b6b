// The one resolver for files opened on a client's or a header's behalf (core/path_policy.h):
// regular files inside the allowed folders after links are resolved, nothing else, and a
// FIFO is never opened in a way that blocks.
#include <catch2/catch.hpp>

#include <sys/stat.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "core/error.h"
#include "core/path_policy.h"
#include "unit/prep_files.h"

using namespace palpsim;
using test::error_message;
namespace fs = std::filesystem;

namespace {

// allowed/ (s.txt, a link in.txt to it, a link out/ to other/, a FIFO) and other/ (s.txt)
struct Tree {
  test::TempDir d;
  fs::path allowed = d.path / "allowed", other = d.path / "other";
  Tree() {
    fs::create_directories(allowed);
    fs::create_directories(other);
    std::ofstream(allowed / "s.txt") << "0123456789";
    std::ofstream(other / "s.txt") << "secret";
    fs::create_symlink(allowed / "s.txt", allowed / "in.txt");
    fs::create_directory_symlink(other, allowed / "out");
    REQUIRE(::mkfifo((allowed / "pipe").c_str(), 0600) == 0);
  }
};

}  // namespace

TEST_CASE("the resolver admits files inside the folders and refuses every way out, saying only that it is out") {
  Tree t;
  const PathPolicy p({t.allowed.string()});
  CHECK(p.resolve((t.allowed / "s.txt").string(), "x") == fs::canonical(t.allowed / "s.txt").string());
  // a link that stays inside is followed
  CHECK(p.resolve((t.allowed / "in.txt").string(), "x") == fs::canonical(t.allowed / "s.txt").string());
  for (const fs::path& bad : {t.other / "s.txt", t.allowed / ".." / "other" / "s.txt", t.allowed / "out" / "s.txt",
                              t.other / "missing", fs::path("/etc/passwd")}) {
    INFO(bad);
    const std::string e = error_message([&] { p.resolve(bad.string(), "LoadScene: path"); });
    CHECK_THAT(e, Catch::Contains("LoadScene: path '" + bad.string() + "' lies outside the folders this server allows"));
    // whether a file outside exists is not told
    CHECK_THAT(e, !Catch::Contains("no such"));
    CHECK_FALSE(p.check(bad.string(), "x").empty());
  }
  CHECK_THAT(error_message([&] { p.resolve((t.allowed / "out" / "s.txt").string(), "x"); }),
             Catch::Contains("once its links are followed"));
  CHECK_THAT(error_message([&] { p.resolve((t.allowed / "missing").string(), "x"); }), Catch::Contains("no such file"));
  CHECK(p.check((t.allowed / "not-yet").string(), "x").empty());  // a folder to create (render.record_dir)
}

TEST_CASE("the resolver admits only the kind asked for: no folder as a file, no FIFO, no device, no NUL") {
  Tree t;
  const PathPolicy p({t.allowed.string()});
  const std::string dir = t.allowed.string();
  CHECK_THAT(error_message([&] { p.resolve(dir, "x"); }), Catch::Contains("is a folder, not a regular file"));
  CHECK(p.resolve(dir, "x", PathKind::kFolder) == fs::canonical(dir).string());
  CHECK(p.resolve(dir, "x", PathKind::kFileOrFolder) == fs::canonical(dir).string());
  CHECK_THAT(error_message([&] { p.resolve((t.allowed / "s.txt").string(), "x", PathKind::kFolder); }),
             Catch::Contains("not a folder"));
  const std::string pipe = (t.allowed / "pipe").string();
  CHECK_THAT(error_message([&] { p.resolve(pipe, "x"); }), Catch::Contains("FIFO"));
  CHECK_THAT(error_message([&] { p.resolve(pipe, "x", PathKind::kFileOrFolder); }), Catch::Contains("FIFO"));
  CHECK_THAT(error_message([&] { PathPolicy({"/dev"}).resolve("/dev/null", "x"); }), Catch::Contains("a device"));
  // the C library would open the part before a NUL
  const std::string nul = (t.allowed / "s.txt").string() + std::string(1, '\0') + "x";
  CHECK_THAT(error_message([&] { p.resolve(nul, "x"); }), Catch::Contains("NUL"));
  CHECK_THAT(p.check(nul, "x"), Catch::Contains("NUL"));
  CHECK_THAT(error_message([&] { p.resolve("", "LoadScene: path"); }), Catch::Contains("LoadScene: path is empty"));
}

TEST_CASE("without folders nothing is admitted, and a missing folder is refused at start, named") {
  Tree t;
  CHECK_THAT(error_message([&] { PathPolicy().resolve((t.allowed / "s.txt").string(), "x"); }),
             Catch::Contains("--scene-dir"));
  CHECK_THAT(error_message([&] { PathPolicy({(t.d.path / "missing").string()}); }),
             Catch::Contains("--scene-dir") && Catch::Contains((t.d.path / "missing").string()));
}

TEST_CASE("files are read only when regular, opened without blocking") {
  Tree t;
  CHECK(read_file_head((t.allowed / "s.txt").string(), 4, "x") == "0123");
  CHECK(read_file_head((t.allowed / "s.txt").string(), 100, "x") == "0123456789");
  // with no writer a blocking open of a FIFO would never return
  CHECK_THAT(error_message([&] { read_file_head((t.allowed / "pipe").string(), 100, "scene file"); }),
             Catch::Contains("scene file") && Catch::Contains("FIFO"));
  CHECK_THAT(error_message([&] { read_file_head(t.allowed.string(), 100, "x"); }), Catch::Contains("folder"));
  CHECK_THAT(error_message([&] { read_file_head((t.allowed / "missing").string(), 100, "x"); }),
             Catch::Contains("no such file"));
}
