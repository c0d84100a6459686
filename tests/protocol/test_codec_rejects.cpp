#include <gtest/gtest.h>

#include <cstdint>
#include <cstring>
#include <limits>
#include <set>
#include <string>
#include <vector>

#include "protocol/codec.hpp"
#include "protocol_test_util.hpp"

namespace hapticd::protocol {
namespace {

using test::AlignedBytes;
using test::RawFrame;
namespace wire = test::wire;

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

DecodeResult decode_bytes(const AlignedBytes& bytes) {
  Message out;
  out.type = MessageType::kBye;  // must be reset on rejection
  const DecodeResult r = decode(bytes.span(), out);
  if (!r.ok()) {
    EXPECT_EQ(out.type, MessageType::kNone);
  }
  return r;
}

AlignedBytes encoded(const PoseSample& m) {
  Encoder encoder;
  const EncodeResult r = encoder.encode(m);
  EXPECT_TRUE(r.ok()) << to_string(r.reason);
  return AlignedBytes(r.bytes);
}

AlignedBytes valid_pose_bytes() { return encoded(test::sample_pose()); }

std::vector<RawFrame> glove_frames() { return test::raw_frames(20); }

AlignedBytes hello_with(const std::vector<RawFrame>& frames, std::uint32_t rate_hz = 1000) {
  return test::craft_hello("glove", wire::DeviceKind::Glove, frames, rate_hz);
}

// ---- size, alignment, identifier, verifier --------------------------------------------------

TEST(CodecRejects, EmptyDatagram) {
  Message out;
  EXPECT_EQ(decode({}, out).reason, RejectReason::kEmpty);
  EXPECT_EQ(decode_bytes(AlignedBytes()).reason, RejectReason::kEmpty);
}

TEST(CodecRejects, EveryLengthBelowTheMinimumIsTooShort) {
  const AlignedBytes valid = valid_pose_bytes();
  for (std::size_t n = 1; n < kMinDatagram; ++n) {
    EXPECT_EQ(decode_bytes(AlignedBytes(valid.span().first(n))).reason, RejectReason::kTooShort) << n;
  }
}

TEST(CodecRejects, OversizedDatagramIsTooLongEvenIfItsPrefixIsValid) {
  AlignedBytes padded = valid_pose_bytes();
  // Trailing bytes after a finished buffer are harmless up to the bound...
  padded.resize(kMaxDatagram);
  EXPECT_TRUE(decode_bytes(padded).ok());
  // ...and past it the datagram is refused before anything reads it.
  for (const std::size_t n : {kMaxDatagram + 1, kMaxDatagram + 4, sizeof(ReceiveBuffer), std::size_t{65536}}) {
    padded.resize(n);
    EXPECT_EQ(decode_bytes(padded).reason, RejectReason::kTooLong) << n;
  }
}

TEST(CodecRejects, LengthNotAMultipleOfFourIsOddSize) {
  const AlignedBytes valid = valid_pose_bytes();
  for (const std::size_t extra : {1, 2, 3, 5}) {
    AlignedBytes odd = valid;
    odd.resize(valid.size() + extra);
    EXPECT_EQ(decode_bytes(odd).reason, RejectReason::kOddSize) << extra;
  }
  EXPECT_EQ(decode_bytes(AlignedBytes(valid.span().first(valid.size() - 2))).reason, RejectReason::kOddSize);
}

TEST(CodecRejects, MisalignedBufferIsRefusedNotReadInPlace) {
  const AlignedBytes valid = valid_pose_bytes();
  AlignedBytes shifted;
  shifted.resize(valid.size() + 8);
  for (const std::size_t offset : {1, 2, 4, 7}) {
    std::memcpy(shifted.data() + offset, valid.data(), valid.size());
    Message out;
    const std::span<const std::uint8_t> view(shifted.data() + offset, valid.size());
    EXPECT_EQ(decode(view, out).reason, RejectReason::kMisaligned) << offset;
  }
  std::memcpy(shifted.data() + 8, valid.data(), valid.size());
  Message out;
  EXPECT_TRUE(decode({shifted.data() + 8, valid.size()}, out).ok());
}

TEST(CodecRejects, WrongFileIdentifier) {
  for (const char* id : {"HPTX", "hptd", "\0\0\0\0", "FBS1"}) {
    AlignedBytes bytes = valid_pose_bytes();
    std::memcpy(bytes.data() + 4, id, 4);  // the identifier follows the 4-byte root offset
    EXPECT_EQ(decode_bytes(bytes).reason, RejectReason::kBadIdentifier) << id;
  }
}

TEST(CodecRejects, TruncatedMessageFailsVerification) {
  const AlignedBytes valid = valid_pose_bytes();
  for (const std::size_t n : {valid.size() / 2 / 4 * 4, valid.size() - std::size_t{256}, std::size_t{kMinDatagram}}) {
    const DecodeResult r = decode_bytes(AlignedBytes(valid.span().first(n)));
    EXPECT_EQ(r.reason, RejectReason::kVerifyFailed) << n;
    EXPECT_EQ(r.type, MessageType::kNone) << "nothing is read from an unverified buffer";
    EXPECT_EQ(r.session_id, kNoSession);
    EXPECT_EQ(r.peer_version, 0);
  }
}

TEST(CodecRejects, RootOffsetOutsideTheBufferFailsVerification) {
  for (const std::uint32_t root : {0u, 3u, 0x7FFF'FFFFu, 0xFFFF'FFF0u}) {
    AlignedBytes bytes = valid_pose_bytes();
    std::memcpy(bytes.data(), &root, sizeof root);
    EXPECT_EQ(decode_bytes(bytes).reason, RejectReason::kVerifyFailed) << root;
  }
  AlignedBytes zeros;
  zeros.resize(256);
  std::memcpy(zeros.data() + 4, "HPTD", 4);
  EXPECT_EQ(decode_bytes(zeros).reason, RejectReason::kVerifyFailed);
}

// ---- version and union tag ------------------------------------------------------------------

TEST(CodecRejects, OtherProtocolVersionsAreRefusedButNamed) {
  for (const std::uint16_t version : {std::uint16_t{0}, std::uint16_t{kProtocolVersion + 1}, std::uint16_t{0xFFFF}}) {
    const DecodeResult pose = decode_bytes(test::craft_pose(42, test::poses_of(test::sample_pose(2)), version));
    EXPECT_EQ(pose.reason, RejectReason::kVersionMismatch);
    EXPECT_EQ(pose.peer_version, version);
    EXPECT_EQ(pose.type, MessageType::kPoseSample);
    EXPECT_FALSE(error_reply_allowed(pose)) << "a stream sample never gets a reply";

    const DecodeResult hello =
        decode_bytes(test::craft_hello("glove", wire::DeviceKind::Glove, glove_frames(), 1000, 0, version));
    EXPECT_EQ(hello.reason, RejectReason::kVersionMismatch);
    EXPECT_EQ(hello.peer_version, version);
    EXPECT_EQ(hello.type, MessageType::kHello);
    EXPECT_TRUE(error_reply_allowed(hello)) << "a verified hello of another version is told why";
    EXPECT_EQ(error_code_for(hello.reason), ErrorCode::kVersionMismatch);
  }
}

TEST(CodecRejects, NoBodyIsMissingBody) {
  auto none = test::craft([](flatbuffers::FlatBufferBuilder&) {
    return std::pair{wire::Body::NONE, flatbuffers::Offset<void>()};
  });
  EXPECT_LT(none.size(), kMinDatagram) << "a Message without a body is shorter than any with one";
  EXPECT_EQ(decode_bytes(none).reason, RejectReason::kTooShort);
  none.resize(64);  // trailing zeros get it past the size check to the body check
  EXPECT_EQ(decode_bytes(none).reason, RejectReason::kMissingBody);
  // A tag without its table: the Verifier accepts an absent field, the codec does not.
  auto tag_only = test::craft([](flatbuffers::FlatBufferBuilder&) {
    return std::pair{wire::Body::PoseSample, flatbuffers::Offset<void>()};
  });
  tag_only.resize(64);
  const DecodeResult r = decode_bytes(tag_only);
  EXPECT_EQ(r.reason, RejectReason::kMissingBody);
  EXPECT_EQ(r.type, MessageType::kPoseSample);
}

TEST(CodecRejects, UnknownUnionTypeIsRefusedWithoutBeingRead) {
  for (const int tag : {static_cast<int>(MessageType::kBye) + 1, 77, 255}) {
    const auto bytes = test::craft([tag](flatbuffers::FlatBufferBuilder& b) {
      return std::pair{static_cast<wire::Body>(tag), wire::CreateBye(b, 42).Union()};
    });
    const DecodeResult r = decode_bytes(bytes);
    EXPECT_EQ(r.reason, RejectReason::kUnknownMessageType) << tag;
    EXPECT_EQ(r.type, MessageType::kNone) << tag;
    EXPECT_FALSE(error_reply_allowed(r));
  }
}

// ---- counts and frame ids ---------------------------------------------------------------------

TEST(CodecRejects, PoseSampleWithNoneOrTooManyFramesIsBadCount) {
  EXPECT_EQ(decode_bytes(test::craft_pose(42, {})).reason, RejectReason::kBadCount);
  const auto no_vector = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    return std::pair{wire::Body::PoseSample, wire::CreatePoseSample(b, 42, 1, 1).Union()};
  });
  EXPECT_EQ(decode_bytes(no_vector).reason, RejectReason::kBadCount);

