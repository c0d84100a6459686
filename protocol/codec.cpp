#include "protocol/codec.hpp"

#include <flatbuffers/flatbuffers.h>

#include <cassert>
#include <cmath>
#include <cstring>
#include <string_view>

#include "protocol/haptic_generated.h"

namespace hapticd::protocol {
namespace {

namespace wire = hapticd::wire;

// The C++ enums mirror the schema's numbering; a schema edit that breaks it fails here.
static_assert(static_cast<int>(wire::Body::Hello) == static_cast<int>(MessageType::kHello));
static_assert(static_cast<int>(wire::Body::Welcome) == static_cast<int>(MessageType::kWelcome));
static_assert(static_cast<int>(wire::Body::Error) == static_cast<int>(MessageType::kError));
static_assert(static_cast<int>(wire::Body::PoseSample) == static_cast<int>(MessageType::kPoseSample));
static_assert(static_cast<int>(wire::Body::ForceSample) == static_cast<int>(MessageType::kForceSample));
static_assert(static_cast<int>(wire::Body::Heartbeat) == static_cast<int>(MessageType::kHeartbeat));
static_assert(static_cast<int>(wire::Body::StatsRequest) == static_cast<int>(MessageType::kStatsRequest));
static_assert(static_cast<int>(wire::Body::Stats) == static_cast<int>(MessageType::kStats));
static_assert(static_cast<int>(wire::Body::Bye) == static_cast<int>(MessageType::kBye));
static_assert(static_cast<int>(wire::Body::MAX) == static_cast<int>(MessageType::kBye));
static_assert(static_cast<int>(wire::DeviceKind::Stylus) == static_cast<int>(DeviceKind::kStylus));
static_assert(static_cast<int>(wire::DeviceKind::Glove) == static_cast<int>(DeviceKind::kGlove));
static_assert(static_cast<int>(wire::ErrorCode::MAX) == static_cast<int>(ErrorCode::kShuttingDown));
static_assert(static_cast<int>(wire::ErrorCode::VersionMismatch) == static_cast<int>(ErrorCode::kVersionMismatch));
static_assert(static_cast<int>(wire::ErrorCode::MalformedHello) == static_cast<int>(ErrorCode::kMalformedHello));
static_assert(static_cast<int>(wire::ForceFlags::InContact) == ForceFlags::kInContact);
static_assert(static_cast<int>(wire::ForceFlags::Clamped) == ForceFlags::kClamped);
static_assert(static_cast<int>(wire::ForceFlags::Stale) == ForceFlags::kStale);
static_assert(static_cast<int>(wire::ForceFlags::Resynced) == ForceFlags::kResynced);
static_assert(static_cast<std::size_t>(wire::RejectReason::MAX) + 1 == kRejectReasonCount);
static_assert(static_cast<int>(wire::RejectReason::VerifyFailed) == static_cast<int>(RejectReason::kVerifyFailed));
static_assert(static_cast<int>(wire::RejectReason::BadString) == static_cast<int>(RejectReason::kBadString));
static_assert(static_cast<int>(wire::RejectReason::BadSession) == static_cast<int>(RejectReason::kBadSession));
static_assert(sizeof(wire::FramePose) == 32 && sizeof(wire::FrameWrench) == 28);

// Message > body > TrackedFrame is the deepest table path of this schema; fields added by newer
// schemas are not descended into by this verifier, so they do not count.
constexpr flatbuffers::uoffset_t kVerifierMaxDepth = 3;
// Message + body + up to 2 kMaxFrames TrackedFrames: a Hello that declares a few frames too many
// still verifies and gets a kBadCount answer instead of silence; kMaxDatagram bounds the rest.
constexpr flatbuffers::uoffset_t kVerifierMaxTables = 2 + 2 * kMaxFrames;

// Builder memory: the largest datagram plus the builder's scratch (vtables, field locations).
constexpr std::size_t kBuilderReserve = 4 * kMaxDatagram;

// ---- checks shared by validate() (encode) and decode() ------------------------------------

bool printable(std::string_view text) noexcept {
  for (const char c : text) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 || u == 0x7F) return false;  // control characters would forge log lines
  }
  return true;
}

