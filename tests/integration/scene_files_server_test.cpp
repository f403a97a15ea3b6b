// The files a client makes the real palpsim-server open through LoadScene (issue 26): a CT
// on which ITK would abort, a header naming a file outside --scene-dir, a scene choosing the
// cache folder, FIFOs, an empty scene, the folder itself and a path holding a NUL are each
// refused with one clear message, and the server keeps serving: Info answers after each.
#include <catch2/catch.hpp>

#include <sys/stat.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <string>
#include <zmq.hpp>

#include "palpsim/wire.pb.h"
#include "server_process.h"
#include "support/zmq_exchange.h"
#include "unit/prep_files.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
namespace fs = std::filesystem;

namespace {

// A healthy server answers in milliseconds (a small CT's preparation in well under a
// second); 5 s covers a loaded 2-core CI machine. A blocked or dead server never answers.
constexpr int kReplyMs = 5000;

// one control connection
class Control {
 public:
  explicit Control(const std::string& endpoint) : s_(ctx_, zmq::socket_type::dealer) {
    s_.set(zmq::sockopt::linger, 0);
    s_.connect(endpoint);
  }
  /// One request and its reply, or nothing within kReplyMs.
  std::optional<v1::ControlReply> call(v1::ControlRequest q) {
    q.set_schema_version(1);
    s_.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::dontwait);
    return test::reply_within<v1::ControlReply>(s_, kReplyMs);
  }
  /// LoadScene of a file path or of scene text; the reply (the test fails without one).
  v1::ControlReply load_path(const std::string& path) { return load(path, ""); }
  v1::ControlReply load_text(const std::string& text) { return load("", text); }
  /// The server's Info (the test fails without one: the server died or its control thread is stuck).
  v1::ServerInfo info() {
    v1::ControlRequest q;
    q.mutable_info();
    const auto r = call(q);
    REQUIRE(r);
    REQUIRE(r->has_info());
    return r->info();
  }

 private:
  zmq::context_t ctx_{1};
  zmq::socket_t s_;

  v1::ControlReply load(const std::string& path, const std::string& text) {
    v1::ControlRequest q;
    if (!path.empty()) q.mutable_load_scene()->set_path(path);
    if (!text.empty()) q.mutable_load_scene()->set_text(text);
    const auto r = call(q);
    INFO("LoadScene " << q.ShortDebugString());
    REQUIRE(r);
    return *r;
  }
};

// a scene folder with the starting scene (the phantom at 2 mm), and a folder beside it
struct Folders {
  test::TempDir root;
  fs::path scenes = root.path / "scenes", other = root.path / "other", cache = root.path / "cache";
  Folders() {
    fs::create_directories(scenes);
    fs::create_directories(other);
    std::ofstream(scenes / "start.textproto") << test::fast_scene_text("start", 10);
    // the operator's cache, so no test writes into the user's
    ::setenv("PALPSIM_CACHE", cache.c_str(), 1);
  }
  std::string scene(const std::string& name, const std::string& text) const {
    std::ofstream(scenes / name) << text;
    return (scenes / name).string();
  }
};

// the server on the folders' starting scene, LoadScene confined to `scenes`
std::unique_ptr<test::ServerProcess> start(const Folders& f, std::vector<std::string> extra = {}) {
  extra.insert(extra.begin(), {"--scene-dir", f.scenes.string()});
  auto s = std::make_unique<test::ServerProcess>((f.scenes / "start.textproto").string(), extra);
  const bool ready = s->wait_ready(120);
  INFO("server stderr:\n" << s->child().err());
  REQUIRE(ready);
  return s;
}

// the load was refused with a message holding every `says`, and the server still serves the
// starting scene
void refused(Control& c, const v1::ControlReply& r, const std::vector<std::string>& says) {
  INFO(r.ShortDebugString());
  CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
  for (const std::string& s : says) CHECK_THAT(r.error().message(), Catch::Contains(s));
  CHECK(r.error().message().find('\n') == std::string::npos);
  const v1::ServerInfo i = c.info();
  CHECK(i.scene_name() == "start");
  CHECK(i.scene_generation() == 1);
}

// a float torso (HU) as a detached NRRD: header `header` naming `data_text`, voxels in `data_path`
void detached_torso(const std::string& header, const std::string& data_text, const std::string& data_path) {
  const Volume<float> v = test::synthetic_torso({40, 32, 12}, {2, 2, 3});
  std::ofstream(header) << "NRRD0004\ntype: float\ndimension: 3\nsizes: 40 32 12\nspacings: 2 2 3\n"
                           "endian: little\nencoding: raw\ndata file: " << data_text << "\n";
  std::ofstream(data_path, std::ios::binary).write(reinterpret_cast<const char*>(v.data.data()), std::streamsize(v.bytes()));
}

}  // namespace