  std::vector<FramePose> too_many = test::poses_of(test::sample_pose(kMaxFrames));
  too_many.push_back({60000, {}, {}});
  EXPECT_EQ(decode_bytes(test::craft_pose(42, too_many)).reason, RejectReason::kBadCount);
  too_many.pop_back();
  EXPECT_TRUE(decode_bytes(test::craft_pose(42, too_many)).ok()) << "kMaxFrames itself is accepted";
}

TEST(CodecRejects, ForceSampleWithNoneOrTooManyFramesIsBadCount) {
  EXPECT_EQ(decode_bytes(test::craft_force(42, {})).reason, RejectReason::kBadCount);
  std::vector<FrameWrench> wrenches(kMaxFrames + 1);
  for (std::size_t i = 0; i < wrenches.size(); ++i) wrenches[i].frame = static_cast<std::uint16_t>(i);
  EXPECT_EQ(decode_bytes(test::craft_force(42, wrenches)).reason, RejectReason::kBadCount);
  wrenches.pop_back();
  EXPECT_TRUE(decode_bytes(test::craft_force(42, wrenches)).ok());
}

TEST(CodecRejects, HelloWithNoneOrTooManyFramesIsBadCountAndAnswerable) {
  for (const std::size_t n : {std::size_t{0}, kMaxFrames + 1, 2 * kMaxFrames}) {
    const DecodeResult r = decode_bytes(hello_with(test::raw_frames(n)));
    EXPECT_EQ(r.reason, RejectReason::kBadCount) << n;
    EXPECT_EQ(r.type, MessageType::kHello);
    EXPECT_TRUE(error_reply_allowed(r));
    EXPECT_EQ(error_code_for(r.reason), ErrorCode::kMalformedHello);
  }
  // Past the Verifier's table budget (2 + 2 kMaxFrames tables) the buffer is not even read.
  EXPECT_EQ(decode_bytes(hello_with(test::raw_frames(2 * kMaxFrames + 1))).reason, RejectReason::kVerifyFailed);
}