RejectReason check_name(std::string_view name) noexcept {
  return !name.empty() && printable(name) ? RejectReason::kNone : RejectReason::kBadString;
}

RejectReason check_session(std::uint64_t session_id) noexcept {
  return session_id == kNoSession ? RejectReason::kBadSession : RejectReason::kNone;
}

RejectReason check_rate(std::uint32_t rate_hz) noexcept {
  return rate_hz < kMinRateHz || rate_hz > kMaxRateHz ? RejectReason::kBadRate : RejectReason::kNone;
}

bool finite(const Vec3& v) noexcept { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }
bool finite(const Quat& q) noexcept {
  return std::isfinite(q.w) && std::isfinite(q.x) && std::isfinite(q.y) && std::isfinite(q.z);
}
bool within(const Vec3& v, float bound) noexcept {
  return std::fabs(v.x) <= bound && std::fabs(v.y) <= bound && std::fabs(v.z) <= bound;
}
float norm(const Quat& q) noexcept { return std::sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z); }

RejectReason check_pose(const FramePose& p) noexcept {
  if (!finite(p.position_m) || !finite(p.orientation)) return RejectReason::kNonFinite;
  if (!within(p.position_m, kMaxPositionM)) return RejectReason::kOutOfRange;
  const float n = norm(p.orientation);
  if (!(n >= kMinQuaternionNorm && n <= kMaxQuaternionNorm)) return RejectReason::kBadQuaternion;
  return RejectReason::kNone;
}

RejectReason check_wrench(const Wrench& w) noexcept {
  if (!finite(w.force_n) || !finite(w.torque_nm)) return RejectReason::kNonFinite;
  if (!within(w.force_n, kMaxForceN) || !within(w.torque_nm, kMaxTorqueNm)) return RejectReason::kOutOfRange;
  return RejectReason::kNone;
}

// A figure that must be finite and in [lo, hi]; lo_open excludes lo itself.
RejectReason check_figure(float value, float lo, float hi, bool lo_open = false) noexcept {
  if (!std::isfinite(value)) return RejectReason::kNonFinite;
  const bool above = lo_open ? value > lo : value >= lo;
  return above && value <= hi ? RejectReason::kNone : RejectReason::kOutOfRange;
}

// Per-frame data must name each frame once, sorted: O(n) instead of a duplicate search.
template <typename Items, typename IdOf>
bool ids_increasing(const Items& items, IdOf id_of) noexcept {
  for (std::size_t i = 1; i < items.size(); ++i) {
    if (id_of(items[i]) <= id_of(items[i - 1])) return false;
  }
  return true;
}

// Frame-indexed vectors hold at least one frame (a session tracks at least one).
template <typename Items>
bool frame_count_ok(const Items& items) noexcept {
  return !items.empty() && items.size() <= kMaxFrames;
}

// ---- wire -> struct ------------------------------------------------------------------------

template <std::size_t N>
bool copy_string(const flatbuffers::String* s, FixedString<N>& out) noexcept {
  if (s == nullptr) return out.assign({});
  return out.assign(std::string_view(s->c_str(), s->size()));
}

Vec3 from_wire(const wire::Vec3& v) noexcept { return {v.x(), v.y(), v.z()}; }
Quat from_wire(const wire::Quat& q) noexcept { return {q.w(), q.x(), q.y(), q.z()}; }
wire::Vec3 to_wire(const Vec3& v) noexcept { return {v.x, v.y, v.z}; }
wire::Quat to_wire(const Quat& q) noexcept { return {q.w, q.x, q.y, q.z}; }

