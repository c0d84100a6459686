#pragma once

// An in-test stand-in for hapticd: a plain UDP socket on 127.0.0.1 served by a thread that
// decodes each datagram and hands it to the test's handler, which answers through reply().
// Everything the handler received is kept for assertions.

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>

#include "protocol/codec.hpp"

namespace hapticd::client::test {

class FakeServer {
 public:
  // Called on the server thread for every datagram that decodes.
  using Handler = std::function<void(FakeServer&, const protocol::Message&)>;

  explicit FakeServer(Handler handler) : handler_(std::move(handler)) {
    fd_ = ::socket(AF_INET, SOCK_DGRAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t length = sizeof address;
    if (fd_ < 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0 ||
        ::getsockname(fd_, reinterpret_cast<sockaddr*>(&address), &length) != 0)
      throw std::runtime_error("fake server: cannot bind 127.0.0.1");
    port_ = ntohs(address.sin_port);
    thread_ = std::thread([this] { serve(); });
  }
  ~FakeServer() {
    stop_.store(true);
    thread_.join();
    ::close(fd_);
  }
  FakeServer(const FakeServer&) = delete;
  FakeServer& operator=(const FakeServer&) = delete;

  [[nodiscard]] std::uint16_t port() const { return port_; }

  // Sends `m` to the peer of the datagram being handled. Server thread only.
  template <typename T>
  void reply(const T& m) {
    const protocol::EncodeResult e = encoder_.encode(m);
    if (!e.ok()) throw std::logic_error("fake server: encoder refused a reply");
    ::sendto(fd_, e.bytes.data(), e.bytes.size(), 0, reinterpret_cast<const sockaddr*>(&peer_), peer_length_);
  }

  // Copies of every decoded message, in arrival order.
  std::vector<protocol::Message> received() const {
    const std::lock_guard lock(mutex_);
    return received_;
  }
  std::size_t count(protocol::MessageType type) const {
    const std::lock_guard lock(mutex_);
    std::size_t n = 0;
    for (const protocol::Message& m : received_) n += m.type == type;
    return n;
  }

 private:
  void serve() {
    protocol::ReceiveBuffer rx;
    protocol::Message message;
    while (!stop_.load()) {
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, 10) <= 0) continue;
      peer_length_ = sizeof peer_;
      const ssize_t n =
          ::recvfrom(fd_, rx.bytes.data(), rx.bytes.size(), 0, reinterpret_cast<sockaddr*>(&peer_), &peer_length_);
      if (n < 0 || !protocol::decode({rx.bytes.data(), static_cast<std::size_t>(n)}, message).ok()) continue;
      {
        const std::lock_guard lock(mutex_);
        received_.push_back(message);
      }
      handler_(*this, message);
    }
  }

  Handler handler_;
  protocol::Encoder encoder_;
  int fd_ = -1;
  std::uint16_t port_ = 0;
  sockaddr_storage peer_{};
  socklen_t peer_length_ = 0;
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  std::vector<protocol::Message> received_;
  std::thread thread_;
};

// A stylus Hello: one 6-DoF frame named "stylus".
inline protocol::Hello stylus_hello(std::uint32_t rate_hz = 1000) {
  protocol::Hello h;
  h.client_name = "client_tests";
  h.device_kind = protocol::DeviceKind::kStylus;
  protocol::TrackedFrame f;
  f.id = 3;
  f.dof = 6;
  f.name = "stylus";
  h.frames.push_back(f);
  h.requested_rate_hz = rate_hz;
  return h;
}

inline protocol::Welcome welcome_for(const protocol::Hello& hello, std::uint64_t session_id) {
  protocol::Welcome w;
  w.session_id = session_id;
  w.rate_hz = hello.requested_rate_hz;
  w.force_limit_n = 8.0f;
  w.torque_limit_nm = 0.5f;
  w.max_force_rate_n_per_s = 1000.0f;
  for (const protocol::TrackedFrame& f : hello.frames) w.frame_map.push_back({f.id, 0});
  return w;
}

// The ForceSample answering `pose`, its force's x set to `fx` so a test can tell replies apart.
inline protocol::ForceSample force_for(const protocol::PoseSample& pose, float fx) {
  protocol::ForceSample f;
  f.session_id = pose.session_id;
  f.sequence = pose.sequence;
  f.client_timestamp_ns = pose.client_timestamp_ns;
  f.server_receive_ns = 1;
  f.server_send_ns = 2;
  protocol::FrameWrench w;
  w.frame = pose.poses[0].frame;
  w.wrench.force_n = {fx, 0.0f, 0.0f};
  f.wrenches.push_back(w);
  return f;
}

// A one-frame pose for the stylus Hello's frame.
inline protocol::PoseSample stylus_pose(float z_m = 0.01f) {
  protocol::PoseSample p;
  protocol::FramePose f;
  f.frame = 3;
  f.position_m = {0.0f, 0.0f, z_m};
  p.poses.push_back(f);
  return p;
}

// A UDP socket bound to a free loopback port, and the port: kept open it is a
// server that never answers; closed, a port where nothing listens.
struct BoundUdp {
  int fd = -1;
  std::uint16_t port = 0;
};
inline BoundUdp bind_loopback_udp() {
  BoundUdp b;
  b.fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof a;
  if (b.fd < 0 || ::bind(b.fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
      ::getsockname(b.fd, reinterpret_cast<sockaddr*>(&a), &length) != 0)
    throw std::runtime_error("cannot bind a loopback UDP socket");
  b.port = ntohs(a.sin_port);
  return b;
}

}  // namespace hapticd::client::test