TEST(CodecRejects, WelcomeWithoutFramesAndStatsWithTooManyReasonsAreBadCount) {
  Welcome welcome = test::sample_welcome();
  welcome.frame_map.clear();
  Encoder encoder;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kBadCount);
  const auto welcome_bytes = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    return std::pair{wire::Body::Welcome, wire::CreateWelcome(b, 42, 1000, 5.0f, 0.1f, 100.0f).Union()};
  });
  EXPECT_EQ(decode_bytes(welcome_bytes).reason, RejectReason::kBadCount);

  const auto stats_bytes = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    const std::vector<std::uint64_t> rejected(kMaxStatsReasons + 1, 1);
    const auto vec = b.CreateVector(rejected);
    return std::pair{wire::Body::Stats, wire::CreateStats(b, 42, 0, 0, 0, vec).Union()};
  });
  EXPECT_EQ(decode_bytes(stats_bytes).reason, RejectReason::kBadCount);
}

// Found by tests/fuzz (fuzz_datagram, UBSan): a Stats whose rejected_by_reason ([ulong]) starts 4
// bytes off an 8-byte boundary. The Verifier checks only the vector's length field for alignment,
// so decode must refuse it before reading (a misaligned 8-byte load); no builder produces it.
TEST(CodecRejects, StatsWithAMisalignedEightByteVectorFailsVerification) {
  const std::uint8_t datagram[] = {
    0x14, 0x00, 0x00, 0x00, 0x48, 0x50, 0x54, 0x44, 0x00, 0x00, 0x0e, 0x00,
    0x0a, 0x00, 0x06, 0x00, 0x05, 0x00, 0x08, 0x00, 0x0a, 0x00, 0x00, 0x00,
    0x00, 0x08, 0x01, 0x00, 0x28, 0x00, 0x00, 0x00, 0x00, 0x00, 0x22, 0x00,
    0x60, 0x00, 0x24, 0x00, 0x2c, 0x00, 0x34, 0x00, 0x3c, 0x00, 0x04, 0x00,
    0x44, 0x00, 0x4c, 0x00, 0x54, 0x00, 0x08, 0x00, 0x0c, 0x00, 0x10, 0x00,
    0x14, 0x00, 0x18, 0x00, 0x1c, 0x00, 0x20, 0x00, 0x22, 0x00, 0x00, 0x00,
    0x58, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1a, 0x42, 0x00, 0x80, 0xb6, 0x42,
    0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00, 0x66, 0x72, 0x61, 0x6d, 0x65,
    0x5f, 0x33, 0x00, 0xce, 0xff, 0xff, 0xff, 0x00, 0x03, 0xff, 0x00, 0x04,
    0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00, 0x66, 0x72, 0x61, 0x6d, 0x65,
    0x5f, 0x32, 0x00, 0xe6, 0xff, 0xff, 0xff, 0x00, 0x03, 0x04, 0x00, 0x00,
    0x3e, 0x00, 0x00, 0x00, 0x03, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x11, 0x00, 0x00, 0x00, 0x00, 0x2b, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x56, 0x33, 0xf0, 0x03, 0x76, 0xf1, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x1d, 0x00, 0x00, 0x00, 0x44, 0x00, 0x00, 0x0a, 0x00, 0x0e, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x0e, 0x00, 0x18, 0x00, 0x08, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x6f, 0x00, 0x65
  };
  const DecodeResult r = decode_bytes(AlignedBytes(datagram));
  EXPECT_EQ(r.reason, RejectReason::kVerifyFailed);
  EXPECT_EQ(r.type, MessageType::kStats);
}