RejectReason read(const wire::Hello& w, Hello& m) noexcept {
  if (!copy_string(w.client_name(), m.client_name)) return RejectReason::kFieldTooLong;
  m.device_kind = static_cast<DeviceKind>(w.device_kind());
  const auto* frames = w.frames();
  if (!m.frames.resize(frames != nullptr ? frames->size() : 0)) return RejectReason::kBadCount;
  for (std::size_t i = 0; i < m.frames.size(); ++i) {
    const wire::TrackedFrame& f = *frames->Get(static_cast<flatbuffers::uoffset_t>(i));
    m.frames[i].id = f.id();
    m.frames[i].dof = f.dof();
    if (!copy_string(f.name(), m.frames[i].name)) return RejectReason::kFieldTooLong;
  }
  m.requested_rate_hz = w.requested_rate_hz();
  m.hand = static_cast<Hand>(w.hand());
  const auto* credentials = w.credentials();
  if (!m.credentials.assign(credentials != nullptr ? std::span(credentials->data(), credentials->size())
                                                   : std::span<const std::uint8_t>())) {
    return RejectReason::kFieldTooLong;
  }
  return validate(m);
}

RejectReason read(const wire::Welcome& w, Welcome& m) noexcept {
  m.session_id = w.session_id();
  m.rate_hz = w.rate_hz();
  m.force_limit_n = w.force_limit_n();
  m.torque_limit_nm = w.torque_limit_nm();
  m.max_force_rate_n_per_s = w.max_force_rate_n_per_s();
  const auto* map = w.frame_map();
  if (!m.frame_map.resize(map != nullptr ? map->size() : 0)) return RejectReason::kBadCount;
  for (std::size_t i = 0; i < m.frame_map.size(); ++i) {
    const wire::FrameMapEntry& e = *map->Get(static_cast<flatbuffers::uoffset_t>(i));
    m.frame_map[i] = {e.client_frame(), e.handle()};
  }
  const auto* nonce = w.server_nonce();
  if (!m.server_nonce.assign(nonce != nullptr ? std::span(nonce->data(), nonce->size())
                                              : std::span<const std::uint8_t>())) {
    return RejectReason::kFieldTooLong;
  }
  return validate(m);
}

RejectReason read(const wire::Error& w, Error& m) noexcept {
  m.code = static_cast<ErrorCode>(w.code());
  if (!copy_string(w.message(), m.message)) return RejectReason::kFieldTooLong;
  return validate(m);
}

RejectReason read(const wire::PoseSample& w, PoseSample& m) noexcept {
  m.session_id = w.session_id();
  m.sequence = w.sequence();
  m.client_timestamp_ns = w.client_timestamp_ns();
  m.buttons = w.buttons();
  const auto* poses = w.poses();
  if (!m.poses.resize(poses != nullptr ? poses->size() : 0)) return RejectReason::kBadCount;
  for (std::size_t i = 0; i < m.poses.size(); ++i) {
    const wire::FramePose& p = *poses->Get(static_cast<flatbuffers::uoffset_t>(i));
    m.poses[i] = {p.frame(), from_wire(p.position()), from_wire(p.orientation())};
  }
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return r;
  // Norms are in [kMinQuaternionNorm, kMaxQuaternionNorm] here: the server always sees rotations.
  for (FramePose& p : m.poses) {
    const float n = norm(p.orientation);
    p.orientation = {p.orientation.w / n, p.orientation.x / n, p.orientation.y / n, p.orientation.z / n};
  }
  return RejectReason::kNone;
}

RejectReason read(const wire::ForceSample& w, ForceSample& m) noexcept {
  m.session_id = w.session_id();
  m.sequence = w.sequence();
  m.client_timestamp_ns = w.client_timestamp_ns();
  m.server_receive_ns = w.server_receive_ns();
  m.server_send_ns = w.server_send_ns();
  m.flags = static_cast<std::uint16_t>(w.flags());
  const auto* wrenches = w.wrenches();
  if (!m.wrenches.resize(wrenches != nullptr ? wrenches->size() : 0)) return RejectReason::kBadCount;
  for (std::size_t i = 0; i < m.wrenches.size(); ++i) {
    const wire::FrameWrench& f = *wrenches->Get(static_cast<flatbuffers::uoffset_t>(i));
    m.wrenches[i] = {f.frame(),
                     static_cast<std::uint16_t>(f.flags()),
                     {from_wire(f.wrench().force()), from_wire(f.wrench().torque())}};
  }
  return validate(m);
}

