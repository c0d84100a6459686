#pragma once

// Shared by the protocol tests: messages with every field set to a distinct non-default value,
// an aligned byte buffer that stands in for a socket read, and builders of hostile datagrams the
// Encoder refuses to produce (they go through the generated FlatBuffers API directly).

#include <flatbuffers/flatbuffers.h>

#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <vector>

#include "protocol/codec.hpp"
#include "protocol/haptic_generated.h"

namespace hapticd::protocol::test {

namespace wire = hapticd::wire;

// Bytes on an 8-aligned address, like a ReceiveBuffer, but of any length (oversize tests).
class AlignedBytes {
 public:
  AlignedBytes() = default;
  explicit AlignedBytes(std::span<const std::uint8_t> bytes) { assign(bytes); }

  void assign(std::span<const std::uint8_t> bytes) {
    resize(bytes.size());
    if (!bytes.empty()) std::memcpy(data(), bytes.data(), bytes.size());
  }
  // Keeps the first min(size, n) bytes; new bytes are zero.
  void resize(std::size_t n) {
    storage_.resize(n / 8 + 1, 0);  // +1: data() stays valid for n == 0
    if (n > size_) std::memset(data() + size_, 0, n - size_);
    size_ = n;
  }
  std::uint8_t* data() { return reinterpret_cast<std::uint8_t*>(storage_.data()); }
  const std::uint8_t* data() const { return reinterpret_cast<const std::uint8_t*>(storage_.data()); }
  std::size_t size() const { return size_; }
  std::span<const std::uint8_t> span() const { return {data(), size_}; }
  std::uint8_t& operator[](std::size_t i) { return data()[i]; }