TEST(CodecRejects, DuplicateOrUnsortedFrameIds) {
  std::vector<FramePose> poses = test::poses_of(test::sample_pose(4));
  poses[2].frame = poses[1].frame;  // duplicate
  EXPECT_EQ(decode_bytes(test::craft_pose(42, poses)).reason, RejectReason::kFrameIdsNotIncreasing);
  poses = test::poses_of(test::sample_pose(4));
  std::swap(poses[0], poses[3]);  // unsorted
  EXPECT_EQ(decode_bytes(test::craft_pose(42, poses)).reason, RejectReason::kFrameIdsNotIncreasing);

  std::vector<FrameWrench> wrenches(3);
  wrenches[0].frame = 5;
  wrenches[1].frame = 5;
  wrenches[2].frame = 6;
  EXPECT_EQ(decode_bytes(test::craft_force(42, wrenches)).reason, RejectReason::kFrameIdsNotIncreasing);

  std::vector<RawFrame> frames = glove_frames();
  frames[7].id = frames[6].id;
  const DecodeResult hello = decode_bytes(hello_with(frames));
  EXPECT_EQ(hello.reason, RejectReason::kFrameIdsNotIncreasing);
  EXPECT_TRUE(error_reply_allowed(hello));

  Welcome welcome = test::sample_welcome(3);
  welcome.frame_map[2].client_frame = welcome.frame_map[0].client_frame;
  Encoder encoder;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kFrameIdsNotIncreasing);
}