RejectReason read(const wire::Heartbeat& w, Heartbeat& m) noexcept {
  m = {w.session_id(), w.timestamp_ns(), w.echo_timestamp_ns()};
  return validate(m);
}

RejectReason read(const wire::StatsRequest& w, StatsRequest& m) noexcept {
  m.session_id = w.session_id();
  return validate(m);
}

RejectReason read(const wire::Bye& w, Bye& m) noexcept {
  m.session_id = w.session_id();
  return validate(m);
}

RejectReason read(const wire::Stats& w, Stats& m) noexcept {
  m.session_id = w.session_id();
  m.packets_in = w.packets_in();
  m.packets_out = w.packets_out();
  m.packets_dropped = w.packets_dropped();
  m.rejected_by_reason.fill(0);
  if (const auto* rejected = w.rejected_by_reason(); rejected != nullptr) {
    // The Verifier (2.0.8) checks a vector's length field for alignment, not its 8-byte elements:
    // a builder always aligns them, so a misaligned one is forged (and Get() would be UB on it).
    if (reinterpret_cast<std::uintptr_t>(rejected->Data()) % alignof(std::uint64_t) != 0)
      return RejectReason::kVerifyFailed;
    if (rejected->size() > kMaxStatsReasons) return RejectReason::kBadCount;
    // A newer peer may count reasons this build does not know: those are dropped.
    const std::size_t n = std::min<std::size_t>(rejected->size(), kRejectReasonCount);
    for (std::size_t i = 0; i < n; ++i) m.rejected_by_reason[i] = rejected->Get(static_cast<flatbuffers::uoffset_t>(i));
  }
  m.clamps = w.clamps();
  m.resets = w.resets();
  m.overruns = w.overruns();
  m.tick_compute_p50_us = w.tick_compute_p50_us();
  m.tick_compute_p99_us = w.tick_compute_p99_us();
  m.tick_jitter_p99_us = w.tick_jitter_p99_us();
  m.visual_step_median_ms = w.visual_step_median_ms();
  m.haptic_rate_hz = w.haptic_rate_hz();
  m.visual_rate_hz = w.visual_rate_hz();
  m.sessions_active = w.sessions_active();
  m.passivity_energy_j = w.passivity_energy_j();
  m.passivity_damped_j = w.passivity_damped_j();
  m.passivity_actions = w.passivity_actions();
  return validate(m);
}

// The session a verified body names, before its other fields are checked.
std::uint64_t session_of(const wire::Message& message) noexcept {
  switch (message.body_type()) {
    case wire::Body::Welcome:
      return message.body_as_Welcome() != nullptr ? message.body_as_Welcome()->session_id() : kNoSession;
    case wire::Body::PoseSample:
      return message.body_as_PoseSample() != nullptr ? message.body_as_PoseSample()->session_id() : kNoSession;
    case wire::Body::ForceSample:
      return message.body_as_ForceSample() != nullptr ? message.body_as_ForceSample()->session_id() : kNoSession;
    case wire::Body::Heartbeat:
      return message.body_as_Heartbeat() != nullptr ? message.body_as_Heartbeat()->session_id() : kNoSession;
    case wire::Body::StatsRequest:
      return message.body_as_StatsRequest() != nullptr ? message.body_as_StatsRequest()->session_id() : kNoSession;
    case wire::Body::Stats:
      return message.body_as_Stats() != nullptr ? message.body_as_Stats()->session_id() : kNoSession;
    case wire::Body::Bye:
      return message.body_as_Bye() != nullptr ? message.body_as_Bye()->session_id() : kNoSession;
    default:
      return kNoSession;  // Hello and Error carry none; unknown bodies are not read
  }
}

template <typename WireBody, typename Out>
RejectReason read_body(const wire::Message& message, Out& out) noexcept {
  const auto* body = message.body_as<WireBody>();
  if (body == nullptr) return RejectReason::kMissingBody;  // tag set, table offset absent
  return read(*body, out);
}

