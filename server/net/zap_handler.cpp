#include "net/zap_handler.h"

#include <spdlog/spdlog.h>
#include <zmq.h>

#include <vector>

#include "core/error.h"
#include "core/thread.h"

namespace palpsim::net {
namespace {

// how often the handler's thread looks at its stop flag (ms)
constexpr int kPollMs = 100;

// the z85 text of a 32-byte binary key
std::string z85_of(const zmq::message_t& key) {
  char out[41] = {};
  if (key.size() != 32 || !zmq_z85_encode(out, static_cast<const std::uint8_t*>(key.data()), 32)) return "";
  return out;
}

}  // namespace

void make_curve_server(zmq::socket_t& s, const std::string& secret_z85) {
  s.set(zmq::sockopt::curve_server, 1);
  s.set(zmq::sockopt::curve_secretkey, secret_z85);
  s.set(zmq::sockopt::zap_domain, kZapDomain);
}

ZapHandler::ZapHandler(zmq::context_t& ctx, std::shared_ptr<const AllowList> allowed,
                       std::atomic<std::uint64_t>& refused, std::atomic<std::uint64_t>& admitted)
    : socket_(ctx, zmq::socket_type::rep), allowed_(std::move(allowed)), refused_(refused), admitted_(admitted) {
  socket_.set(zmq::sockopt::linger, 0);
  try {
    socket_.bind("inproc://zeromq.zap.01");
  } catch (const zmq::error_t& e) {
    throw Error(std::string("ZAP handler: cannot bind inproc://zeromq.zap.01: ") + e.what());
  }
  thread_ = std::thread([this] {
    name_this_thread("palpsim-zap");
    run();
  });
}

ZapHandler::~ZapHandler() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
  socket_.close();
}

void ZapHandler::run() {
  zmq::pollitem_t items[] = {{socket_.handle(), 0, ZMQ_POLLIN, 0}};
  std::vector<zmq::message_t> req;
  while (!stop_.load()) {
    zmq::poll(items, 1, std::chrono::milliseconds(kPollMs));
    if (!(items[0].revents & ZMQ_POLLIN)) continue;
    // a request: version, request id, domain, address, routing id, mechanism, credentials...
    req.clear();
    do {
      req.emplace_back();
      (void)socket_.recv(req.back());
    } while (socket_.get(zmq::sockopt::rcvmore));
    const auto text = [&](std::size_t i) { return i < req.size() ? req[i].to_string() : std::string(); };
    std::string status = "400", why, user;
    if (req.size() < 6 || text(0) != "1.0") {
      why = "malformed ZAP request";
    } else if (text(2) != kZapDomain || text(5) != "CURVE" || req.size() < 7) {
      why = "mechanism " + text(5) + " in domain '" + text(2) + "': only CURVE is served";
    } else {
      user = z85_of(req[6]);
      if (!user.empty() && allowed_->count(user)) {
        status = "200";
        why = "OK";
      } else {
        why = "client key " + user + " is not on the allow-list";
      }
    }
    if (status == "200") {
      admitted_.fetch_add(1);
      spdlog::debug("ZAP: admitted {} from {}", user, text(3));
    } else {
      refused_.fetch_add(1);
      user.clear();
      spdlog::debug("ZAP: refused {}: {}", text(3), why);
    }
    // the reply: version, request id, status code and text, user id, metadata
    const std::string reply[] = {"1.0", text(1), status, why, user, ""};
    for (std::size_t i = 0; i < 6; ++i)
      socket_.send(zmq::buffer(reply[i]), i < 5 ? zmq::send_flags::sndmore : zmq::send_flags::none);
  }
}

}  // namespace palpsim::net