// ---- numbers --------------------------------------------------------------------------------

// Every float of a pose, in turn, set to NaN, +Inf and -Inf.
TEST(CodecRejects, NonFinitePoseInAnyComponent) {
  const PoseSample valid = test::sample_pose(3);
  int cases = 0;
  for (const float bad : {kNaN, kInf, -kInf}) {
    for (int component = 0; component < 7; ++component) {
      std::vector<FramePose> poses = test::poses_of(valid);
      FramePose& p = poses[1];
      float* fields[7] = {&p.position_m.x,  &p.position_m.y,  &p.position_m.z, &p.orientation.w,
                          &p.orientation.x, &p.orientation.y, &p.orientation.z};
      *fields[component] = bad;
      const DecodeResult r = decode_bytes(test::craft_pose(42, poses));
      EXPECT_EQ(r.reason, RejectReason::kNonFinite) << component;
      EXPECT_EQ(r.session_id, 42u) << "the server can zero the force of the session that sent it";
      EXPECT_FALSE(error_reply_allowed(r));
      ++cases;
    }
  }
  EXPECT_EQ(cases, 21);
}

TEST(CodecRejects, NonFiniteForceAndTorqueNeverPassEitherWay) {
  ForceSample m = test::sample_force(2);
  Encoder encoder;
  for (const float bad : {kNaN, kInf, -kInf}) {
    m.wrenches[1].wrench.force_n.y = bad;
    const EncodeResult sent = encoder.encode(m);
    EXPECT_EQ(sent.reason, RejectReason::kNonFinite) << "the server cannot emit a non-finite force";
    EXPECT_TRUE(sent.bytes.empty());
    EXPECT_EQ(decode_bytes(test::craft_force(42, {m.wrenches.begin(), m.wrenches.end()})).reason,
              RejectReason::kNonFinite);
    m.wrenches[1].wrench.force_n.y = 0.0f;
    m.wrenches[0].wrench.torque_nm.z = bad;
    EXPECT_EQ(encoder.encode(m).reason, RejectReason::kNonFinite);
    EXPECT_EQ(decode_bytes(test::craft_force(42, {m.wrenches.begin(), m.wrenches.end()})).reason,
              RejectReason::kNonFinite);
    m.wrenches[0].wrench.torque_nm.z = 0.0f;
  }
}

TEST(CodecRejects, NonFiniteLimitsAndFigures) {
  Encoder encoder;
  Welcome welcome = test::sample_welcome();
  welcome.force_limit_n = kNaN;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kNonFinite);
  const auto welcome_bytes = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    const wire::FrameMapEntry entry(1, 0);
    const auto map = b.CreateVectorOfStructs(&entry, 1);
    return std::pair{wire::Body::Welcome, wire::CreateWelcome(b, 42, 1000, 5.0f, kInf, 100.0f, map).Union()};
  });
  EXPECT_EQ(decode_bytes(welcome_bytes).reason, RejectReason::kNonFinite);
  Stats stats = test::sample_stats();
  stats.tick_jitter_p99_us = kNaN;
  EXPECT_EQ(encoder.encode(stats).reason, RejectReason::kNonFinite);
}

