#include "prep/cache.h"

#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include "core/error.h"

namespace palpsim {
namespace {

namespace fs = std::filesystem;
constexpr char kMagic[8] = {'P', 'A', 'L', 'P', 'P', 'A', 'T', '\n'};

// a fast 64-bit checksum over the entry's bytes (detects truncation and corruption)
struct Checksum {
  std::uint64_t h = 0x9e3779b97f4a7c15ull;
  void add(const void* data, std::size_t n) {
    const auto* p = static_cast<const unsigned char*>(data);
    std::size_t i = 0;
    for (; i + 8 <= n; i += 8) {
      std::uint64_t w;
      std::memcpy(&w, p + i, 8);
      mix(w);
    }
    std::uint64_t tail = n;
    for (; i < n; ++i) tail = (tail << 8) | p[i];
    mix(tail);
  }
  void mix(std::uint64_t w) {
    w *= 0x87c37b91114253d5ull;
    w = (w << 31) | (w >> 33);
    h ^= w * 0x4cf5ad432745937full;
    h = ((h << 27) | (h >> 37)) * 5 + 0x52dce729;
  }
};

// writes and checksums one block
struct Writer {
  std::ofstream out;
  Checksum sum;
  void put(const void* d, std::size_t n) {
    out.write(static_cast<const char*>(d), std::streamsize(n));
    sum.add(d, n);
  }
  template <typename T>
  void pod(const T& v) { put(&v, sizeof(T)); }
};

// reads and checksums one block; false at a short read
struct Reader {
  std::ifstream in;
  Checksum sum;
  bool get(void* d, std::size_t n) {
    in.read(static_cast<char*>(d), std::streamsize(n));
    if (!in || std::size_t(in.gcount()) != n) return false;
    sum.add(d, n);
    return true;
  }
  template <typename T>
  bool pod(T& v) { return get(&v, sizeof(T)); }
};

bool read_entry(const fs::path& dir, Patient& p, std::string& json) {
  Reader r;
  r.in.open(dir / "patient.bin", std::ios::binary);
  if (!r.in) return false;
  char magic[8];
  std::int32_t version = 0;
  if (!r.get(magic, 8) || std::memcmp(magic, kMagic, 8) != 0 || !r.pod(version) || version != kPrepFormatVersion)
    return false;
  Grid g;
  std::int32_t size[3];
  double sp[3], org[3];
  if (!r.get(size, sizeof size) || !r.get(sp, sizeof sp) || !r.get(org, sizeof org) ||
      !r.get(g.direction.data(), sizeof(double) * 9))
    return false;
  for (int a = 0; a < 3; ++a)
    if (size[a] <= 0 || size[a] > 100000 || !(sp[a] > 0)) return false;
  g.size = {size[0], size[1], size[2]};
  g.spacing_mm = {sp[0], sp[1], sp[2]};
  g.origin_mm = {org[0], org[1], org[2]};
  std::uint8_t has_bone = 0;
  std::uint32_t source_len = 0;
  if (!r.pod(has_bone) || !r.pod(source_len) || source_len > 65536) return false;
  p.source.resize(source_len);
  if (!r.get(p.source.data(), source_len)) return false;
  p.grid = g;
  p.has_bone = has_bone != 0;
  p.intensity = Volume<float>(g);
  p.body = Volume<std::uint8_t>(g);
  p.bone = Volume<std::uint8_t>(g);
  p.dist_bone_mm = Volume<float>(g);
  p.dist_skin_mm = Volume<float>(g);
  if (!r.get(p.intensity.data.data(), p.intensity.bytes()) || !r.get(p.body.data.data(), p.body.bytes()) ||
      !r.get(p.bone.data.data(), p.bone.bytes()) || !r.get(p.dist_bone_mm.data.data(), p.dist_bone_mm.bytes()) ||
      !r.get(p.dist_skin_mm.data.data(), p.dist_skin_mm.bytes()))
    return false;
  // the stored checksum must match, and nothing may follow it
  const std::uint64_t expect = r.sum.h;
  std::uint64_t stored = 0;
  r.in.read(reinterpret_cast<char*>(&stored), sizeof stored);
  if (!r.in || stored != expect || r.in.peek() != std::char_traits<char>::eof()) return false;
  std::ifstream j(dir / "prep.json");
  if (!j) return false;
  std::ostringstream s;
  s << j.rdbuf();
  json = s.str();
  while (!json.empty() && (json.back() == '\n' || json.back() == ' ')) json.pop_back();
  return !json.empty();
}

}  // namespace

std::string cache_root(const PrepSettings& prep) {
  if (!prep.cache_dir.empty()) return prep.cache_dir;
  if (const char* env = std::getenv("PALPSIM_CACHE"); env && *env) return env;
  if (const char* home = std::getenv("HOME"); home && *home) return std::string(home) + "/.cache/palpsim";
  return (fs::temp_directory_path() / "palpsim-cache").string();
}

bool load_cached_patient(const std::string& entry_dir, Patient& p, std::string& json) {
  std::error_code ec;
  if (!fs::is_directory(entry_dir, ec)) return false;
  if (read_entry(entry_dir, p, json)) return true;
  // corrupt or of another format: drop it so it is rebuilt
  p = Patient{};
  fs::remove_all(entry_dir, ec);
  return false;
}

std::string store_cached_patient(const std::string& root, const std::string& key, const Patient& p,
                                 const std::string& json) {
  std::error_code ec;
  fs::create_directories(root, ec);
  if (ec) throw Error("cannot create the cache folder '" + root + "': " + ec.message());
  const fs::path entry = fs::path(root) / key;
  std::mt19937_64 rng(std::random_device{}());
  const fs::path tmp =
      fs::path(root) / (".tmp-" + key.substr(0, 16) + "-" + std::to_string(::getpid()) + "-" + std::to_string(rng()));
  fs::create_directory(tmp, ec);
  if (ec) throw Error("cannot create the cache folder '" + tmp.string() + "': " + ec.message());
  try {
    Writer w;
    w.out.open(tmp / "patient.bin", std::ios::binary);
    if (!w.out) throw Error("cannot create '" + (tmp / "patient.bin").string() + "'");
    const Grid& g = p.grid;
    const std::int32_t version = kPrepFormatVersion, size[3] = {g.size.x, g.size.y, g.size.z};
    const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z},
                 org[3] = {g.origin_mm.x, g.origin_mm.y, g.origin_mm.z};
    w.put(kMagic, 8);
    w.pod(version);
    w.put(size, sizeof size);
    w.put(sp, sizeof sp);
    w.put(org, sizeof org);
    w.put(g.direction.data(), sizeof(double) * 9);
    w.pod(std::uint8_t(p.has_bone));
    w.pod(std::uint32_t(p.source.size()));
    w.put(p.source.data(), p.source.size());
    w.put(p.intensity.data.data(), p.intensity.bytes());
    w.put(p.body.data.data(), p.body.bytes());
    w.put(p.bone.data.data(), p.bone.bytes());
    w.put(p.dist_bone_mm.data.data(), p.dist_bone_mm.bytes());
    w.put(p.dist_skin_mm.data.data(), p.dist_skin_mm.bytes());
    const std::uint64_t sum = w.sum.h;
    w.out.write(reinterpret_cast<const char*>(&sum), sizeof sum);
    w.out.close();
    if (!w.out) throw Error("error writing '" + (tmp / "patient.bin").string() + "' (disk full?)");
    std::ofstream j(tmp / "prep.json");
    j << json << "\n";
    j.close();
    if (!j) throw Error("error writing '" + (tmp / "prep.json").string() + "'");
    // publish: the rename is atomic; if another process was first, keep its entry
    fs::rename(tmp, entry, ec);
    if (ec) fs::remove_all(tmp, ec);
  } catch (...) {
    fs::remove_all(tmp, ec);
    throw;
  }
  return entry.string();
}

}  // namespace palpsim
