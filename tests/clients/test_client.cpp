#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "clients/cpp/client.hpp"
#include "fake_server.hpp"
#include "protocol/clock.hpp"

namespace hapticd::client {
namespace {

using namespace std::chrono_literals;
using protocol::MessageType;
using test::FakeServer;

// Answers a Hello with a Welcome for session 42 and each pose with its force (x = sequence / 1000).
void answer_everything(FakeServer& server, const protocol::Message& m) {
  if (m.type == MessageType::kHello) server.reply(test::welcome_for(m.hello, 42));
  if (m.type == MessageType::kPoseSample)
    server.reply(test::force_for(m.pose_sample, static_cast<float>(m.pose_sample.sequence) * 1e-3f));
}

// What a ClientError from `call` says; fails the test if it does not throw one.
template <typename F>
ClientError error_from(F&& call) {
  try {
    call();
  } catch (const ClientError& e) {
    return e;
  }
  ADD_FAILURE() << "no ClientError thrown";
  return ClientError(ErrorKind::kSocket, "none");
}

TEST(ClientHandshake, WelcomeOpensTheSessionTheServerNamed) {
  FakeServer server(answer_everything);
  Client client;
  const protocol::Hello hello = test::stylus_hello(500);
  const protocol::Welcome welcome = client.connect("127.0.0.1", server.port(), hello, 2s);
  EXPECT_EQ(welcome, test::welcome_for(hello, 42));
  EXPECT_TRUE(client.connected());
  EXPECT_EQ(client.session_id(), 42u);
  EXPECT_EQ(client.server_address(), "127.0.0.1:" + std::to_string(server.port()));
  EXPECT_NE(client.local_port(), 0);
  ASSERT_EQ(server.count(MessageType::kHello), 1u);
  EXPECT_EQ(server.received()[0].hello, hello) << "the server must see the Hello field for field";
}

TEST(ClientHandshake, LocalhostResolvesToTheIpv4Loopback) {
  FakeServer server(answer_everything);
  Client client;
  client.connect("localhost", server.port(), test::stylus_hello(), 2s);
  EXPECT_EQ(client.server_address(), "127.0.0.1:" + std::to_string(server.port()));
}

TEST(ClientHandshake, ServerErrorIsSurfacedWithItsCodeAndMessage) {
  FakeServer server([](FakeServer& s, const protocol::Message& m) {
    if (m.type != MessageType::kHello) return;
    protocol::Error e;
    e.code = protocol::ErrorCode::kUnsupportedDevice;
    e.message = "the scene has no glove";
    s.reply(e);
  });
  Client client;
  const ClientError e = error_from([&] { client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s); });
  EXPECT_EQ(e.kind(), ErrorKind::kRejected);
  EXPECT_EQ(e.server_code(), protocol::ErrorCode::kUnsupportedDevice);
  EXPECT_EQ(e.server_message(), "the scene has no glove");
  const std::string what = e.what();
  EXPECT_NE(what.find("unsupported_device (5)"), std::string::npos) << what;
  EXPECT_NE(what.find("the scene has no glove"), std::string::npos) << what;
  EXPECT_FALSE(client.connected());
  EXPECT_EQ(client.native_handle(), -1) << "a refused handshake leaves no socket open";
}

TEST(ClientHandshake, SilentServerTimesOutAfterResendingTheHello) {
  FakeServer server([](FakeServer&, const protocol::Message&) {});
  Client client;
  const auto start = std::chrono::steady_clock::now();
  const ClientError e =
      error_from([&] { client.connect("127.0.0.1", server.port(), test::stylus_hello(), 300ms, 100ms); });
  const double elapsed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_EQ(e.kind(), ErrorKind::kTimeout);
  EXPECT_GE(elapsed_s, 0.3);
  EXPECT_LT(elapsed_s, 1.0);
  const std::string what = e.what();
  EXPECT_NE(what.find("127.0.0.1:" + std::to_string(server.port())), std::string::npos) << what;
  EXPECT_NE(what.find("300 ms"), std::string::npos) << what;
  // Sent at 0, 100 and 200 ms (300 is the deadline); the fake server thread may lag one.
  EXPECT_GE(server.count(MessageType::kHello), 2u);
  EXPECT_LE(server.count(MessageType::kHello), 3u);
}

TEST(ClientHandshake, HelloIsResentUntilTheServerAnswers) {
  std::atomic<int> hellos{0};
  FakeServer server([&](FakeServer& s, const protocol::Message& m) {
    if (m.type == MessageType::kHello && ++hellos == 2) s.reply(test::welcome_for(m.hello, 7));
  });
  Client client;
  EXPECT_EQ(client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s, 50ms).session_id, 7u);
  EXPECT_EQ(hellos.load(), 2);
}

