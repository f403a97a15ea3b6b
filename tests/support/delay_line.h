// A slow link for integration tests: a thread that relays one haptic client's pose path to
// the server and holds every message for a one-way delay in each direction (round trip =
// twice that), with jitter and loss as a TCP link shows them to ZeroMQ: messages stay in
// order (a late one holds those behind it), and a lost segment arrives one retransmission
// later (a round trip and 3 ms: fast retransmit after three duplicate ACKs at 1 kHz)
// instead of never. The client connects its pose DEALER to endpoint() (palpsim-haptic
// --pose-via) instead of the server's pose endpoint.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <deque>
#include <random>
#include <string>
#include <thread>
#include <zmq.hpp>

namespace palpsim::test {

/// How the link is impaired, per direction.
struct LinkImpairment {
  double one_way_s = 0;  // delay (s)
  double jitter_s = 0;   // each message's delay varies uniformly by +- this (s), order kept
  double loss = 0;       // share of messages lost once (then retransmitted, see above)
};

/// Relays [payload] messages between one DEALER client and a server's pose ROUTER, late.
class DelayLine {
 public:
  /// Binds a ROUTER on a free loopback port and connects to `server_pose`; every message
  /// in each direction is held as `link` says (random draws from `seed`).
  DelayLine(const std::string& server_pose, double one_way_s) : DelayLine(server_pose, LinkImpairment{one_way_s}) {}
  DelayLine(const std::string& server_pose, const LinkImpairment& link, unsigned seed = 1)
      : front_(ctx_, zmq::socket_type::router), back_(ctx_, zmq::socket_type::dealer), link_(link), rng_(seed) {
    front_.set(zmq::sockopt::linger, 0);
    back_.set(zmq::sockopt::linger, 0);
    front_.bind("tcp://127.0.0.1:*");
    endpoint_ = front_.get(zmq::sockopt::last_endpoint);
    back_.connect(server_pose);
    thread_ = std::thread([this] { run(); });
  }
  ~DelayLine() {
    stop_ = true;
    thread_.join();
  }
  DelayLine(const DelayLine&) = delete;
  DelayLine& operator=(const DelayLine&) = delete;

  /// The address the client sends its poses to.
  const std::string& endpoint() const { return endpoint_; }

 private:
  using Clock = std::chrono::steady_clock;
  struct Held {
    Clock::time_point due;
    zmq::message_t payload;
  };
  // one direction: its queue and the due time of its newest message (order is kept)
  struct Direction {
    std::deque<Held> queue;
    Clock::time_point last_due{};
  };
  zmq::context_t ctx_{1};
  zmq::socket_t front_, back_;
  std::string endpoint_;
  LinkImpairment link_;
  std::mt19937 rng_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  Direction to_server_, to_client_;
  zmq::message_t client_id_;

  // holds a message: delay, jitter, a retransmission when lost, never before the one ahead
  void hold(Direction& d, zmq::message_t&& m) {
    std::uniform_real_distribution<double> u(0, 1);
    double s = link_.one_way_s + link_.jitter_s * (2 * u(rng_) - 1);
    if (link_.loss > 0 && u(rng_) < link_.loss) s += 2 * link_.one_way_s + 0.003;
    const auto due = std::max(d.last_due, Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                                            std::chrono::duration<double>(std::max(s, 0.0))));
    d.last_due = due;
    d.queue.push_back({due, std::move(m)});
  }

  // holds what arrives, sends what is due, sleeps in poll until the next is due (at most 1 ms)
  void run() {
    zmq::pollitem_t items[] = {{front_.handle(), 0, ZMQ_POLLIN, 0}, {back_.handle(), 0, ZMQ_POLLIN, 0}};
    while (!stop_) {
      zmq::poll(items, 2, std::chrono::milliseconds(1));
      zmq::message_t id, m;
      while (front_.recv(id, zmq::recv_flags::dontwait)) {
        (void)front_.recv(m);
        client_id_.copy(id);
        hold(to_server_, std::move(m));
      }
      while (back_.recv(m, zmq::recv_flags::dontwait)) hold(to_client_, std::move(m));
      const auto now = Clock::now();
      while (!to_server_.queue.empty() && to_server_.queue.front().due <= now) {
        (void)back_.send(to_server_.queue.front().payload, zmq::send_flags::dontwait);
        to_server_.queue.pop_front();
      }
      while (!to_client_.queue.empty() && to_client_.queue.front().due <= now && client_id_.size() > 0) {
        zmq::message_t id;
        id.copy(client_id_);
        (void)front_.send(id, zmq::send_flags::sndmore | zmq::send_flags::dontwait);
        (void)front_.send(to_client_.queue.front().payload, zmq::send_flags::dontwait);
        to_client_.queue.pop_front();
      }
    }
  }
};

}  // namespace palpsim::test