RejectReason read_message(const wire::Message& message, Message& out) noexcept {
  switch (message.body_type()) {
    case wire::Body::Hello:
      return read_body<wire::Hello>(message, out.hello);
    case wire::Body::Welcome:
      return read_body<wire::Welcome>(message, out.welcome);
    case wire::Body::Error:
      return read_body<wire::Error>(message, out.error);
    case wire::Body::PoseSample:
      return read_body<wire::PoseSample>(message, out.pose_sample);
    case wire::Body::ForceSample:
      return read_body<wire::ForceSample>(message, out.force_sample);
    case wire::Body::Heartbeat:
      return read_body<wire::Heartbeat>(message, out.heartbeat);
    case wire::Body::StatsRequest:
      return read_body<wire::StatsRequest>(message, out.stats_request);
    case wire::Body::Stats:
      return read_body<wire::Stats>(message, out.stats);
    case wire::Body::Bye:
      return read_body<wire::Bye>(message, out.bye);
    case wire::Body::NONE:
      return RejectReason::kMissingBody;
  }
  return RejectReason::kUnknownMessageType;
}

}  // namespace

// ---- validate ------------------------------------------------------------------------------

RejectReason validate(const Hello& m) noexcept {
  if (check_name(m.client_name.view()) != RejectReason::kNone) return RejectReason::kBadString;
  if (m.device_kind != DeviceKind::kStylus && m.device_kind != DeviceKind::kGlove) return RejectReason::kBadDeviceKind;
  if (m.hand != Hand::kUnspecified && m.hand != Hand::kLeft && m.hand != Hand::kRight) return RejectReason::kBadDeviceKind;
  if (!frame_count_ok(m.frames)) return RejectReason::kBadCount;
  if (!ids_increasing(m.frames, [](const TrackedFrame& f) { return f.id; })) {
    return RejectReason::kFrameIdsNotIncreasing;
  }
  for (const TrackedFrame& f : m.frames) {
    if (f.dof != 3 && f.dof != 6) return RejectReason::kBadDof;
    if (check_name(f.name.view()) != RejectReason::kNone) return RejectReason::kBadString;
  }
  return check_rate(m.requested_rate_hz);
}

RejectReason validate(const Welcome& m) noexcept {
  if (const RejectReason r = check_session(m.session_id); r != RejectReason::kNone) return r;
  if (const RejectReason r = check_rate(m.rate_hz); r != RejectReason::kNone) return r;
  if (const RejectReason r = check_figure(m.force_limit_n, 0.0f, kMaxForceN, true); r != RejectReason::kNone) return r;
  if (const RejectReason r = check_figure(m.torque_limit_nm, 0.0f, kMaxTorqueNm); r != RejectReason::kNone) return r;
  if (const RejectReason r = check_figure(m.max_force_rate_n_per_s, 0.0f, kMaxForceRateNPerS, true);
      r != RejectReason::kNone) {
    return r;
  }
  if (!frame_count_ok(m.frame_map)) return RejectReason::kBadCount;
  if (!ids_increasing(m.frame_map, [](const FrameMapEntry& e) { return e.client_frame; })) {
    return RejectReason::kFrameIdsNotIncreasing;
  }
  return RejectReason::kNone;
}

RejectReason validate(const Error& m) noexcept {
  return printable(m.message.view()) ? RejectReason::kNone : RejectReason::kBadString;
}

RejectReason validate(const PoseSample& m) noexcept {
  if (const RejectReason r = check_session(m.session_id); r != RejectReason::kNone) return r;
  if (!frame_count_ok(m.poses)) return RejectReason::kBadCount;
  if (!ids_increasing(m.poses, [](const FramePose& p) { return p.frame; })) {
    return RejectReason::kFrameIdsNotIncreasing;
  }
  for (const FramePose& p : m.poses) {
    if (const RejectReason r = check_pose(p); r != RejectReason::kNone) return r;
  }
  return RejectReason::kNone;
}