TEST(ClientHandshake, NothingListeningIsRefusedAtOnce) {
  // A port that was just free: bind, read it back, close.
  const test::BoundUdp free_port = test::bind_loopback_udp();
  ::close(free_port.fd);
  Client client;
  const auto start = std::chrono::steady_clock::now();
  const ClientError e = error_from([&] { client.connect("127.0.0.1", free_port.port, test::stylus_hello(), 2s); });
  EXPECT_EQ(e.kind(), ErrorKind::kRefused) << e.what();
  EXPECT_LT(std::chrono::steady_clock::now() - start, 1s) << "ICMP port unreachable must not wait for the timeout";
}

TEST(ClientHandshake, BadHostPortAndHelloAreRefusedBeforeAnythingIsSent) {
  Client client;
  const protocol::Hello hello = test::stylus_hello();
  EXPECT_EQ(error_from([&] { client.connect("no-such-host.invalid", 7000, hello, 1s); }).kind(),
            ErrorKind::kBadAddress);
  const ClientError empty = error_from([&] { client.connect("", 7000, hello, 1s); });
  EXPECT_EQ(empty.kind(), ErrorKind::kBadAddress);
  const ClientError port = error_from([&] { client.connect("127.0.0.1", 0, hello, 1s); });
  EXPECT_EQ(port.kind(), ErrorKind::kBadAddress);
  EXPECT_NE(std::string(port.what()).find("port 0"), std::string::npos) << port.what();

  protocol::Hello no_frames = hello;
  no_frames.frames.clear();
  const ClientError invalid = error_from([&] { client.connect("127.0.0.1", 7000, no_frames, 1s); });
  EXPECT_EQ(invalid.kind(), ErrorKind::kInvalid);
  EXPECT_NE(std::string(invalid.what()).find("bad_count"), std::string::npos) << invalid.what();
}

TEST(ClientSession, CallsWithoutASessionFailPlainly) {
  Client client;
  protocol::PoseSample pose = test::stylus_pose();
  EXPECT_EQ(client.send_pose(pose), SendResult::kNotConnected);
  EXPECT_EQ(client.heartbeat(), SendResult::kNotConnected);
  EXPECT_FALSE(client.poll_force(1ms).has_value());
  EXPECT_EQ(error_from([&] { client.request_stats(10ms); }).kind(), ErrorKind::kNotConnected);
  client.bye();  // harmless
}