TEST_CASE("LoadScene of a CT whose spacing is NaN is refused, and the server keeps serving", "[integration][files]") {
  Folders f;
  const double sp[3] = {1, std::numeric_limits<double>::quiet_NaN(), 1};
  test::write_nifti_int16((f.scenes / "nan.nii").string(), 16, 16, 16, sp, std::vector<std::int16_t>(16 * 16 * 16, 40));
  const std::string scene = f.scene("nan.textproto", "name: \"nan\"\nct_path: \"nan.nii\"\n");
  auto server = start(f);
  Control c(server->control());
  // ITK's NIfTI reader would abort the whole server (VNL: matrix has non-finite elements)
  refused(c, c.load_path(scene), {"nan.nii", "pixdim[2]"});
  CHECK(server->child().wait(0) == -1);  // still running
}

TEST_CASE("a client's scene cannot choose the cache folder nor reach a file outside --scene-dir through a header",
          "[integration][files]") {
  Folders f;
  auto server = start(f);
  Control c(server->control());
  // the cache folder is the operator's
  const fs::path evil = f.other / "evil-cache";
  refused(c, c.load_text("name: \"c\"\nphantom { voxel_mm: 2 }\nprep { cache_dir: \"" + evil.string() + "\" }\n"),
          {"prep.cache_dir", "operator"});
  CHECK_FALSE(fs::exists(evil));
  // voxels of another folder named by a header inside: absolutely, by "..", through a link; NRRD and MetaImage
  detached_torso((f.scenes / "abs.nhdr").string(), (f.other / "t.raw").string(), (f.other / "t.raw").string());
  detached_torso((f.scenes / "up.nhdr").string(), "../other/t.raw", (f.other / "t.raw").string());
  fs::create_symlink(f.other / "t.raw", f.scenes / "link.raw");
  detached_torso((f.scenes / "link.nhdr").string(), "link.raw", (f.other / "t.raw").string());
  std::ofstream(f.scenes / "abs.mhd") << "ObjectType = Image\nNDims = 3\nDimSize = 40 32 12\nElementSpacing = 2 2 3\n"
                                         "ElementType = MET_FLOAT\nElementDataFile = " << (f.other / "t.raw").string() << "\n";
  for (const char* ct : {"abs.nhdr", "up.nhdr", "link.nhdr", "abs.mhd"}) {
    const std::string scene = f.scene(std::string(ct) + ".textproto", "name: \"x\"\nct_path: \"" + std::string(ct) + "\"\n");
    refused(c, c.load_path(scene), {ct, "data file", "outside the folders this server allows"});
  }
}

TEST_CASE("a FIFO as the scene, the CT or a header's data file is refused at once", "[integration][files]") {
  Folders f;
  for (const char* p : {"pipe.textproto", "pipe.nii", "pipe.raw"}) REQUIRE(::mkfifo((f.scenes / p).c_str(), 0600) == 0);
  std::ofstream(f.scenes / "pipe.nhdr") << "NRRD0004\ntype: float\ndimension: 3\nsizes: 16 16 16\nspacings: 1 1 1\n"
                                           "endian: little\nencoding: raw\ndata file: pipe.raw\n";
  auto server = start(f);
  Control c(server->control());
  // a blocking open() of a FIFO without a writer never returns: no Info, no OpenSession for anyone
  refused(c, c.load_path((f.scenes / "pipe.textproto").string()), {"pipe.textproto", "FIFO"});
  refused(c, c.load_path(f.scene("a.textproto", "name: \"a\"\nct_path: \"pipe.nii\"\n")), {"pipe.nii", "FIFO"});
  refused(c, c.load_path(f.scene("b.textproto", "name: \"b\"\nct_path: \"pipe.nhdr\"\n")), {"pipe.raw", "FIFO"});
}

TEST_CASE("an empty scene, the scene folder itself and a path holding a NUL are refused", "[integration][files]") {
  Folders f;
  const std::string good = f.scene("good.textproto", "name: \"good\"\nphantom { voxel_mm: 2 }\n");
  auto server = start(f);
  Control c(server->control());
  refused(c, c.load_path(f.scene("empty.textproto", "")), {"empty.textproto", "empty"});
  refused(c, c.load_path(f.scene("blank.textproto", "\n# nothing\n")), {"blank.textproto", "empty"});
  refused(c, c.load_text("  \n"), {"empty"});
  refused(c, c.load_path(f.scenes.string()), {"folder"});
  // the part before the NUL names a good scene, which must not be loaded
  refused(c, c.load_path(good + std::string(1, '\0') + ".evil"), {"NUL"});
  // the good scene itself loads
  const v1::ControlReply r = c.load_path(good);
  CHECK(r.error().code() == v1::ERROR_NONE);
  CHECK(c.info().scene_name() == "good");
}

