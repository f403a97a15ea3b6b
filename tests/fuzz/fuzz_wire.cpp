// libFuzzer target: wire messages through the server's control and pose handlers, on an
// in-process palpsim-server (net::Server on ipc:// sockets, haptics on a synthetic patient).
//
// An input is a sequence of at most 32 messages, each [kind: 1 byte][length: 2 bytes,
// little-endian][payload]. Bit 0 of kind is the socket (0 poses, 1 control); bits 1-2 the
// frames: 0 the payload alone (a DEALER), 1 an empty delimiter then the payload (a REQ), 2
// the payload cut in two frames, 3 an empty frame alone. A session id of 1 in a payload
// that parses stands for the newest session this input opened (the fuzzer cannot guess the
// server's random ids). Each input talks on connections of its own, and the sessions it
// opened are closed after it.
//
// Every message must get exactly one reply (after the delimiter it sent, for a REQ's), which
// parses, and which echoes the request's id (control) or seq (poses) when the request
// parsed. A missing or wrong reply aborts (a finding), as does a crash, an ASan or UBSan
// report or an uncaught exception in any of the server's threads.
#include <spdlog/spdlog.h>

#include <google/protobuf/stubs/logging.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>
#include <zmq.hpp>

#include "core/error.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "net/wire_limits.h"
#include "palpsim/wire.pb.h"
#include "support/synthetic_patient.h"

namespace v1 = palpsim::v1;

namespace {

// the stand-in for "the newest session this input opened"
constexpr std::uint64_t kNewestSession = 1;
// how long a reply may take (ASan makes a LoadScene's synthetic patient slow) before it is missing
constexpr int kReplyTimeoutMs = 10000;

// the server, made once for the whole run: haptics on the 60 mm slab; a LoadScene's scene
// is served when it asks for haptics only (frames or deformation would start EGL or the
// deformation worker in the fuzzer), else refused as the real server refuses a scene
struct Fuzzed {
  std::string control;
  std::unique_ptr<palpsim::net::Server> server;
  zmq::context_t ctx{1};