TEST(ClientSession, EachReplyIsMatchedToItsPoseBySequence) {
  FakeServer server(answer_everything);
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  for (std::uint64_t i = 1; i <= 50; ++i) {
    protocol::PoseSample pose = test::stylus_pose();
    ASSERT_EQ(client.send_pose(pose), SendResult::kSent);
    EXPECT_EQ(pose.session_id, 42u);
    EXPECT_EQ(pose.sequence, i) << "sequences start at 1 and increase by 1";
    EXPECT_NE(pose.client_timestamp_ns, 0u);
    const auto reply = client.poll_force(1s);
    ASSERT_TRUE(reply.has_value()) << "pose " << i;
    EXPECT_EQ(reply->sample.sequence, i);
    EXPECT_EQ(reply->sample.client_timestamp_ns, pose.client_timestamp_ns);
    EXPECT_FLOAT_EQ(reply->sample.wrenches[0].wrench.force_n.x, static_cast<float>(i) * 1e-3f);
    EXPECT_GT(reply->rtt_ns(), 0u);
    EXPECT_LT(reply->rtt_ns(), 1'000'000'000u);
  }
  EXPECT_EQ(client.counters().poses_sent, 50u);
  EXPECT_EQ(client.counters().forces_accepted, 50u);
  EXPECT_EQ(client.counters().forces_stale, 0u);
  EXPECT_FALSE(client.poll_force(0ns).has_value()) << "nothing left over";
}

TEST(ClientSession, StaleDuplicatedForeignAndUnsentRepliesAreDropped) {
  // The server holds poses 1..3, then answers 3, 2, 1, 3 again, a reply for another session and
  // one for a pose never sent.
  FakeServer server([](FakeServer& s, const protocol::Message& m) {
    static std::vector<protocol::PoseSample> held;
    if (m.type == MessageType::kHello) {
      held.clear();
      s.reply(test::welcome_for(m.hello, 42));
    }
    if (m.type != MessageType::kPoseSample) return;
    held.push_back(m.pose_sample);
    if (held.size() < 3) return;
    for (int i : {2, 1, 0, 2}) s.reply(test::force_for(held[i], static_cast<float>(held[i].sequence)));
    protocol::ForceSample foreign = test::force_for(held[2], 9.0f);
    foreign.session_id = 43;
    s.reply(foreign);
    protocol::ForceSample unsent = test::force_for(held[2], 9.0f);
    unsent.sequence = 4;
    s.reply(unsent);
  });
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  for (int i = 0; i < 3; ++i) {
    protocol::PoseSample pose = test::stylus_pose();
    ASSERT_EQ(client.send_pose(pose), SendResult::kSent);
  }
  const auto newest = client.poll_force(1s);
  ASSERT_TRUE(newest.has_value());
  EXPECT_EQ(newest->sample.sequence, 3u);
  EXPECT_FLOAT_EQ(newest->sample.wrenches[0].wrench.force_n.x, 3.0f);
  EXPECT_FALSE(client.poll_force(200ms).has_value()) << "no older force may come out after a newer one";
  EXPECT_EQ(client.counters().forces_accepted, 1u);
  EXPECT_EQ(client.counters().forces_stale, 3u);          // 2, 1 and the duplicate 3
  EXPECT_EQ(client.counters().datagrams_unexpected, 2u);  // session 43, sequence 4
}

TEST(ClientSession, StatsHeartbeatAndByeReachTheServer) {
  FakeServer server([](FakeServer& s, const protocol::Message& m) {
    static std::uint64_t last_pose = 0;
    if (m.type == MessageType::kHello) s.reply(test::welcome_for(m.hello, 42));
    if (m.type == MessageType::kPoseSample) last_pose = m.pose_sample.sequence;
    if (m.type == MessageType::kHeartbeat) s.reply(protocol::Heartbeat{42, 777, m.heartbeat.timestamp_ns});
    if (m.type == MessageType::kStatsRequest) {
      // A force for the last pose overtakes the Stats: the client must keep it for poll_force().
      protocol::PoseSample answered = test::stylus_pose();
      answered.session_id = 42;
      answered.sequence = last_pose;
      answered.client_timestamp_ns = 5;
      s.reply(test::force_for(answered, 1.5f));
      protocol::Stats stats;
      stats.session_id = 42;
      stats.packets_in = 7;
      stats.haptic_rate_hz = 999.5f;
      s.reply(stats);
    }
  });
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  protocol::PoseSample pose = test::stylus_pose();
  ASSERT_EQ(client.send_pose(pose), SendResult::kSent);

  const protocol::Stats stats = client.request_stats(1s);
  EXPECT_EQ(stats.packets_in, 7u);
  EXPECT_FLOAT_EQ(stats.haptic_rate_hz, 999.5f);
  const auto kept = client.poll_force(0ns);
  ASSERT_TRUE(kept.has_value());
  EXPECT_EQ(kept->sample.sequence, 1u);
  EXPECT_FLOAT_EQ(kept->sample.wrenches[0].wrench.force_n.x, 1.5f);

  // The first heartbeat has nothing to echo; the server's answer (timestamp 777) is echoed next.
  ASSERT_EQ(client.heartbeat(), SendResult::kSent);
  EXPECT_FALSE(client.poll_force(100ms).has_value());  // reads the Heartbeat answer
  ASSERT_EQ(client.heartbeat(), SendResult::kSent);

  client.bye();
  EXPECT_FALSE(client.connected());
  EXPECT_EQ(client.send_pose(pose), SendResult::kNotConnected);
  const auto deadline = std::chrono::steady_clock::now() + 1s;
  while (server.count(MessageType::kBye) == 0 && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(1ms);
  std::vector<protocol::Heartbeat> beats;
  std::vector<protocol::Bye> byes;
  for (const protocol::Message& m : server.received()) {
    if (m.type == MessageType::kHeartbeat) beats.push_back(m.heartbeat);
    if (m.type == MessageType::kBye) byes.push_back(m.bye);
  }
  ASSERT_EQ(beats.size(), 2u);
  EXPECT_EQ(beats[0].echo_timestamp_ns, 0u);
  EXPECT_EQ(beats[1].echo_timestamp_ns, 777u);
  ASSERT_EQ(byes.size(), 1u);
  EXPECT_EQ(byes[0].session_id, 42u);
}

TEST(ClientSession, InvalidPoseIsNotSentAndSpendsNoSequence) {
  FakeServer server(answer_everything);
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  protocol::PoseSample bad = test::stylus_pose(std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(client.send_pose(bad), SendResult::kInvalid);
  protocol::PoseSample good = test::stylus_pose();
  EXPECT_EQ(client.send_pose(good), SendResult::kSent);
  EXPECT_EQ(good.sequence, 1u);
  const auto reply = client.poll_force(1s);
  ASSERT_TRUE(reply.has_value());
  EXPECT_EQ(reply->sample.sequence, 1u);
  EXPECT_EQ(server.count(MessageType::kPoseSample), 1u);
}

// A glove frame whose tracking failed (NaN) is left out of the sample; the others are sent.
TEST(ClientSession, NonFiniteFramesAreLeftOutOfTheSample) {
  FakeServer server(answer_everything);
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  protocol::PoseSample pose = test::stylus_pose();
  protocol::FramePose second = pose.poses[0], third = pose.poses[0];
  second.frame = static_cast<std::uint16_t>(pose.poses[0].frame + 1);
  second.orientation.x = std::numeric_limits<float>::quiet_NaN();
  third.frame = static_cast<std::uint16_t>(pose.poses[0].frame + 2);
  third.position_m.y = 0.25f;
  pose.poses.push_back(second);
  pose.poses.push_back(third);
  EXPECT_EQ(client.send_pose(pose), SendResult::kSent);
  EXPECT_EQ(client.counters().frames_dropped, 1u);
  ASSERT_TRUE(client.poll_force(1s).has_value());
  const std::vector<protocol::Message> got = server.received();
  const protocol::Message* sample = nullptr;
  for (const protocol::Message& m : got)
    if (m.type == MessageType::kPoseSample) sample = &m;
  ASSERT_NE(sample, nullptr);
  ASSERT_EQ(sample->pose_sample.poses.size(), 2u);
  EXPECT_EQ(sample->pose_sample.poses[0].frame, pose.poses[0].frame);
  EXPECT_EQ(sample->pose_sample.poses[1].frame, third.frame);
  EXPECT_EQ(sample->pose_sample.poses[1].position_m.y, 0.25f);
}

}  // namespace
}  // namespace hapticd::client