TEST(CodecRejects, QuaternionNormOutsideTheAcceptedRange) {
  for (const Quat q : {Quat{0, 0, 0, 0}, Quat{0.49f, 0, 0, 0}, Quat{0, 0.28f, 0.28f, 0.28f}, Quat{2.01f, 0, 0, 0},
                       Quat{1e20f, 1e20f, 0, 0}}) {
    std::vector<FramePose> poses = test::poses_of(test::sample_pose(2));
    poses[0].orientation = q;
    EXPECT_EQ(decode_bytes(test::craft_pose(42, poses)).reason, RejectReason::kBadQuaternion) << q.w;
  }
}

TEST(CodecRejects, AbsurdButFiniteNumbersAreOutOfRange) {
  std::vector<FramePose> poses = test::poses_of(test::sample_pose(1));
  poses[0].position_m.z = kMaxPositionM;
  EXPECT_TRUE(decode_bytes(test::craft_pose(42, poses)).ok());
  poses[0].position_m.z = -1.001f * kMaxPositionM;
  EXPECT_EQ(decode_bytes(test::craft_pose(42, poses)).reason, RejectReason::kOutOfRange);

  std::vector<FrameWrench> wrenches(1);
  wrenches[0].wrench.force_n.x = 1.001f * kMaxForceN;
  EXPECT_EQ(decode_bytes(test::craft_force(42, wrenches)).reason, RejectReason::kOutOfRange);
  wrenches[0].wrench.force_n.x = 0.0f;
  wrenches[0].wrench.torque_nm.y = -1.001f * kMaxTorqueNm;
  EXPECT_EQ(decode_bytes(test::craft_force(42, wrenches)).reason, RejectReason::kOutOfRange);

  Encoder encoder;
  Welcome welcome = test::sample_welcome();
  welcome.force_limit_n = 0.0f;  // a zero limit is no device
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kOutOfRange);
  welcome = test::sample_welcome();
  welcome.torque_limit_nm = -0.1f;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kOutOfRange);
  welcome.torque_limit_nm = 0.0f;  // a 3-DoF device renders no torque
  EXPECT_TRUE(encoder.encode(welcome).ok());
  Stats stats = test::sample_stats();
  stats.haptic_rate_hz = -1.0f;
  EXPECT_EQ(encoder.encode(stats).reason, RejectReason::kOutOfRange);
}

// ---- hello fields -----------------------------------------------------------------------------

TEST(CodecRejects, DofOtherThanThreeOrSix) {
  for (int dof = 0; dof < 256; ++dof) {
    std::vector<RawFrame> frames = glove_frames();
    frames[4].dof = static_cast<std::uint8_t>(dof);
    const DecodeResult r = decode_bytes(hello_with(frames));
    if (dof == 3 || dof == 6) {
      EXPECT_TRUE(r.ok()) << dof;
    } else {
      EXPECT_EQ(r.reason, RejectReason::kBadDof) << dof;
      EXPECT_TRUE(error_reply_allowed(r));
    }
  }
}

TEST(CodecRejects, RateOutsideTheSaneRange) {
  EXPECT_TRUE(decode_bytes(hello_with(glove_frames(), kMinRateHz)).ok());
  EXPECT_TRUE(decode_bytes(hello_with(glove_frames(), kMaxRateHz)).ok());
  for (const std::uint32_t rate : {0u, kMinRateHz - 1, kMaxRateHz + 1, 0xFFFF'FFFFu}) {
    EXPECT_EQ(decode_bytes(hello_with(glove_frames(), rate)).reason, RejectReason::kBadRate) << rate;
  }
  Welcome welcome = test::sample_welcome();
  welcome.rate_hz = 0;
  Encoder encoder;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kBadRate);
}