RejectReason validate(const ForceSample& m) noexcept {
  if (const RejectReason r = check_session(m.session_id); r != RejectReason::kNone) return r;
  if (!frame_count_ok(m.wrenches)) return RejectReason::kBadCount;
  if (!ids_increasing(m.wrenches, [](const FrameWrench& w) { return w.frame; })) {
    return RejectReason::kFrameIdsNotIncreasing;
  }
  for (const FrameWrench& w : m.wrenches) {
    if (const RejectReason r = check_wrench(w.wrench); r != RejectReason::kNone) return r;
  }
  return RejectReason::kNone;
}

RejectReason validate(const Heartbeat& m) noexcept { return check_session(m.session_id); }
RejectReason validate(const StatsRequest& m) noexcept { return check_session(m.session_id); }
RejectReason validate(const Bye& m) noexcept { return check_session(m.session_id); }

RejectReason validate(const Stats& m) noexcept {
  if (const RejectReason r = check_session(m.session_id); r != RejectReason::kNone) return r;
  constexpr float kHuge = 3.0e38f;  // any finite, non-negative figure
  for (const float figure : {m.tick_compute_p50_us, m.tick_compute_p99_us, m.tick_jitter_p99_us,
                             m.visual_step_median_ms, m.haptic_rate_hz, m.visual_rate_hz, m.passivity_damped_j}) {
    if (const RejectReason r = check_figure(figure, 0.0f, kHuge); r != RejectReason::kNone) return r;
  }
  // The observer's energy has either sign.
  if (const RejectReason r = check_figure(m.passivity_energy_j, -kHuge, kHuge); r != RejectReason::kNone) return r;
  return RejectReason::kNone;
}

// ---- decode --------------------------------------------------------------------------------

DecodeResult decode(std::span<const std::uint8_t> datagram, Message& out) noexcept {
  out.type = MessageType::kNone;
  DecodeResult result;
  const auto reject = [&result](RejectReason reason) {
    result.reason = reason;
    return result;
  };

  // Cheap structural checks first, in the order that names the most specific fault.
  const std::size_t size = datagram.size();
  if (size == 0) return reject(RejectReason::kEmpty);
  if (size > kMaxDatagram) return reject(RejectReason::kTooLong);
  if (size < kMinDatagram) return reject(RejectReason::kTooShort);
  if (size % sizeof(flatbuffers::uoffset_t) != 0) return reject(RejectReason::kOddSize);
  const std::uint8_t* data = datagram.data();
  if (reinterpret_cast<std::uintptr_t>(data) % kDatagramAlignment != 0) return reject(RejectReason::kMisaligned);
  if (!wire::MessageBufferHasIdentifier(data)) return reject(RejectReason::kBadIdentifier);

  flatbuffers::Verifier::Options options;
  options.max_depth = kVerifierMaxDepth;
  options.max_tables = kVerifierMaxTables;
  options.check_alignment = true;
  options.check_nested_flatbuffers = false;  // the schema nests none
  flatbuffers::Verifier verifier(data, size, options);
  if (!wire::VerifyMessageBuffer(verifier)) return reject(RejectReason::kVerifyFailed);

  // Verified: from here reading any field is safe.
  const wire::Message& message = *wire::GetMessage(data);
  result.peer_version = message.protocol_version();
  const auto tag = static_cast<std::uint8_t>(message.body_type());
  if (tag <= static_cast<std::uint8_t>(wire::Body::MAX)) result.type = static_cast<MessageType>(tag);
  result.session_id = session_of(message);
  if (result.peer_version != kProtocolVersion) return reject(RejectReason::kVersionMismatch);
  if (tag > static_cast<std::uint8_t>(wire::Body::MAX)) return reject(RejectReason::kUnknownMessageType);

  if (const RejectReason r = read_message(message, out); r != RejectReason::kNone) return reject(r);
  out.type = result.type;
  return result;
}

// ---- encode --------------------------------------------------------------------------------

