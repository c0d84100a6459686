#pragma once

// Encoding and decoding of datagrams. Decoding trusts nothing: size, alignment, identifier, the
// FlatBuffers Verifier, version, union tag, then every count, float and range, before a single
// field reaches the caller. Encoding applies the same rules, so a sender cannot emit what a
// receiver would reject (no NaN force reaches a device through this codec).
//
// Hot path: Encoder::encode(PoseSample / ForceSample) and decode() allocate nothing once the
// Encoder has encoded its first message (tests/protocol/test_codec_no_allocation.cpp proves it).

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include "protocol/limits.hpp"
#include "protocol/messages.hpp"
#include "protocol/reject_reason.hpp"

namespace hapticd::protocol {

// Receive datagrams into this: aligned so decode() reads in place, and one byte longer than
// kMaxDatagram so an oversized datagram shows up as kMaxDatagram + 1 bytes (rejected kTooLong)
// rather than silently truncated to a plausible prefix.
struct alignas(kDatagramAlignment) ReceiveBuffer {
  std::array<std::uint8_t, kMaxDatagram + 1> bytes{};
};

struct DecodeResult {
  RejectReason reason = RejectReason::kNone;
  // Body type once the buffer passed the Verifier (even if a later check rejected it), else kNone.
  MessageType type = MessageType::kNone;
  // Message.protocol_version the sender wrote, once verified (set on kVersionMismatch too), else 0.
  std::uint16_t peer_version = 0;
  // The body's session id once verified, also when a later check rejected it (a NaN pose still
  // names its session, so the server can zero that session's force), else kNoSession. Untrusted:
  // the server acts on it only for the peer address the session belongs to.
  std::uint64_t session_id = kNoSession;

  [[nodiscard]] bool ok() const noexcept { return reason == RejectReason::kNone; }
};

// Verifies `datagram` and fills the member of `out` named by the result's type; sets out.type
// (kNone on rejection, when the target member's contents are unspecified). Quaternions within
// [kMinQuaternionNorm, kMaxQuaternionNorm] come out normalized. Never throws, never allocates,
// never reads outside `datagram`, whatever its bytes.
DecodeResult decode(std::span<const std::uint8_t> datagram, Message& out) noexcept;

// The checks decode() applies after copying, on a plain struct (kNone when valid). encode() runs
// them too. Quaternion norms are only range-checked here, not normalized.
RejectReason validate(const Hello& m) noexcept;
RejectReason validate(const Welcome& m) noexcept;
RejectReason validate(const Error& m) noexcept;
RejectReason validate(const PoseSample& m) noexcept;
RejectReason validate(const ForceSample& m) noexcept;
RejectReason validate(const Heartbeat& m) noexcept;
RejectReason validate(const StatsRequest& m) noexcept;
RejectReason validate(const Stats& m) noexcept;
RejectReason validate(const Bye& m) noexcept;

struct EncodeResult {
  RejectReason reason = RejectReason::kNone;
  // The datagram, kDatagramAlignment-aligned; valid until the Encoder's next encode. Empty when
  // rejected.
  std::span<const std::uint8_t> bytes;

  [[nodiscard]] bool ok() const noexcept { return reason == RejectReason::kNone; }
};

// Owns one FlatBuffers builder whose memory is reused (reserved for kMaxDatagram up front), so
// encoding allocates only in the constructor. One Encoder per sending thread.
class Encoder {
 public:
  Encoder();
  ~Encoder();
  Encoder(const Encoder&) = delete;
  Encoder& operator=(const Encoder&) = delete;
  Encoder(Encoder&&) noexcept;
  Encoder& operator=(Encoder&&) noexcept;

  EncodeResult encode(const Hello& m) noexcept;
  EncodeResult encode(const Welcome& m) noexcept;
  EncodeResult encode(const Error& m) noexcept;
  EncodeResult encode(const PoseSample& m) noexcept;
  EncodeResult encode(const ForceSample& m) noexcept;
  EncodeResult encode(const Heartbeat& m) noexcept;
  EncodeResult encode(const StatsRequest& m) noexcept;
  EncodeResult encode(const Stats& m) noexcept;
  EncodeResult encode(const Bye& m) noexcept;
  // The member named by m.type; kMissingBody for kNone, kUnknownMessageType past kBye.
  EncodeResult encode(const Message& m) noexcept;

 private:
  struct Impl;  // holds the flatbuffers::FlatBufferBuilder, kept out of the public API
  std::unique_ptr<Impl> impl_;
};

// A server answers with an Error only a datagram that verified as a FlatBuffer carrying a Hello,
// accepted or not (a handshake: the peer asked for a reply). Every other rejected datagram is
// dropped and counted: answering unverified bytes would make the server a reflector.
[[nodiscard]] bool error_reply_allowed(const DecodeResult& result) noexcept;

// The ErrorCode that answers a Hello rejected for `reason` (kVersionMismatch or kMalformedHello).
[[nodiscard]] ErrorCode error_code_for(RejectReason reason) noexcept;

}  // namespace hapticd::protocol
