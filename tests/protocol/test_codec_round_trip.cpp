#include <gtest/gtest.h>

#include <cfloat>
#include <cmath>
#include <cstdint>

#include "protocol/codec.hpp"
#include "protocol_test_util.hpp"

namespace hapticd::protocol {
namespace {

using test::decode_copy;

// Encodes m, decodes it on an aligned copy, and checks the result says `type`.
template <typename M>
Message round_trip(const M& m, MessageType type) {
  Encoder encoder;
  const EncodeResult encoded = encoder.encode(m);
  EXPECT_TRUE(encoded.ok()) << to_string(encoded.reason);
  EXPECT_GE(encoded.bytes.size(), kMinDatagram);
  EXPECT_LE(encoded.bytes.size(), kMaxDatagram);
  Message out;
  const DecodeResult decoded = decode_copy(encoded.bytes, out);
  EXPECT_TRUE(decoded.ok()) << to_string(decoded.reason);
  EXPECT_EQ(decoded.type, type);
  EXPECT_EQ(decoded.peer_version, kProtocolVersion);
  EXPECT_EQ(out.type, type);
  if constexpr (requires { m.session_id; }) {
    EXPECT_EQ(decoded.session_id, m.session_id);
  } else {
    EXPECT_EQ(decoded.session_id, kNoSession);
  }
  return out;
}

TEST(CodecRoundTrip, HelloKeepsEveryField) {
  const Hello in = test::sample_hello();
  const Hello out = round_trip(in, MessageType::kHello).hello;
  EXPECT_EQ(out.client_name.view(), "glove-left #7");
  EXPECT_EQ(out.device_kind, DeviceKind::kGlove);
  EXPECT_EQ(out.hand, Hand::kLeft);
  ASSERT_EQ(out.frames.size(), 20u);
  for (std::size_t i = 0; i < 20; ++i) {
    EXPECT_EQ(out.frames[i].id, 3 * i + 1);
    EXPECT_EQ(out.frames[i].dof, i % 3 == 0 ? 6 : 3);
    EXPECT_EQ(out.frames[i].name.view(), "frame_" + std::to_string(i));
  }
  EXPECT_EQ(out.requested_rate_hz, 2000u);
  ASSERT_EQ(out.credentials.size(), 5u);
  EXPECT_EQ(out.credentials[0], 0x00);
  EXPECT_EQ(out.credentials[1], 0xFF);
  EXPECT_EQ(out.credentials[2], 0x7F);
  EXPECT_EQ(out.credentials[3], 0x80);
  EXPECT_EQ(out.credentials[4], 0x42);
  EXPECT_EQ(out, in);
}

TEST(CodecRoundTrip, HelloWithoutCredentialsHasNone) {
  Hello in = test::sample_hello(1);
  in.credentials.clear();
  in.device_kind = DeviceKind::kStylus;
  const Hello out = round_trip(in, MessageType::kHello).hello;
  EXPECT_EQ(out.credentials.size(), 0u);
  EXPECT_EQ(out.device_kind, DeviceKind::kStylus);
  EXPECT_EQ(out.frames.size(), 1u);
}

TEST(CodecRoundTrip, WelcomeKeepsEveryField) {
  const Welcome in = test::sample_welcome();
  const Welcome out = round_trip(in, MessageType::kWelcome).welcome;
  EXPECT_EQ(out.session_id, 0x0123456789ABCDEFull);
  EXPECT_EQ(out.rate_hz, 1000u);
  EXPECT_EQ(out.force_limit_n, 7.5f);
  EXPECT_EQ(out.torque_limit_nm, 0.25f);
  EXPECT_EQ(out.max_force_rate_n_per_s, 400.0f);
  ASSERT_EQ(out.frame_map.size(), 20u);
  for (std::size_t i = 0; i < 20; ++i) {
    EXPECT_EQ(out.frame_map[i].client_frame, 3 * i + 1);
    EXPECT_EQ(out.frame_map[i].handle, i == 5 ? kNoHandle : i);
  }
  ASSERT_EQ(out.server_nonce.size(), kNonceBytes);
  EXPECT_EQ(out.server_nonce[31], 7 * 31 + 3);
  EXPECT_EQ(out, in);
}

TEST(CodecRoundTrip, ErrorKeepsCodeAndMessage) {
  const Error out = round_trip(test::sample_error(), MessageType::kError).error;
  EXPECT_EQ(out.code, ErrorCode::kUnsupportedRate);
  EXPECT_EQ(out.message.view(), "requested 20000 Hz, this server runs at most 4000 Hz");
}

TEST(CodecRoundTrip, ErrorKeepsAnUnknownCodeFromANewerPeer) {
  Error in = test::sample_error();
  in.code = static_cast<ErrorCode>(977);
  const Error out = round_trip(in, MessageType::kError).error;
  EXPECT_EQ(static_cast<std::uint16_t>(out.code), 977);
  EXPECT_EQ(to_string(out.code), "unknown");
}

TEST(CodecRoundTrip, PoseSampleKeepsEveryField) {
  const PoseSample in = test::sample_pose();
  const PoseSample out = round_trip(in, MessageType::kPoseSample).pose_sample;
  EXPECT_EQ(out.session_id, 42u);
  EXPECT_EQ(out.sequence, 0xFFFF'FFFF'0000'0001ull);
  EXPECT_EQ(out.client_timestamp_ns, 1'234'567'890'123ull);
  EXPECT_EQ(out.buttons, 0b1010'0000'0000'0000'0000'0000'0000'0101u);
  ASSERT_EQ(out.poses.size(), 20u);
  for (std::size_t i = 0; i < 20; ++i) {
    const float s = static_cast<float>(i);
    EXPECT_EQ(out.poses[i].frame, 3 * i + 1);
    EXPECT_EQ(out.poses[i].position_m.x, 0.01f * s);
    EXPECT_EQ(out.poses[i].position_m.y, -0.02f * s);
    EXPECT_EQ(out.poses[i].position_m.z, 0.5f + s);
    // Exactly unit in float, so normalization leaves every bit.
    EXPECT_EQ(out.poses[i].orientation, test::unit_quaternion(i));
  }
  EXPECT_EQ(out, in);
}

TEST(CodecRoundTrip, PoseSampleQuaternionIsNormalizedOnDecode) {
  PoseSample in = test::sample_pose(2);
  in.poses[0].orientation = {1.2f, 0.0f, 1.6f, 0.0f};   // norm 2: the widest accepted
  in.poses[1].orientation = {0.3f, 0.0f, 0.0f, -0.4f};  // norm 0.5: the narrowest accepted
  const PoseSample out = round_trip(in, MessageType::kPoseSample).pose_sample;
  // 4 eps: one division by a norm that is itself rounded.
  const float tol = 4 * FLT_EPSILON;
  EXPECT_NEAR(out.poses[0].orientation.w, 0.6f, tol);
  EXPECT_NEAR(out.poses[0].orientation.y, 0.8f, tol);
  EXPECT_EQ(out.poses[0].orientation.x, 0.0f);
  EXPECT_NEAR(out.poses[1].orientation.w, 0.6f, tol);
  EXPECT_NEAR(out.poses[1].orientation.z, -0.8f, tol);
  for (const FramePose& p : out.poses) {
    const Quat& q = p.orientation;
    EXPECT_NEAR(std::sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z), 1.0f, tol);
  }
}

TEST(CodecRoundTrip, PoseSampleWithTheMaximumFrameCount) {
  const PoseSample in = test::sample_pose(kMaxFrames);
  const PoseSample out = round_trip(in, MessageType::kPoseSample).pose_sample;
  EXPECT_EQ(out.poses.size(), kMaxFrames);
  EXPECT_EQ(out, in);
}

TEST(CodecRoundTrip, ForceSampleKeepsEveryField) {
  const ForceSample in = test::sample_force();
  const ForceSample out = round_trip(in, MessageType::kForceSample).force_sample;
  EXPECT_EQ(out.session_id, 42u);
  EXPECT_EQ(out.sequence, 0xFFFF'FFFF'0000'0001ull);
  EXPECT_EQ(out.client_timestamp_ns, 1'234'567'890'123ull);
  EXPECT_EQ(out.server_receive_ns, 9'000'000'000'001ull);
  EXPECT_EQ(out.server_send_ns, 9'000'000'040'002ull);
  EXPECT_EQ(out.flags, ForceFlags::kInContact | ForceFlags::kClamped);
  ASSERT_EQ(out.wrenches.size(), 20u);
  for (std::size_t i = 0; i < 20; ++i) {
    const float s = static_cast<float>(i);
    const FrameWrench& w = out.wrenches[i];
    EXPECT_EQ(w.frame, 3 * i + 1);
    EXPECT_EQ(w.flags, i % 2 == 0 ? ForceFlags::kInContact : 0);
    EXPECT_EQ(w.wrench.force_n.x, 1.5f * s);
    EXPECT_EQ(w.wrench.force_n.y, -2.0f);
    EXPECT_EQ(w.wrench.force_n.z, 0.125f);
    EXPECT_EQ(w.wrench.torque_nm.x, 0.01f);
    EXPECT_EQ(w.wrench.torque_nm.y, 0.0f);
    EXPECT_EQ(w.wrench.torque_nm.z, -0.02f * s);
  }
  EXPECT_EQ(out, in);
}

TEST(CodecRoundTrip, ForceSampleKeepsFlagBitsThisBuildDoesNotKnow) {
  ForceSample in = test::sample_force(1);
  in.flags = ForceFlags::kStale | ForceFlags::kResynced | 0x8000;
  in.wrenches[0].flags = 0x4001;
  const ForceSample out = round_trip(in, MessageType::kForceSample).force_sample;
  EXPECT_EQ(out.flags, 0x800C);
  EXPECT_EQ(out.wrenches[0].flags, 0x4001);
}

TEST(CodecRoundTrip, HeartbeatKeepsEveryField) {
  const Heartbeat out = round_trip(test::sample_heartbeat(), MessageType::kHeartbeat).heartbeat;
  EXPECT_EQ(out.session_id, 42u);
  EXPECT_EQ(out.timestamp_ns, 5'000'000'000ull);
  EXPECT_EQ(out.echo_timestamp_ns, 4'999'000'000ull);
}

TEST(CodecRoundTrip, StatsRequestKeepsTheSession) {
  EXPECT_EQ(round_trip(test::sample_stats_request(), MessageType::kStatsRequest).stats_request.session_id, 42u);
}

TEST(CodecRoundTrip, StatsKeepsEveryCounterAndFigure) {
  const Stats out = round_trip(test::sample_stats(), MessageType::kStats).stats;
  EXPECT_EQ(out.session_id, 42u);
  EXPECT_EQ(out.packets_in, 1'000'001u);
  EXPECT_EQ(out.packets_out, 999'998u);
  EXPECT_EQ(out.packets_dropped, 3u);
  for (std::size_t i = 0; i < kRejectReasonCount; ++i) EXPECT_EQ(out.rejected_by_reason[i], 100 + i) << i;
  EXPECT_EQ(out.clamps, 17u);
  EXPECT_EQ(out.resets, 2u);
  EXPECT_EQ(out.overruns, 5u);
  EXPECT_EQ(out.tick_compute_p50_us, 38.5f);
  EXPECT_EQ(out.tick_compute_p99_us, 91.25f);
  EXPECT_EQ(out.tick_jitter_p99_us, 120.0f);
  EXPECT_EQ(out.visual_step_median_ms, 12.75f);
  EXPECT_EQ(out.haptic_rate_hz, 999.5f);
  EXPECT_EQ(out.visual_rate_hz, 60.25f);
  EXPECT_EQ(out.sessions_active, 2u);
  EXPECT_EQ(out.passivity_energy_j, -0.0125f);  // the observer's energy may be negative
  EXPECT_EQ(out.passivity_damped_j, 0.5f);
  EXPECT_EQ(out.passivity_actions, 77u);
}

TEST(CodecRoundTrip, ByeKeepsTheSession) {
  EXPECT_EQ(round_trip(test::sample_bye(), MessageType::kBye).bye.session_id, 42u);
}

// Stats from a peer that counts more reasons (newer) or fewer (older) than this build.
TEST(CodecRoundTrip, StatsFromOlderAndNewerPeersKeepTheReasonsBothKnow) {
  for (const std::size_t peer_reasons : {std::size_t{3}, kRejectReasonCount + 9}) {
    const auto bytes = test::craft([&](flatbuffers::FlatBufferBuilder& b) {
      std::vector<std::uint64_t> rejected(peer_reasons);
      for (std::size_t i = 0; i < peer_reasons; ++i) rejected[i] = 1000 + i;
      const auto vec = b.CreateVector(rejected);
      return std::pair{test::wire::Body::Stats, test::wire::CreateStats(b, 42, 1, 2, 3, vec).Union()};
    });
    Message out;
    ASSERT_TRUE(decode(bytes.span(), out).ok());
    const std::size_t shared = std::min(peer_reasons, kRejectReasonCount);
    for (std::size_t i = 0; i < kRejectReasonCount; ++i) {
      EXPECT_EQ(out.stats.rejected_by_reason[i], i < shared ? 1000 + i : 0) << peer_reasons << " " << i;
    }
  }
}

TEST(CodecRoundTrip, EncodeMessageDispatchesOnType) {
  Encoder encoder;
  for (const Message& in : test::sample_messages()) {
    const EncodeResult encoded = encoder.encode(in);
    ASSERT_TRUE(encoded.ok()) << to_string(in.type);
    Message out;
    ASSERT_TRUE(decode_copy(encoded.bytes, out).ok()) << to_string(in.type);
    EXPECT_TRUE(test::same_body(in, out)) << to_string(in.type);
  }
  Message none;
  EXPECT_EQ(encoder.encode(none).reason, RejectReason::kMissingBody);
  none.type = static_cast<MessageType>(10);
  EXPECT_EQ(encoder.encode(none).reason, RejectReason::kUnknownMessageType);
}

// One Message is reused for every datagram: a decode must overwrite what the previous one left.
TEST(CodecRoundTrip, ReusedMessageHoldsOnlyTheLatestDatagram) {
  Encoder encoder;
  Message out;
  const PoseSample big = test::sample_pose(kMaxFrames);
  ASSERT_TRUE(decode(encoder.encode(big).bytes, out).ok());
  PoseSample small = test::sample_pose(1);
  small.buttons = 0;
  small.sequence = 0;
  ASSERT_TRUE(decode(encoder.encode(small).bytes, out).ok());
  EXPECT_EQ(out.pose_sample, small);
  EXPECT_EQ(out.pose_sample.poses.size(), 1u);
  EXPECT_EQ(out.pose_sample.buttons, 0u);  // absent on the wire (default), still written
}

// The encoder's output is decodable where it lies: 8-aligned start, size a multiple of 8.
TEST(CodecRoundTrip, EncodedBytesAreAlignedForInPlaceDecoding) {
  Encoder encoder;
  for (const Message& in : test::sample_messages()) {
    const EncodeResult encoded = encoder.encode(in);
    EXPECT_EQ(reinterpret_cast<std::uintptr_t>(encoded.bytes.data()) % kDatagramAlignment, 0u);
    EXPECT_EQ(encoded.bytes.size() % kDatagramAlignment, 0u);
    Message out;
    EXPECT_TRUE(decode(encoded.bytes, out).ok()) << to_string(in.type);
  }
}

// The bounds of limits.hpp, as numbers: the largest legal Hello fits kMaxDatagram, a full glove
// sample fits one Ethernet frame (1472-byte UDP payload), the smallest message is >= kMinDatagram.
TEST(CodecRoundTrip, DatagramSizesStayWithinTheDocumentedBounds) {
  Encoder encoder;
  Hello largest;
  largest.client_name.assign(std::string(kMaxClientName, 'c'));
  largest.device_kind = DeviceKind::kGlove;
  for (std::size_t i = 0; i < kMaxFrames; ++i) {
    TrackedFrame f;
    f.id = static_cast<std::uint16_t>(60000 + i);
    f.name.assign(std::string(kMaxFrameName, 'n'));
    largest.frames.push_back(f);
  }
  for (std::size_t i = 0; i < kMaxCredentials; ++i) largest.credentials.push_back(0xEE);
  const EncodeResult hello = encoder.encode(largest);
  ASSERT_TRUE(hello.ok()) << to_string(hello.reason);
  const std::size_t hello_size = hello.bytes.size();
  EXPECT_LE(hello_size, kMaxDatagram);
  Message out;
  EXPECT_TRUE(decode_copy(hello.bytes, out).ok());

  const std::size_t pose_size = encoder.encode(test::sample_pose(kMaxFrames)).bytes.size();
  const std::size_t force_size = encoder.encode(test::sample_force(kMaxFrames)).bytes.size();
  EXPECT_LE(pose_size, 1472u);
  EXPECT_LE(force_size, 1472u);
  const std::size_t bye_size = encoder.encode(Bye{1}).bytes.size();
  EXPECT_GE(bye_size, kMinDatagram);
  const std::size_t stats_request_size = encoder.encode(StatsRequest{1}).bytes.size();
  EXPECT_GE(stats_request_size, kMinDatagram);
  RecordProperty("largest_hello_bytes", static_cast<int>(hello_size));
  std::printf("largest hello %zu B, pose x%zu %zu B, force x%zu %zu B, bye %zu B\n", hello_size, kMaxFrames, pose_size,
              kMaxFrames, force_size, bye_size);
}

}  // namespace
}  // namespace hapticd::protocol