struct Encoder::Impl {
  flatbuffers::FlatBufferBuilder builder{kBuilderReserve};

  flatbuffers::FlatBufferBuilder& start() noexcept {
    builder.Clear();  // keeps the memory
    return builder;
  }

  EncodeResult finish(wire::Body type, flatbuffers::Offset<void> body) noexcept {
    const auto root = wire::CreateMessage(builder, kProtocolVersion, type, body);
    // The buffer ends on an 8-aligned address; padding its size to 8 makes it start on one, so
    // it is decodable in place (loopback, tests) with the same alignment rule as received bytes.
    builder.TrackMinAlign(kDatagramAlignment);
    wire::FinishMessageBuffer(builder, root);
    const std::span<const std::uint8_t> bytes(builder.GetBufferPointer(), builder.GetSize());
    assert(reinterpret_cast<std::uintptr_t>(bytes.data()) % kDatagramAlignment == 0);
    if (bytes.size() > kMaxDatagram) return {RejectReason::kTooLong, {}};
    return {RejectReason::kNone, bytes};
  }

  // Structs are copied to a stack array first: 2.0.8's CreateUninitializedVectorOfStructs aligns
  // to sizeof(T), which is wrong for the 28-byte FrameWrench.
  template <typename WireStruct, typename Items, typename Convert>
  flatbuffers::Offset<flatbuffers::Vector<const WireStruct*>> structs(const Items& items, Convert convert) noexcept {
    std::array<WireStruct, kMaxFrames> staged;
    for (std::size_t i = 0; i < items.size(); ++i) staged[i] = convert(items[i]);
    return builder.CreateVectorOfStructs(staged.data(), items.size());
  }
};

Encoder::Encoder() : impl_(std::make_unique<Impl>()) {
  // The builder allocates lazily: make it take its memory now, not on the first hot-path encode.
  encode(Bye{1});
}
Encoder::~Encoder() = default;
Encoder::Encoder(Encoder&&) noexcept = default;
Encoder& Encoder::operator=(Encoder&&) noexcept = default;

EncodeResult Encoder::encode(const Hello& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  // Children before parents: FlatBuffers cannot nest table construction.
  std::array<flatbuffers::Offset<wire::TrackedFrame>, kMaxFrames> frames;
  for (std::size_t i = 0; i < m.frames.size(); ++i) {
    const TrackedFrame& f = m.frames[i];
    const auto name = b.CreateString(f.name.view().data(), f.name.size());
    frames[i] = wire::CreateTrackedFrame(b, f.id, name, f.dof);
  }
  const auto frames_vector = b.CreateVector(frames.data(), m.frames.size());
  const auto name = b.CreateString(m.client_name.view().data(), m.client_name.size());
  const auto credentials =
      m.credentials.empty() ? 0 : b.CreateVector(m.credentials.span().data(), m.credentials.size());
  const auto body = wire::CreateHello(b, name, static_cast<wire::DeviceKind>(m.device_kind), frames_vector,
                                      m.requested_rate_hz, credentials, static_cast<wire::Hand>(m.hand));
  return impl_->finish(wire::Body::Hello, body.Union());
}

EncodeResult Encoder::encode(const Welcome& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto map = impl_->structs<wire::FrameMapEntry>(
      m.frame_map, [](const FrameMapEntry& e) { return wire::FrameMapEntry(e.client_frame, e.handle); });
  const auto nonce =
      m.server_nonce.empty() ? 0 : b.CreateVector(m.server_nonce.span().data(), m.server_nonce.size());
  const auto body = wire::CreateWelcome(b, m.session_id, m.rate_hz, m.force_limit_n, m.torque_limit_nm,
                                        m.max_force_rate_n_per_s, map, nonce);
  return impl_->finish(wire::Body::Welcome, body.Union());
}

EncodeResult Encoder::encode(const Error& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto message = b.CreateString(m.message.view().data(), m.message.size());
  const auto body = wire::CreateError(b, static_cast<wire::ErrorCode>(m.code), message);
  return impl_->finish(wire::Body::Error, body.Union());
}

