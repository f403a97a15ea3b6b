// A slow link for integration tests: a thread that relays one haptic client's pose path to
// the server and holds every message for a one-way delay in each direction (round trip =
// twice that), optionally dropping a share of them. The client connects its pose DEALER
// to endpoint() (palpsim-haptic --pose-via) instead of the server's pose endpoint.
#pragma once

#include <atomic>
#include <chrono>
#include <deque>
#include <random>
#include <string>
#include <thread>
#include <zmq.hpp>

namespace palpsim::test {

/// Relays [payload] messages between one DEALER client and a server's pose ROUTER, late.
class DelayLine {
 public:
  /// Binds a ROUTER on a free loopback port and connects to `server_pose`; `one_way_s` is
  /// added to each direction, and each message is dropped with probability `loss`.
  DelayLine(const std::string& server_pose, double one_way_s, double loss = 0.0, unsigned seed = 1)
      : front_(ctx_, zmq::socket_type::router), back_(ctx_, zmq::socket_type::dealer), delay_(one_way_s),
        loss_(loss), rng_(seed) {
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
  zmq::context_t ctx_{1};
  zmq::socket_t front_, back_;
  std::string endpoint_;
  double delay_, loss_;
  std::mt19937 rng_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  std::deque<Held> to_server_, to_client_;
  zmq::message_t client_id_;

  bool drop() { return loss_ > 0 && std::uniform_real_distribution<double>(0, 1)(rng_) < loss_; }

  // holds what arrives, sends what is due, sleeps in poll until the next is due (at most 1 ms)
  void run() {
    const auto hold = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(delay_));
    zmq::pollitem_t items[] = {{front_.handle(), 0, ZMQ_POLLIN, 0}, {back_.handle(), 0, ZMQ_POLLIN, 0}};
    while (!stop_) {
      zmq::poll(items, 2, std::chrono::milliseconds(1));
      zmq::message_t id, m;
      while (front_.recv(id, zmq::recv_flags::dontwait)) {
        (void)front_.recv(m);
        client_id_.copy(id);
        if (!drop()) to_server_.push_back({Clock::now() + hold, std::move(m)});
      }
      while (back_.recv(m, zmq::recv_flags::dontwait))
        if (!drop()) to_client_.push_back({Clock::now() + hold, std::move(m)});
      const auto now = Clock::now();
      while (!to_server_.empty() && to_server_.front().due <= now) {
        (void)back_.send(to_server_.front().payload, zmq::send_flags::dontwait);
        to_server_.pop_front();
      }
      while (!to_client_.empty() && to_client_.front().due <= now && client_id_.size() > 0) {
        zmq::message_t id;
        id.copy(client_id_);
        (void)front_.send(id, zmq::send_flags::sndmore | zmq::send_flags::dontwait);
        (void)front_.send(to_client_.front().payload, zmq::send_flags::dontwait);
        to_client_.pop_front();
      }
    }
  }
};

}  // namespace palpsim::test