TEST(CodecRejects, UnspecifiedOrUnknownDeviceKind) {
  for (const int kind : {0, 3, 200}) {
    const auto bytes = test::craft_hello("glove", static_cast<wire::DeviceKind>(kind), glove_frames(), 1000);
    EXPECT_EQ(decode_bytes(bytes).reason, RejectReason::kBadDeviceKind) << kind;
  }
}

// The hand a glove names: absent (an older client) reads as unspecified; a value past Right is refused.
TEST(CodecRejects, UnknownHand) {
  for (const int hand : {0, 1, 2}) {
    const auto bytes = test::craft_hello("glove", wire::DeviceKind::Glove, glove_frames(), 1000, 0, kProtocolVersion,
                                         static_cast<wire::Hand>(hand));
    const DecodeResult r = decode_bytes(bytes);
    ASSERT_TRUE(r.ok()) << hand;
  }
  for (const int hand : {3, 255}) {
    const auto bytes = test::craft_hello("glove", wire::DeviceKind::Glove, glove_frames(), 1000, 0, kProtocolVersion,
                                         static_cast<wire::Hand>(hand));
    EXPECT_EQ(decode_bytes(bytes).reason, RejectReason::kBadDeviceKind) << hand;
  }
  Hello hello = test::sample_hello();
  hello.hand = static_cast<Hand>(3);
  Encoder encoder;
  EXPECT_EQ(encoder.encode(hello).reason, RejectReason::kBadDeviceKind);
}

TEST(CodecRejects, StringsAndBytesLongerThanTheirBounds) {
  const auto hello = [](std::size_t name, std::size_t frame_name, std::size_t credentials) {
    std::vector<RawFrame> frames = test::raw_frames(2);
    frames[1].name = std::string(frame_name, 'f');
    return test::craft_hello(std::string(name, 'c'), wire::DeviceKind::Stylus, frames, 1000, credentials);
  };
  EXPECT_TRUE(decode_bytes(hello(kMaxClientName, kMaxFrameName, kMaxCredentials)).ok());
  EXPECT_EQ(decode_bytes(hello(kMaxClientName + 1, 4, 0)).reason, RejectReason::kFieldTooLong);
  EXPECT_EQ(decode_bytes(hello(8, kMaxFrameName + 1, 0)).reason, RejectReason::kFieldTooLong);
  EXPECT_EQ(decode_bytes(hello(8, 4, kMaxCredentials + 1)).reason, RejectReason::kFieldTooLong);

  const auto error = [](std::size_t n) {
    return test::craft([n](flatbuffers::FlatBufferBuilder& b) {
      const auto message = b.CreateString(std::string(n, 'e'));
      return std::pair{wire::Body::Error, wire::CreateError(b, wire::ErrorCode::Internal, message).Union()};
    });
  };
  EXPECT_TRUE(decode_bytes(error(kMaxErrorMessage)).ok());
  EXPECT_EQ(decode_bytes(error(kMaxErrorMessage + 1)).reason, RejectReason::kFieldTooLong);

  FixedString<4> s;
  EXPECT_FALSE(s.assign("12345"));  // the struct side cannot hold it either
}

TEST(CodecRejects, EmptyNamesAndControlCharacters) {
  const auto client = [](const std::string& name) {
    return decode_bytes(test::craft_hello(name, wire::DeviceKind::Stylus, test::raw_frames(1), 1000)).reason;
  };
  EXPECT_EQ(client(""), RejectReason::kBadString);
  EXPECT_EQ(client("glove\nFAKE LOG LINE"), RejectReason::kBadString);
  EXPECT_EQ(client(std::string("nul\0inside", 10)), RejectReason::kBadString);
  EXPECT_EQ(client("del\x7F"), RejectReason::kBadString);
  EXPECT_EQ(client("gl\xC3\xB6ve"), RejectReason::kNone) << "UTF-8 is allowed";

  std::vector<RawFrame> frames = test::raw_frames(2);
  frames[0].name = "";
  EXPECT_EQ(decode_bytes(hello_with(frames)).reason, RejectReason::kBadString);
  frames[0].name = "tab\there";
  EXPECT_EQ(decode_bytes(hello_with(frames)).reason, RejectReason::kBadString);

  Error error = test::sample_error();
  error.message = "line\r\n";
  Encoder encoder;
  EXPECT_EQ(encoder.encode(error).reason, RejectReason::kBadString);
  error.message = "";
  EXPECT_TRUE(encoder.encode(error).ok()) << "an error may carry no message";
}