EncodeResult Encoder::encode(const PoseSample& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto poses = impl_->structs<wire::FramePose>(m.poses, [](const FramePose& p) {
    return wire::FramePose(p.frame, to_wire(p.position_m), to_wire(p.orientation));
  });
  const auto body = wire::CreatePoseSample(b, m.session_id, m.sequence, m.client_timestamp_ns, poses, m.buttons);
  return impl_->finish(wire::Body::PoseSample, body.Union());
}

EncodeResult Encoder::encode(const ForceSample& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto wrenches = impl_->structs<wire::FrameWrench>(m.wrenches, [](const FrameWrench& w) {
    return wire::FrameWrench(w.frame, static_cast<wire::ForceFlags>(w.flags),
                             wire::Wrench(to_wire(w.wrench.force_n), to_wire(w.wrench.torque_nm)));
  });
  const auto body = wire::CreateForceSample(b, m.session_id, m.sequence, m.client_timestamp_ns, m.server_receive_ns,
                                            m.server_send_ns, wrenches, static_cast<wire::ForceFlags>(m.flags));
  return impl_->finish(wire::Body::ForceSample, body.Union());
}

EncodeResult Encoder::encode(const Heartbeat& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto body = wire::CreateHeartbeat(b, m.session_id, m.timestamp_ns, m.echo_timestamp_ns);
  return impl_->finish(wire::Body::Heartbeat, body.Union());
}

EncodeResult Encoder::encode(const StatsRequest& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto body = wire::CreateStatsRequest(b, m.session_id);
  return impl_->finish(wire::Body::StatsRequest, body.Union());
}

EncodeResult Encoder::encode(const Stats& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto rejected = b.CreateVector(m.rejected_by_reason.data(), m.rejected_by_reason.size());
  const auto body =
      wire::CreateStats(b, m.session_id, m.packets_in, m.packets_out, m.packets_dropped, rejected, m.clamps, m.resets,
                        m.overruns, m.tick_compute_p50_us, m.tick_compute_p99_us, m.tick_jitter_p99_us,
                        m.visual_step_median_ms, m.haptic_rate_hz, m.visual_rate_hz, m.sessions_active,
                        m.passivity_energy_j, m.passivity_damped_j, m.passivity_actions);
  return impl_->finish(wire::Body::Stats, body.Union());
}

EncodeResult Encoder::encode(const Bye& m) noexcept {
  if (const RejectReason r = validate(m); r != RejectReason::kNone) return {r, {}};
  auto& b = impl_->start();
  const auto body = wire::CreateBye(b, m.session_id);
  return impl_->finish(wire::Body::Bye, body.Union());
}

EncodeResult Encoder::encode(const Message& m) noexcept {
  switch (m.type) {
    case MessageType::kHello:
      return encode(m.hello);
    case MessageType::kWelcome:
      return encode(m.welcome);
    case MessageType::kError:
      return encode(m.error);
    case MessageType::kPoseSample:
      return encode(m.pose_sample);
    case MessageType::kForceSample:
      return encode(m.force_sample);
    case MessageType::kHeartbeat:
      return encode(m.heartbeat);
    case MessageType::kStatsRequest:
      return encode(m.stats_request);
    case MessageType::kStats:
      return encode(m.stats);
    case MessageType::kBye:
      return encode(m.bye);
    case MessageType::kNone:
      return {RejectReason::kMissingBody, {}};
  }
  return {RejectReason::kUnknownMessageType, {}};
}

// ---- replies -------------------------------------------------------------------------------

bool error_reply_allowed(const DecodeResult& result) noexcept { return result.type == MessageType::kHello; }

ErrorCode error_code_for(RejectReason reason) noexcept {
  switch (reason) {
    case RejectReason::kNone:
      return ErrorCode::kUnspecified;
    case RejectReason::kVersionMismatch:
      return ErrorCode::kVersionMismatch;
    default:
      return ErrorCode::kMalformedHello;
  }
}

}  // namespace hapticd::protocol