  Fuzzed() {
    // every refusal is logged, and protobuf logs strings that are not UTF-8: the fuzzer makes millions
    spdlog::set_level(spdlog::level::off);
    google::protobuf::SetLogHandler(nullptr);
    palpsim::net::ServerOptions o;
    o.control_bind = "ipc:///tmp/palpsim-fuzz-wire-" + std::to_string(::getpid());
    o.pose_priority = 0;
    o.background_idle = false;
    auto loader = [](const palpsim::Scene& s) -> palpsim::PatientPtr {
      const auto& e = s.effects;
      if (e.chainmail || e.relaxation || e.inversion || e.frames || e.bricks)
        throw palpsim::Error("scene '" + s.name + "': the wire fuzzer serves haptics only");
      return palpsim::test::slab_patient();
    };
    server = std::make_unique<palpsim::net::Server>(palpsim::default_scene(), palpsim::test::slab_patient(), loader, o);
    server->start();
    control = server->control_endpoint();
  }
};

[[noreturn]] void finding(const std::string& what) {
  std::fprintf(stderr, "fuzz_wire: %s\n", what.c_str());
  std::abort();
}

// session id 1 in a request that parses becomes `newest`
template <class Message>
bool substitute(Message& m, std::uint64_t newest);

template <>
bool substitute(v1::PoseRequest& q, std::uint64_t newest) {
  if (q.session_id() != kNewestSession || newest == 0) return false;
  q.set_session_id(newest);
  return true;
}

template <>
bool substitute(v1::ControlRequest& q, std::uint64_t newest) {
  if (newest == 0) return false;
  bool changed = false;
  auto fix = [&](auto* body) {
    if (body->session_id() == kNewestSession) {
      body->set_session_id(newest);
      changed = true;
    }
  };
  if (q.has_close()) fix(q.mutable_close());
  if (q.has_reset()) fix(q.mutable_reset());
  if (q.has_set_parameter()) fix(q.mutable_set_parameter());
  if (q.has_stats()) fix(q.mutable_stats());
  if (q.has_watch()) fix(q.mutable_watch());
  return changed;
}

// the reply to the message just sent on `s`: its frames
std::vector<zmq::message_t> reply_frames(zmq::socket_t& s) {
  zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}};
  const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(kReplyTimeoutMs);
  // libFuzzer's timer signal (-timeout) interrupts the wait now and then
  while (!(items[0].revents & ZMQ_POLLIN) && std::chrono::steady_clock::now() < end) {
    try {
      zmq::poll(items, 1, std::chrono::duration_cast<std::chrono::milliseconds>(end - std::chrono::steady_clock::now()));
    } catch (const zmq::error_t& e) {
      if (e.num() != EINTR) throw;
    }
  }
  if (!(items[0].revents & ZMQ_POLLIN)) finding("no reply within " + std::to_string(kReplyTimeoutMs) + " ms");
  std::vector<zmq::message_t> frames;
  do {
    frames.emplace_back();
    (void)s.recv(frames.back());
  } while (s.get(zmq::sockopt::rcvmore));
  return frames;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static Fuzzed f;
  zmq::socket_t pose(f.ctx, zmq::socket_type::dealer), ctl(f.ctx, zmq::socket_type::dealer);
  for (zmq::socket_t* s : {&pose, &ctl}) s->set(zmq::sockopt::linger, 0);
  pose.connect(f.server->pose_endpoint());
  ctl.connect(f.control);
  std::uint64_t newest = 0;
  std::vector<std::uint64_t> opened;
  std::size_t at = 0;
  for (int n = 0; n < 32 && at + 3 <= size; ++n) {
    const int kind = data[at];
    const std::size_t len = std::min<std::size_t>(data[at + 1] | (std::size_t(data[at + 2]) << 8), size - at - 3);
    std::string payload(reinterpret_cast<const char*>(data) + at + 3, len);
    at += 3 + len;
    const bool to_control = kind & 1;
    const int framing = (kind >> 1) & 3;
    zmq::socket_t& s = to_control ? ctl : pose;
    // a request the server reads is a single frame, or an empty delimiter and one frame (a REQ's)
    v1::ControlRequest cq;
    v1::PoseRequest pq;
    const bool whole = framing == 0 || framing == 1;
    const bool parsed = whole && (to_control ? cq.ParseFromString(payload)
                                             : payload.size() <= palpsim::net::kMaxPoseBytes && pq.ParseFromString(payload));
    if (parsed && (to_control ? substitute(cq, newest) : substitute(pq, newest)))
      payload = to_control ? cq.SerializeAsString() : pq.SerializeAsString();
    std::vector<std::string> sent;
    if (framing == 0) sent = {payload};
    else if (framing == 1) sent = {"", payload};
    else if (framing == 2) sent = {payload.substr(0, payload.size() / 2), payload.substr(payload.size() / 2)};
    else sent = {""};
    for (std::size_t i = 0; i < sent.size(); ++i)
      s.send(zmq::buffer(sent[i]), i + 1 < sent.size() ? zmq::send_flags::sndmore : zmq::send_flags::none);
    // one reply, after the delimiter echoed when the message began with one (PROTOCOL.md)
    const bool envelope = sent.size() >= 2 && sent[0].empty();
    std::vector<zmq::message_t> frames = reply_frames(s);
    if (frames.size() != (envelope ? 2u : 1u))
      finding("a reply of " + std::to_string(frames.size()) + " frames to a message of " + std::to_string(sent.size()) +
              (envelope ? " beginning with a delimiter" : ""));
    if (envelope && frames[0].size() != 0) finding("a REQ's delimiter not echoed");
    const zmq::message_t& body = frames.back();
    const bool readable = parsed && (framing == 1 || !payload.empty());
    if (to_control) {
      v1::ControlReply r;
      if (!r.ParseFromArray(body.data(), int(body.size()))) finding("a control reply that does not parse");
      if (readable && r.request_id() != cq.request_id()) finding("a control reply with another request id");
      if (r.has_open()) {
        newest = r.open().session_id();
        opened.push_back(newest);
      }
    } else {
      v1::PoseReply r;
      if (!r.ParseFromArray(body.data(), int(body.size()))) finding("a pose reply that does not parse");
      if (readable && r.seq() != pq.seq()) finding("a pose reply with another seq");
    }
  }
  // the sessions this input opened are closed, so that later inputs find free ones
  for (const std::uint64_t id : opened) {
    v1::ControlRequest q;
    q.set_schema_version(v1::VERSION_CURRENT);
    q.mutable_close()->set_session_id(id);
    ctl.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::none);
    reply_frames(ctl);
  }
  return 0;
}
