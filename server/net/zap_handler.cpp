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

// seconds on the steady clock
double steady_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// at most this many characters of a ZAP frame go into a log line
constexpr std::size_t kMaxLoggedChars = 64;

}  // namespace

std::string RefusalLog::refused(const std::string& address, const std::string& key, const std::string& why,
                                double now_s) {
  const std::string addr = address.empty() ? std::string("an unnamed peer") : address.substr(0, kMaxLoggedChars);
  const std::string who = key.empty() ? std::string("no client key") : "client key " + key;
  // quiet for a period: this one at once
  if (peers_.empty() && others_ == 0 && (!logged_ || now_s - last_line_s_ >= period_s_)) {
    logged_ = true;
    last_line_s_ = now_s;
    char period[32];
    std::snprintf(period, sizeof period, "%g", period_s_);
    return "CURVE: refused a connection from " + addr + ", " + who + ": " + why +
           " (further refusals are summarised every " + period + " s at most)";
  }
  for (Peer& p : peers_)
    if (p.address == addr && p.key == key) {
      ++p.count;
      return flush(now_s);
    }
  if (peers_.size() < max_peers_)
    peers_.push_back({addr, key, why, 1});
  else
    ++others_;
  return flush(now_s);
}

std::string RefusalLog::flush(double now_s, bool force) {
  if (peers_.empty() && others_ == 0) return "";
  if (!force && logged_ && now_s - last_line_s_ < period_s_) return "";
  std::uint64_t total = others_;
  for (const Peer& p : peers_) total += p.count;
  char head[96];
  std::snprintf(head, sizeof head, "CURVE: refused %llu more connection%s in %.1f s: ", (unsigned long long)total,
                total == 1 ? "" : "s", logged_ ? now_s - last_line_s_ : 0.0);
  std::string line = head;
  for (std::size_t i = 0; i < peers_.size(); ++i) {
    const Peer& p = peers_[i];
    line += (i ? "; " : "") + p.address + " " + (p.key.empty() ? std::string("no client key") : "key " + p.key) +
            " x" + std::to_string(p.count) + " (" + p.why + ")";
  }
  if (others_) line += "; " + std::to_string(others_) + " from other peers";
  peers_.clear();
  others_ = 0;
  logged_ = true;
  last_line_s_ = now_s;
  return line;
}

void make_curve_server(zmq::socket_t& s, const std::string& secret_z85) {
  s.set(zmq::sockopt::curve_server, 1);
  s.set(zmq::sockopt::curve_secretkey, secret_z85);
  s.set(zmq::sockopt::zap_domain, kZapDomain);
}

ZapHandler::ZapHandler(zmq::context_t& ctx, std::shared_ptr<const AllowList> allowed,
                       std::atomic<std::uint64_t>& refused, std::atomic<std::uint64_t>& admitted, double log_period_s)
    : socket_(ctx, zmq::socket_type::rep),
      allowed_(std::move(allowed)),
      refused_(refused),
      admitted_(admitted),
      log_(log_period_s) {
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
    // the refusals counted since the last line, once its period has passed
    if (const std::string line = log_.flush(steady_s()); !line.empty()) spdlog::warn("{}", line);
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
      why = "mechanism " + text(5).substr(0, kMaxLoggedChars) + " in domain '" + text(2).substr(0, kMaxLoggedChars) +
            "': only CURVE is served";
    } else {
      user = z85_of(req[6]);
      if (!user.empty() && allowed_->count(user)) {
        status = "200";
        why = "OK";
      } else {
        why = "not on the allow-list";
      }
    }
    if (status == "200") {
      admitted_.fetch_add(1);
      spdlog::debug("ZAP: admitted {} from {}", user, text(3).substr(0, kMaxLoggedChars));
    } else {
      refused_.fetch_add(1);
      // the peer's address (ZAP's address frame: its IP) and the key it offered
      const std::string line = log_.refused(text(3), user, why, steady_s());
      if (!line.empty()) spdlog::warn("{}", line);
      user.clear();
    }
    // the reply: version, request id, status code and text, user id, metadata
    const std::string reply[] = {"1.0", text(1), status, why, user, ""};
    for (std::size_t i = 0; i < 6; ++i)
      socket_.send(zmq::buffer(reply[i]), i < 5 ? zmq::send_flags::sndmore : zmq::send_flags::none);
  }
  // what was counted and not yet told
  if (const std::string line = log_.flush(steady_s(), true); !line.empty()) spdlog::warn("{}", line);
}

}  // namespace palpsim::net