TEST(CodecRejects, SessionZeroWhereASessionIsRequired) {
  Encoder encoder;
  PoseSample pose = test::sample_pose(1);
  pose.session_id = kNoSession;
  EXPECT_EQ(encoder.encode(pose).reason, RejectReason::kBadSession);
  EXPECT_EQ(decode_bytes(test::craft_pose(kNoSession, test::poses_of(test::sample_pose(1)))).reason,
            RejectReason::kBadSession);
  ForceSample force = test::sample_force(1);
  force.session_id = kNoSession;
  EXPECT_EQ(encoder.encode(force).reason, RejectReason::kBadSession);
  Welcome welcome = test::sample_welcome();
  welcome.session_id = kNoSession;
  EXPECT_EQ(encoder.encode(welcome).reason, RejectReason::kBadSession);
  EXPECT_EQ(encoder.encode(Heartbeat{}).reason, RejectReason::kBadSession);
  EXPECT_EQ(encoder.encode(StatsRequest{}).reason, RejectReason::kBadSession);
  EXPECT_EQ(encoder.encode(Stats{}).reason, RejectReason::kBadSession);
  EXPECT_EQ(encoder.encode(Bye{}).reason, RejectReason::kBadSession);
  const auto bye = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    return std::pair{wire::Body::Bye, wire::CreateBye(b, kNoSession).Union()};
  });
  EXPECT_EQ(decode_bytes(bye).reason, RejectReason::kBadSession);
}

// ---- the reasons themselves -------------------------------------------------------------------

TEST(RejectReasons, EachHasADistinctName) {
  std::set<std::string_view> names;
  for (std::size_t i = 0; i < kRejectReasonCount; ++i) {
    const std::string_view name = to_string(static_cast<RejectReason>(i));
    EXPECT_FALSE(name.empty());
    EXPECT_NE(name, "unknown") << i;
    names.insert(name);
  }
  EXPECT_EQ(names.size(), kRejectReasonCount);
  EXPECT_EQ(kRejectReasonCount, 29u);
  EXPECT_EQ(to_string(static_cast<RejectReason>(kRejectReasonCount)), "unknown");
  EXPECT_EQ(to_string(RejectReason::kVerifyFailed), "verify_failed");
}

TEST(RejectReasons, MatchTheSchemaNames) {
  // haptic.fbs spells them in CamelCase; the stats of a Python client read them from there.
  for (std::size_t i = 0; i < kRejectReasonCount; ++i) {
    std::string camel;
    bool upper = true;
    for (const char c : to_string(static_cast<RejectReason>(i))) {
      if (c == '_') {
        upper = true;
        continue;
      }
      camel += upper ? static_cast<char>(c - 'a' + 'A') : c;
      upper = false;
    }
    EXPECT_EQ(camel, wire::EnumNameRejectReason(static_cast<wire::RejectReason>(i))) << i;
  }
}

TEST(RejectReasons, OnlyHelloRejectionsAreAnswered) {
  DecodeResult r;
  r.reason = RejectReason::kBadDof;
  r.type = MessageType::kHello;
  EXPECT_TRUE(error_reply_allowed(r));
  EXPECT_EQ(error_code_for(r.reason), ErrorCode::kMalformedHello);
  for (const MessageType type : {MessageType::kNone, MessageType::kPoseSample, MessageType::kBye}) {
    r.type = type;
    EXPECT_FALSE(error_reply_allowed(r)) << to_string(type);
  }
}

}  // namespace
}  // namespace hapticd::protocol