 private:
  std::vector<std::uint64_t> storage_ = std::vector<std::uint64_t>(1, 0);
  std::size_t size_ = 0;
};

// Decodes a copy placed on an aligned address, as a receiver sees it.
inline DecodeResult decode_copy(std::span<const std::uint8_t> bytes, Message& out) {
  const AlignedBytes copy(bytes);
  return decode(copy.span(), out);
}

// Exact in float: decode's normalization leaves these unchanged bit for bit.
inline Quat unit_quaternion(std::size_t i) {
  switch (i % 4) {
    case 0:
      return {1.0f, 0.0f, 0.0f, 0.0f};
    case 1:
      return {0.5f, -0.5f, 0.5f, -0.5f};
    case 2:
      return {0.0f, 0.0f, 1.0f, 0.0f};
    default:
      return {-0.5f, 0.5f, 0.5f, 0.5f};
  }
}

inline Hello sample_hello(std::size_t frames = 20) {
  Hello m;
  m.client_name = "glove-left #7";
  m.device_kind = DeviceKind::kGlove;
  m.hand = Hand::kLeft;
  for (std::size_t i = 0; i < frames; ++i) {
    TrackedFrame f;
    f.id = static_cast<std::uint16_t>(3 * i + 1);
    f.dof = i % 3 == 0 ? 6 : 3;
    f.name.assign("frame_" + std::to_string(i));
    m.frames.push_back(f);
  }
  m.requested_rate_hz = 2000;
  for (std::uint8_t b : {0x00, 0xFF, 0x7F, 0x80, 0x42}) m.credentials.push_back(b);
  return m;
}

inline Welcome sample_welcome(std::size_t frames = 20) {
  Welcome m;
  m.session_id = 0x0123456789ABCDEFull;
  m.rate_hz = 1000;
  m.force_limit_n = 7.5f;
  m.torque_limit_nm = 0.25f;
  m.max_force_rate_n_per_s = 400.0f;
  for (std::size_t i = 0; i < frames; ++i) {
    m.frame_map.push_back({static_cast<std::uint16_t>(3 * i + 1), i == 5 ? kNoHandle : static_cast<std::uint16_t>(i)});
  }
  for (std::size_t i = 0; i < kNonceBytes; ++i) m.server_nonce.push_back(static_cast<std::uint8_t>(7 * i + 3));
  return m;
}

inline Error sample_error() {
  Error m;
  m.code = ErrorCode::kUnsupportedRate;
  m.message = "requested 20000 Hz, this server runs at most 4000 Hz";
  return m;
}

inline PoseSample sample_pose(std::size_t frames = 20) {
  PoseSample m;
  m.session_id = 42;
  m.sequence = 0xFFFF'FFFF'0000'0001ull;
  m.client_timestamp_ns = 1'234'567'890'123ull;
  m.buttons = 0b1010'0000'0000'0000'0000'0000'0000'0101u;
  for (std::size_t i = 0; i < frames; ++i) {
    const float s = static_cast<float>(i);
    m.poses.push_back({static_cast<std::uint16_t>(3 * i + 1), {0.01f * s, -0.02f * s, 0.5f + s}, unit_quaternion(i)});
  }
  return m;
}

inline ForceSample sample_force(std::size_t frames = 20) {
  ForceSample m;
  m.session_id = 42;
  m.sequence = 0xFFFF'FFFF'0000'0001ull;
  m.client_timestamp_ns = 1'234'567'890'123ull;
  m.server_receive_ns = 9'000'000'000'001ull;
  m.server_send_ns = 9'000'000'040'002ull;
  m.flags = ForceFlags::kInContact | ForceFlags::kClamped;
  for (std::size_t i = 0; i < frames; ++i) {
    const float s = static_cast<float>(i);
    m.wrenches.push_back({static_cast<std::uint16_t>(3 * i + 1),
                          static_cast<std::uint16_t>(i % 2 == 0 ? ForceFlags::kInContact : 0),
                          {{1.5f * s, -2.0f, 0.125f}, {0.01f, 0.0f, -0.02f * s}}});
  }
  return m;
}

inline Heartbeat sample_heartbeat() { return {42, 5'000'000'000ull, 4'999'000'000ull}; }
inline StatsRequest sample_stats_request() { return {42}; }
inline Bye sample_bye() { return {42}; }

inline Stats sample_stats() {
  Stats m;
  m.session_id = 42;
  m.packets_in = 1'000'001;
  m.packets_out = 999'998;
  m.packets_dropped = 3;
  for (std::size_t i = 0; i < m.rejected_by_reason.size(); ++i) m.rejected_by_reason[i] = 100 + i;
  m.clamps = 17;
  m.resets = 2;
  m.overruns = 5;
  m.tick_compute_p50_us = 38.5f;
  m.tick_compute_p99_us = 91.25f;
  m.tick_jitter_p99_us = 120.0f;
  m.visual_step_median_ms = 12.75f;
  m.haptic_rate_hz = 999.5f;
  m.visual_rate_hz = 60.25f;
  m.sessions_active = 2;
  m.passivity_energy_j = -0.0125f;
  m.passivity_damped_j = 0.5f;
  m.passivity_actions = 77;
  return m;
}

// One valid Message of each type, every field set.
inline std::vector<Message> sample_messages() {
  std::vector<Message> all(9);
  all[0].type = MessageType::kHello;
  all[0].hello = sample_hello();
  all[1].type = MessageType::kWelcome;
  all[1].welcome = sample_welcome();
  all[2].type = MessageType::kError;
  all[2].error = sample_error();
  all[3].type = MessageType::kPoseSample;
  all[3].pose_sample = sample_pose();
  all[4].type = MessageType::kForceSample;
  all[4].force_sample = sample_force();
  all[5].type = MessageType::kHeartbeat;
  all[5].heartbeat = sample_heartbeat();
  all[6].type = MessageType::kStatsRequest;
  all[6].stats_request = sample_stats_request();
  all[7].type = MessageType::kStats;
  all[7].stats = sample_stats();
  all[8].type = MessageType::kBye;
  all[8].bye = sample_bye();
  return all;
}

// Whether the member of `a` named by a.type equals that of `b`.
inline bool same_body(const Message& a, const Message& b) {
  if (a.type != b.type) return false;
  switch (a.type) {
    case MessageType::kHello:
      return a.hello == b.hello;
    case MessageType::kWelcome:
      return a.welcome == b.welcome;
    case MessageType::kError:
      return a.error == b.error;
    case MessageType::kPoseSample:
      return a.pose_sample == b.pose_sample;
    case MessageType::kForceSample:
      return a.force_sample == b.force_sample;
    case MessageType::kHeartbeat:
      return a.heartbeat == b.heartbeat;
    case MessageType::kStatsRequest:
      return a.stats_request == b.stats_request;
    case MessageType::kStats:
      return a.stats == b.stats;
    case MessageType::kBye:
      return a.bye == b.bye;
    case MessageType::kNone:
      return true;
  }
  return false;
}

// ---- hostile datagrams, built without the Encoder's checks ----------------------------------

// Finishes the body that build(builder) returns as {tag, offset} into a datagram.
template <typename BuildBody>
AlignedBytes craft(BuildBody build, std::uint16_t version = kProtocolVersion) {
  flatbuffers::FlatBufferBuilder b;
  const auto [tag, body] = build(b);
  const auto root = wire::CreateMessage(b, version, tag, body);
  wire::FinishMessageBuffer(b, root);
  return AlignedBytes({b.GetBufferPointer(), b.GetSize()});
}

inline AlignedBytes craft_pose(std::uint64_t session_id, const std::vector<FramePose>& poses,
                               std::uint16_t version = kProtocolVersion) {
  return craft(
      [&](flatbuffers::FlatBufferBuilder& b) {
        std::vector<wire::FramePose> staged;
        staged.reserve(poses.size());
        for (const FramePose& p : poses) {
          staged.emplace_back(p.frame, wire::Vec3(p.position_m.x, p.position_m.y, p.position_m.z),
                              wire::Quat(p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z));
        }
        const auto vec = b.CreateVectorOfStructs(staged.data(), staged.size());
        return std::pair{wire::Body::PoseSample, wire::CreatePoseSample(b, session_id, 7, 1000, vec, 0).Union()};
      },
      version);
}

inline std::vector<FramePose> poses_of(const PoseSample& m) { return {m.poses.begin(), m.poses.end()}; }

inline AlignedBytes craft_force(std::uint64_t session_id, const std::vector<FrameWrench>& wrenches) {
  return craft([&](flatbuffers::FlatBufferBuilder& b) {
    std::vector<wire::FrameWrench> staged;
    staged.reserve(wrenches.size());
    for (const FrameWrench& w : wrenches) {
      const Vec3& f = w.wrench.force_n;
      const Vec3& t = w.wrench.torque_nm;
      staged.emplace_back(w.frame, static_cast<wire::ForceFlags>(w.flags),
                          wire::Wrench(wire::Vec3(f.x, f.y, f.z), wire::Vec3(t.x, t.y, t.z)));
    }
    const auto vec = b.CreateVectorOfStructs(staged.data(), staged.size());
    return std::pair{wire::Body::ForceSample, wire::CreateForceSample(b, session_id, 7, 1000, 2000, 3000, vec).Union()};
  });
}

struct RawFrame {
  std::uint16_t id;
  std::uint8_t dof;
  std::string name;
};

inline AlignedBytes craft_hello(const std::string& client_name, wire::DeviceKind kind,
                                const std::vector<RawFrame>& frames, std::uint32_t rate_hz,
                                std::size_t credential_bytes = 0, std::uint16_t version = kProtocolVersion,
                                wire::Hand hand = wire::Hand::Unspecified) {
  return craft(
      [&](flatbuffers::FlatBufferBuilder& b) {
        std::vector<flatbuffers::Offset<wire::TrackedFrame>> offsets;
        offsets.reserve(frames.size());
        for (const RawFrame& f : frames) {
          offsets.push_back(wire::CreateTrackedFrame(b, f.id, b.CreateString(f.name), f.dof));
        }
        const auto frames_vector = b.CreateVector(offsets);
        const auto name = b.CreateString(client_name);
        const std::vector<std::uint8_t> credentials(credential_bytes, 0xA5);
        const auto credentials_vector = credential_bytes > 0 ? b.CreateVector(credentials) : 0;
        return std::pair{wire::Body::Hello,
                         wire::CreateHello(b, name, kind, frames_vector, rate_hz, credentials_vector, hand).Union()};
      },
      version);
}

inline std::vector<RawFrame> raw_frames(std::size_t n) {
  std::vector<RawFrame> frames;
  frames.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    frames.push_back({static_cast<std::uint16_t>(i), 6, "f" + std::to_string(i)});
  }
  return frames;
}

}  // namespace hapticd::protocol::test
