// A viewer of the server's stream for tests: a SUB socket on the stream endpoint that
// reads [topic, StreamMessage] messages, plus the decoding of bricks (int16 or float32,
// zstd or not) and of the whole-volume key into a Volume.
#pragma once

#include <catch2/catch.hpp>
#include <zstd.h>

#include <chrono>
#include <cstdint>
#include <cstring>
#include <functional>
#include <string>
#include <vector>
#include <zmq.hpp>

#include "core/volume.h"
#include "palpsim/wire.pb.h"

namespace palpsim::test {

/// A SUB socket on a stream endpoint.
struct StreamViewer {
  zmq::context_t ctx{1};
  zmq::socket_t sub{ctx, zmq::socket_type::sub};

  explicit StreamViewer(const std::string& endpoint) {
    sub.set(zmq::sockopt::linger, 0);
    sub.connect(endpoint);
  }
  void subscribe(const std::string& topic) { sub.set(zmq::sockopt::subscribe, topic); }
  void unsubscribe(const std::string& topic) { sub.set(zmq::sockopt::unsubscribe, topic); }

  /// The next message within `timeout_ms` (false when none came); its topic into `topic`.
  bool next(palpsim::v1::StreamMessage& m, std::string* topic = nullptr, int timeout_ms = 10000) {
    zmq::pollitem_t it[] = {{sub.handle(), 0, ZMQ_POLLIN, 0}};
    zmq::poll(it, 1, std::chrono::milliseconds(timeout_ms));
    if (!(it[0].revents & ZMQ_POLLIN)) return false;
    zmq::message_t t, body;
    (void)sub.recv(t);
    REQUIRE(sub.get(zmq::sockopt::rcvmore));
    (void)sub.recv(body);
    REQUIRE_FALSE(sub.get(zmq::sockopt::rcvmore));  // exactly two frames
    if (topic) *topic = t.to_string();
    REQUIRE(m.ParseFromArray(body.data(), int(body.size())));
    REQUIRE(m.schema_version() == 1);
    return true;
  }

  /// Reads messages until `pred` accepts one (true) or `timeout_s` passes (false).
  bool until(const std::function<bool(const palpsim::v1::StreamMessage&)>& pred, double timeout_s,
             palpsim::v1::StreamMessage* out = nullptr) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    palpsim::v1::StreamMessage m;
    while (std::chrono::steady_clock::now() < end) {
      if (!next(m, nullptr, 100)) continue;
      if (pred(m)) {
        if (out) *out = m;
        return true;
      }
    }
    return false;
  }
};

/// The values of a brick as floats (i fastest): int16 HU or float32, decompressed.
inline std::vector<float> brick_values(const palpsim::v1::Brick& b) {
  const std::size_t n = std::size_t(b.size_i()) * b.size_j() * b.size_k();
  std::string raw = b.data();
  if (b.compression() == palpsim::v1::COMPRESSION_ZSTD) {
    raw.assign(b.raw_bytes(), '\0');
    const std::size_t got = ZSTD_decompress(raw.data(), raw.size(), b.data().data(), b.data().size());
    REQUIRE_FALSE(ZSTD_isError(got));
    REQUIRE(got == b.raw_bytes());
  }
  std::vector<float> out(n);
  if (b.encoding() == palpsim::v1::BRICK_FLOAT32) {
    REQUIRE(raw.size() == n * sizeof(float));
    std::memcpy(out.data(), raw.data(), raw.size());
  } else {
    REQUIRE(raw.size() == n * sizeof(std::int16_t));
    for (std::size_t e = 0; e < n; ++e) {
      std::int16_t v;
      std::memcpy(&v, raw.data() + e * sizeof v, sizeof v);
      out[e] = v;
    }
  }
  return out;
}

/// Writes a brick's values into `v` (on the brick's grid) at the brick's box.
inline void paste_brick(const palpsim::v1::Brick& b, Volume<float>& v) {
  const std::vector<float> vals = brick_values(b);
  for (std::uint32_t k = 0; k < b.size_k(); ++k)
    for (std::uint32_t j = 0; j < b.size_j(); ++j)
      std::memcpy(&v.data[v.grid.index(b.lo_i(), b.lo_j() + j, b.lo_k() + k)],
                  &vals[(std::size_t(k) * b.size_j() + j) * b.size_i()], sizeof(float) * b.size_i());
}

}  // namespace palpsim::test
