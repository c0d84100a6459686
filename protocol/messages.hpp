#pragma once

// The messages of the wire as plain C++ structs (protocol/README.md documents every field).
// No FlatBuffers type appears here: server and clients see only these, and codec.hpp converts.
// Every container has a fixed capacity, so a struct reused across datagrams never allocates.
//
// Conventions: SI units, named in the field (_m, _n, _nm, _ns, _hz); a pose is that of tracked
// frame F in the device base frame D (right-handed); a wrench acts at F's origin, expressed in D;
// timestamps are ns on the sender's CLOCK_MONOTONIC (see clock.hpp).

#include <array>
#include <cstdint>
#include <string_view>

#include "protocol/bounded.hpp"
#include "protocol/limits.hpp"
#include "protocol/reject_reason.hpp"

namespace hapticd::protocol {

// Values are the FlatBuffers union tags of haptic.fbs (checked in codec.cpp).
enum class MessageType : std::uint8_t {
  kNone = 0,
  kHello = 1,
  kWelcome = 2,
  kError = 3,
  kPoseSample = 4,
  kForceSample = 5,
  kHeartbeat = 6,
  kStatsRequest = 7,
  kStats = 8,
  kBye = 9,
};

enum class DeviceKind : std::uint8_t { kUnspecified = 0, kStylus = 1, kGlove = 2 };
// A glove's hand; unspecified: any hand (a stylus, or a client that does not say).
enum class Hand : std::uint8_t { kUnspecified = 0, kLeft = 1, kRight = 2 };

// Unknown codes from a newer peer are kept as their number, not rejected.
enum class ErrorCode : std::uint16_t {
  kUnspecified = 0,
  kVersionMismatch = 1,
  kMalformedHello = 2,
  kUnauthorized = 3,
  kServerFull = 4,
  kUnsupportedDevice = 5,
  kUnsupportedRate = 6,
  kInternal = 7,
  kShuttingDown = 8,
};

// ForceSample.flags and FrameWrench.flags bits. Unknown bits from a newer peer are kept.
struct ForceFlags {
  static constexpr std::uint16_t kInContact = 1u << 0;
  static constexpr std::uint16_t kClamped = 1u << 1;
  static constexpr std::uint16_t kStale = 1u << 2;
  static constexpr std::uint16_t kResynced = 1u << 3;
};

struct Vec3 {
  float x = 0.0f;
  float y = 0.0f;
  float z = 0.0f;
  bool operator==(const Vec3&) const = default;
};

// Scalar first; the identity by default, which is also what 3-DoF frames send.
struct Quat {
  float w = 1.0f;
  float x = 0.0f;
  float y = 0.0f;
  float z = 0.0f;
  bool operator==(const Quat&) const = default;
};

struct TrackedFrame {
  std::uint16_t id = 0;  // chosen by the client; ids strictly increasing within a Hello
  std::uint8_t dof = 6;  // 3: position only, 6: position and orientation
  FixedString<kMaxFrameName> name;
  bool operator==(const TrackedFrame&) const = default;
};

struct Hello {
  FixedString<kMaxClientName> client_name;
  DeviceKind device_kind = DeviceKind::kUnspecified;
  BoundedArray<TrackedFrame, kMaxFrames> frames;
  std::uint32_t requested_rate_hz = 1000;
  // Opaque to the codec; with authentication, the client's kNonceBytes nonce (auth.hpp).
  BoundedArray<std::uint8_t, kMaxCredentials> credentials;
  Hand hand = Hand::kUnspecified;
  bool operator==(const Hello&) const = default;
};

struct FrameMapEntry {
  std::uint16_t client_frame = 0;
  std::uint16_t handle = kNoHandle;  // server handle index the frame drives
  bool operator==(const FrameMapEntry&) const = default;
};

struct Welcome {
  std::uint64_t session_id = kNoSession;
  std::uint32_t rate_hz = 1000;
  float force_limit_n = 0.0f;
  float torque_limit_nm = 0.0f;  // 0 for 3-DoF devices
  float max_force_rate_n_per_s = 0.0f;
  BoundedArray<FrameMapEntry, kMaxFrames> frame_map;  // client_frame strictly increasing
  // kNonceBytes random bytes from a server that authenticates (auth.hpp), else empty.
  BoundedArray<std::uint8_t, kNonceBytes> server_nonce;
  bool operator==(const Welcome&) const = default;
};

struct Error {
  ErrorCode code = ErrorCode::kUnspecified;
  FixedString<kMaxErrorMessage> message;
  bool operator==(const Error&) const = default;
};

struct FramePose {
  std::uint16_t frame = 0;  // client frame id
  Vec3 position_m;          // p_DF
  Quat orientation;         // R_DF; unit after decode (normalized)
  bool operator==(const FramePose&) const = default;
};

struct PoseSample {
  std::uint64_t session_id = kNoSession;
  std::uint64_t sequence = 0;
  std::uint64_t client_timestamp_ns = 0;
  BoundedArray<FramePose, kMaxFrames> poses;  // frame strictly increasing, at least one
  std::uint32_t buttons = 0;                  // bit i: button i pressed
  bool operator==(const PoseSample&) const = default;
};

struct Wrench {
  Vec3 force_n;
  Vec3 torque_nm;
  bool operator==(const Wrench&) const = default;
};

struct FrameWrench {
  std::uint16_t frame = 0;  // client frame id
  std::uint16_t flags = 0;  // ForceFlags: kInContact, kClamped for this frame
  Wrench wrench;
  bool operator==(const FrameWrench&) const = default;
};

struct ForceSample {
  std::uint64_t session_id = kNoSession;
  std::uint64_t sequence = 0;                      // echoed from the PoseSample answered
  std::uint64_t client_timestamp_ns = 0;           // echoed, client clock
  std::uint64_t server_receive_ns = 0;             // server clock
  std::uint64_t server_send_ns = 0;                // server clock
  BoundedArray<FrameWrench, kMaxFrames> wrenches;  // frame strictly increasing, at least one
  std::uint16_t flags = 0;                         // ForceFlags: OR of the frames' + kStale, kResynced
  bool operator==(const ForceSample&) const = default;
};

struct Heartbeat {
  std::uint64_t session_id = kNoSession;
  std::uint64_t timestamp_ns = 0;       // sender clock
  std::uint64_t echo_timestamp_ns = 0;  // the peer's last heartbeat timestamp, 0 if none
  bool operator==(const Heartbeat&) const = default;
};

struct StatsRequest {
  std::uint64_t session_id = kNoSession;
  bool operator==(const StatsRequest&) const = default;
};

// Server-wide figures since start. Counters are counts; figures are >= 0.
struct Stats {
  std::uint64_t session_id = kNoSession;
  std::uint64_t packets_in = 0;
  std::uint64_t packets_out = 0;
  std::uint64_t packets_dropped = 0;
  std::array<std::uint64_t, kRejectReasonCount> rejected_by_reason{};  // index: RejectReason
  std::uint64_t clamps = 0;
  std::uint64_t resets = 0;
  std::uint64_t overruns = 0;
  float tick_compute_p50_us = 0.0f;
  float tick_compute_p99_us = 0.0f;
  float tick_jitter_p99_us = 0.0f;
  float visual_step_median_ms = 0.0f;
  float haptic_rate_hz = 0.0f;
  float visual_rate_hz = 0.0f;
  std::uint32_t sessions_active = 0;
  // The requesting session's passivity observer and controller, summed over its frames: the work its
  // device has done on the rendering (J, may be negative), the energy the damping took back (J, >= 0),
  // and the replies damped.
  float passivity_energy_j = 0.0f;
  float passivity_damped_j = 0.0f;
  std::uint64_t passivity_actions = 0;
  bool operator==(const Stats&) const = default;
};

struct Bye {
  std::uint64_t session_id = kNoSession;
  bool operator==(const Bye&) const = default;
};

// A decoded datagram without std::variant: `type` says which member holds it; the others keep
// whatever they held before, so one Message is reused for every datagram.
struct Message {
  MessageType type = MessageType::kNone;
  Hello hello;
  Welcome welcome;
  Error error;
  PoseSample pose_sample;
  ForceSample force_sample;
  Heartbeat heartbeat;
  StatsRequest stats_request;
  Stats stats;
  Bye bye;
};

std::string_view to_string(MessageType type) noexcept;
std::string_view to_string(DeviceKind kind) noexcept;
std::string_view to_string(Hand hand) noexcept;
std::string_view to_string(ErrorCode code) noexcept;

}  // namespace hapticd::protocol
