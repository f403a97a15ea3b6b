// SHA-256 for the cache's content keys (the CT's bytes plus the settings).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>

namespace palpsim {

/// Incremental SHA-256 (FIPS 180-4).
class Sha256 {
 public:
  Sha256();
  /// Adds `n` bytes.
  void update(const void* data, std::size_t n);
  /// Adds a string's bytes followed by a 0 byte (so "ab","c" differs from "a","bc").
  void update_field(const std::string& s);
  /// Finishes and returns the digest as 64 lowercase hex characters.
  std::string hex();

 private:
  void block(const std::uint8_t* p);
  std::array<std::uint32_t, 8> h_;
  std::array<std::uint8_t, 64> buf_{};
  std::size_t used_ = 0;
  std::uint64_t bits_ = 0;
};

/// SHA-256 of a file's bytes, fed into `sha` (throws palpsim::Error if unreadable).
void hash_file(Sha256& sha, const std::string& path);

}  // namespace palpsim