TEST_CASE("a scene whose elastic model is bad is refused naming the field, and the server keeps serving",
          "[integration][files]") {
  Folders f;
  auto server = start(f);
  Control c(server->control());
  auto elastic_scene = [](const std::string& elastic) {
    return "name: \"elastic\"\nphantom { voxel_mm: 2 }\neffects { chainmail: true relaxation: true }\n"
           "deform { relax_method: \"elastic\" grab_radius_mm: 5 backend: \"cpu\" elastic { " + elastic + " } }\n";
  };
  // E <= 0, nu outside (0, 0.5), an unsorted and an empty table: as text and as a file
  refused(c, c.load_text(elastic_scene("modulus { point { hu: -100 e_kpa: 3 } point { hu: 20 e_kpa: 0 } }")),
          {"LoadScene", "deform.elastic.modulus.point[1].e_kpa", "above 0"});
  refused(c, c.load_text(elastic_scene("skin_e_kpa: -1")), {"deform.elastic.skin_e_kpa"});
  refused(c, c.load_text(elastic_scene("poisson: 0.5")), {"deform.elastic.poisson", "(0, 0.5)"});
  refused(c, c.load_text(elastic_scene("poisson: 0")), {"deform.elastic.poisson", "(0, 0.5)"});
  refused(c, c.load_text(elastic_scene("modulus { point { hu: 20 e_kpa: 12 } point { hu: -100 e_kpa: 3 } }")),
          {"deform.elastic.modulus.point[1].hu", "sorted"});
  refused(c, c.load_path(f.scene("empty-table.textproto", elastic_scene("modulus { }"))),
          {"empty-table.textproto", "deform.elastic.modulus is empty"});
  // poses are answered all along: a session opened now is served
  v1::ControlRequest open;
  open.mutable_open()->set_client_name("after refusals");
  const auto o = c.call(open);
  REQUIRE(o);
  CHECK(o->error().code() == v1::ERROR_NONE);
  CHECK(o->open().session_id() != 0);
  // and a good elastic scene loads
  const v1::ControlReply r = c.load_text(elastic_scene("poisson: 0.49"));
  INFO(r.ShortDebugString());
  CHECK(r.error().code() == v1::ERROR_NONE);
  CHECK(c.info().scene_name() == "elastic");
}

TEST_CASE("a CT scene inside --scene-dir loads, its patient cached in the operator's --cache-dir",
          "[integration][files]") {
  Folders f;
  const fs::path cache = f.root.path / "operator-cache";
  fs::create_directories(f.scenes / "ct");
  fs::create_directories(f.scenes / "raw");
  detached_torso((f.scenes / "ct/torso.nhdr").string(), "../raw/torso.raw", (f.scenes / "raw/torso.raw").string());
  const std::string scene = f.scene("torso.textproto", "name: \"torso\"\nct_path: \"ct/torso.nhdr\"\n");
  auto server = start(f, {"--cache-dir", cache.string()});
  Control c(server->control());
  const v1::ControlReply r = c.load_path(scene);
  INFO(r.ShortDebugString());
  CHECK(r.error().code() == v1::ERROR_NONE);
  const v1::ServerInfo i = c.info();
  CHECK(i.scene_name() == "torso");
  CHECK(i.scene_generation() == 2);
  // two entries in the operator's cache (the starting phantom's and the torso's), none in the environment's
  CHECK(std::distance(fs::directory_iterator(cache), fs::directory_iterator{}) == 2);
  CHECK_FALSE(fs::exists(f.cache));
}

TEST_CASE("the server's log names each scene it serves with its file and its CT", "[integration][files]") {
  // a scene copied to another CT keeps its name; the file and the CT beside it tell the
  // copies apart in every line that names the scene (the start, ready and LoadScene lines)
  Folders f;
  fs::create_directories(f.scenes / "ct");
  detached_torso((f.scenes / "ct/torso.nhdr").string(), "torso.raw", (f.scenes / "ct/torso.raw").string());
  const std::string scene = f.scene("copy.textproto", "name: \"start\"\nct_path: \"ct/torso.nhdr\"\n");
  auto server = start(f);
  Control c(server->control());
  CHECK(c.load_path(scene).error().code() == v1::ERROR_NONE);
  const std::string start_file = (f.scenes / "start.textproto").string();
  const std::string log = server->child().out() + server->child().err();
  INFO(log);
  CHECK_THAT(log, Catch::Contains("scene 'start' (" + start_file + ", phantom)"));
  CHECK_THAT(log, Catch::Contains("now serving scene 'start' (" + scene + ", CT " + (f.scenes / "ct/torso.nhdr").string()));
}
