#include "control_link.h"

#include <algorithm>
#include <chrono>
#include <stdexcept>

#include "net/curve_keys.h"

namespace palpsim::haptic {

ControlLink::ControlLink(zmq::context_t& ctx, std::string address, std::function<void(zmq::socket_t&)> setup,
                         bool curve)
    : ctx_(ctx), address_(std::move(address)), setup_(std::move(setup)), curve_(curve) {}

zmq::socket_t& ControlLink::socket() {
  if (!socket_) {
    socket_ = std::make_unique<zmq::socket_t>(ctx_, zmq::socket_type::req);
    socket_->set(zmq::sockopt::linger, 0);
    if (setup_) setup_(*socket_);
    socket_->connect(address_);
    waiting_ = false;
  }
  return *socket_;
}

zmq::socket_t& ControlLink::ready_socket() {
  if (waiting_) socket_.reset();
  return socket();
}

v1::ControlReply ControlLink::call(const v1::ControlRequest& request, int timeout_ms) {
  using Clock = std::chrono::steady_clock;
  const auto end = Clock::now() + std::chrono::milliseconds(timeout_ms);
  const std::string silent = "no reply from a palpsim-server at " + address_ + " within " + std::to_string(timeout_ms) +
                             " ms" + (curve_ ? net::kCurveSilenceHint : net::kPlainSilenceHint);
  zmq::socket_t& s = ready_socket();
  // the send waits for a connection at most until the deadline (a refused handshake leaves none)
  s.set(zmq::sockopt::sndtimeo, timeout_ms);
  if (!s.send(zmq::buffer(request.SerializeAsString()), zmq::send_flags::none)) throw std::runtime_error(silent);
  waiting_ = true;
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(end - Clock::now());
  zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::poll(items, 1, std::max(left, std::chrono::milliseconds(0)));
  v1::ControlReply reply;
  bool parsed = false;
  if (!take(reply, &parsed)) throw std::runtime_error(silent);
  if (!parsed) throw std::runtime_error(address_ + ": a control reply that does not parse");
  if (reply.has_error() && reply.error().code() != v1::ERROR_NONE)
    throw std::runtime_error(address_ + ": " + v1::ErrorCode_Name(reply.error().code()) + ": " + reply.error().message());
  return reply;
}

bool ControlLink::start(const v1::ControlRequest& request) {
  zmq::socket_t& s = ready_socket();
  if (!s.send(zmq::buffer(request.SerializeAsString()), zmq::send_flags::dontwait)) {
    // no connection to queue it on (refused in the handshake): the next request tries a fresh socket
    socket_.reset();
    return false;
  }
  waiting_ = true;
  return true;
}

bool ControlLink::take(v1::ControlReply& reply, bool* parsed) {
  if (!waiting_ || !socket_) return false;
  zmq::message_t m;
  if (!socket_->recv(m, zmq::recv_flags::dontwait)) return false;
  waiting_ = false;
  const bool ok = reply.ParseFromArray(m.data(), int(m.size()));
  if (!ok) reply.Clear();
  if (parsed) *parsed = ok;
  return true;
}

}  // namespace palpsim::haptic
