#pragma once
// Shared by the haptic server's loopback tests: the server on its own thread with a wall for a world,
// and a device's end of the wire speaking the project's codec (plain, or sealed by hand).
#include <gtest/gtest.h>
#include <poll.h>

#include <atomic>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/udp.hpp>
#include <chrono>
#include <cmath>
#include <memory>
#include <thread>

#include "allocation_counter.hpp"
#include "protocol/clock.hpp"
#include "server/haptic/haptic_server.hpp"

namespace hapticd::test {

namespace asio = boost::asio;
using protocol::Message;
using protocol::MessageType;

// A wall z <= 0 in world space (see test_virtual_coupling.cpp), 3000 N/m.
inline haptic::HapticSnapshot wall_snapshot() {
  haptic::HapticSnapshot s;
  s.hands = 1;
  haptic::HapticModel& m = s.model[0];
  m.handles = 1;
  m.F0 = haptic::HapticVector::Zero(6);
  m.K = haptic::HapticMatrix::Zero(6, 6);
  m.D = haptic::HapticMatrix::Zero(6, 6);
  m.K(2, 2) = -3000.0;
  m.v0[0].setZero();
  m.w0[0].setZero();
  m.in_contact = true;
  return s;
}

inline haptic::DeviceLink stylus_link() {
  haptic::DeviceLink l;
  l.name = "stylus";
  l.mass_kg[0] = 0.05;
  l.inertia_B[0] = 1e-5 * Eigen::Matrix3d::Identity();
  l.gains = haptic::coupling_gains_for(1000.0, 1.0, 1e-3);
  return l;
}

// The server on its own thread, and (unless `visual` is false) a stand-in for
// the visual loop that republishes the wall, acknowledging the hand's re-syncs
// (the wall does not move with the hand, so its model stays valid).
struct RunningServer {
  // `world`: the snapshot the stand-in visual loop publishes (a stylus on the wall by default),
  // for the device `link`.
  explicit RunningServer(const haptic::ServerOptions& options = {}, bool visual = true,
                         haptic::HapticSnapshot (*world_fn)() = wall_snapshot,
                         const haptic::DeviceLink& link = stylus_link())
      : world(world_fn),
        snapshots_storage(std::make_unique<haptic::TripleBuffer<haptic::HapticSnapshot>>(world_fn())),
        snapshots(*snapshots_storage),
        server({link}, options, snapshots, targets) {
    thread = std::thread([this] {
      testing_util::count_allocations_on_this_thread(true);
      server.run(stop);
      allocations = testing_util::allocations_on_this_thread();
    });
    if (visual)
      visual_thread = std::thread([this] {
        while (!stop) {
          targets.update();
          snapshots.back() = this->world();
          snapshots.back().model[0].resyncs = targets.front().resyncs[0];
          snapshots.publish();
          std::this_thread::sleep_for(std::chrono::milliseconds(5));
        }
      });
  }
  ~RunningServer() { halt(); }
  void halt() {
    stop = true;
    if (thread.joinable()) thread.join();
    if (visual_thread.joinable()) visual_thread.join();
  }
  haptic::HapticSnapshot (*world)();
  // Three snapshots of four hands' models are 4 MB: on the heap, as hapticd keeps them, not on a
  // test's stack (two servers in one test overflowed it under ASan).
  std::unique_ptr<haptic::TripleBuffer<haptic::HapticSnapshot>> snapshots_storage;
  haptic::TripleBuffer<haptic::HapticSnapshot>& snapshots;
  haptic::TripleBuffer<haptic::ProxyTargets> targets;
  haptic::HapticServer server;
  std::atomic<bool> stop{false};
  std::atomic<long> allocations{-1};
  std::thread thread, visual_thread;
};

// A device's end of the wire, with the project's codec.
struct TestClient {
  explicit TestClient(std::uint16_t port) : server(asio::ip::make_address("127.0.0.1"), port) {
    socket.open(asio::ip::udp::v4());
  }
  void send_bytes(const void* data, std::size_t n) { socket.send_to(asio::buffer(data, n), server); }
  template <typename T>
  void send(const T& m) {
    const auto r = encoder.encode(m);
    ASSERT_TRUE(r.ok());
    send_bytes(r.bytes.data(), r.bytes.size());
  }
  // The next datagram within `timeout_ms`, decoded; type kNone on timeout.
  Message receive(int timeout_ms = 200) {
    Message m;
    pollfd p{socket.native_handle(), POLLIN, 0};
    if (poll(&p, 1, timeout_ms) <= 0) return m;
    const std::size_t n = socket.receive(asio::buffer(rx.bytes));
    const auto r = protocol::decode({rx.bytes.data(), n}, m);
    EXPECT_TRUE(r.ok()) << to_string(r.reason);
    return m;
  }
  std::uint64_t hello() {
    protocol::Hello h;
    h.client_name.assign("test");
    h.device_kind = protocol::DeviceKind::kStylus;
    protocol::TrackedFrame f;
    f.id = 7;
    f.name.assign("tip");
    h.frames.push_back(f);
    send(h);
    const Message m = receive(1000);
    EXPECT_EQ(m.type, MessageType::kWelcome);
    session = m.welcome.session_id;
    return session;
  }
  protocol::PoseSample pose_at(double z, std::uint64_t seq) const {
    protocol::PoseSample p;
    p.session_id = session;
    p.sequence = seq;
    p.client_timestamp_ns = protocol::now_ns();
    protocol::FramePose f;
    f.frame = 7;
    f.position_m = {0.0f, 0.0f, static_cast<float>(z)};
    p.poses.push_back(f);
    return p;
  }
  // Sends a pose and returns the force reply's z force (NaN without a reply).
  double press(double z, std::uint64_t seq) {
    send(pose_at(z, seq));
    const Message m = receive();
    if (m.type != MessageType::kForceSample || m.force_sample.sequence != seq) return NAN;
    last = m.force_sample;
    return m.force_sample.wrenches[0].wrench.force_n.z;
  }
  asio::io_context io;
  asio::ip::udp::socket socket{io};
  asio::ip::udp::endpoint server;
  protocol::Encoder encoder;
  alignas(8) protocol::ReceiveBuffer rx;
  std::uint64_t session = 0;
  protocol::ForceSample last;
};

}  // namespace hapticd::test
