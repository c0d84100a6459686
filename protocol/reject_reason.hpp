#pragma once

#include <cstddef>
#include <cstdint>
#include <string_view>

namespace hapticd::protocol {

// Why a datagram (or a struct handed to the Encoder) was refused. The values are on the wire
// (Stats.rejected_by_reason is indexed by them, haptic.fbs mirrors them): append only.
enum class RejectReason : std::uint8_t {
  kNone = 0,               // accepted
  kEmpty,                  // zero bytes
  kTooShort,               // fewer than kMinDatagram bytes
  kTooLong,                // more than kMaxDatagram bytes
  kOddSize,                // length not a multiple of 4: no FlatBuffers builder produces that
  kMisaligned,             // buffer address not kDatagramAlignment-aligned: cannot read in place
  kBadIdentifier,          // file identifier is not "HPTD"
  kVerifyFailed,           // FlatBuffers Verifier refused it (offsets, bounds, depth, table count)
  kVersionMismatch,        // Message.protocol_version != kProtocolVersion
  kMissingBody,            // union type NONE, or a type without its table
  kUnknownMessageType,     // union type this build does not know
  kBadCount,               // a vector is empty where it must not be or longer than its bound
  kFrameIdsNotIncreasing,  // frame ids duplicated or unsorted
  kBadDof,                 // tracked frame DoF other than 3 or 6
  kNonFinite,              // NaN or Inf in a float field
  kBadQuaternion,          // quaternion norm outside [kMinQuaternionNorm, kMaxQuaternionNorm]
  kOutOfRange,             // finite but absurd: position, force, torque, limit, negative figure
  kBadRate,                // rate outside [kMinRateHz, kMaxRateHz]
  kBadDeviceKind,          // device kind unspecified or unknown
  kFieldTooLong,           // string or byte field longer than its bound
  kBadString,              // empty where a name is required, or holds control characters
  kBadSession,             // session id 0 where a session is required
  // Authentication and sessions (a server with a key; auth.hpp): every one of these is dropped
  // without a reply, except a Hello's kMissingMac / kBadMac (a plain Error{Unauthorized}).
  kMissingMac,      // no authentication trailer where the key requires one
  kBadMac,          // the trailer's tag does not verify (wrong key, corrupted, forged, wrong kind)
  kReplayed,        // authentic, but its counter (or a Hello's nonce) was seen or is too old
  kWrongPeer,       // names a live session but comes from another address than the session's
  kUnknownSession,  // names no live session
  kBadNonce,        // an authenticated Hello whose credentials are not a kNonceBytes client nonce
  // Resource bounds (the server's haptic loop): dropped before it is authenticated or decoded.
  kRateLimited,  // its source (address and port) sent more than its allowance (ServerOptions::source_rate_hz)
};

inline constexpr std::size_t kRejectReasonCount = static_cast<std::size_t>(RejectReason::kRateLimited) + 1;

// Stable snake_case name, for logs and stats ("too_short"); "unknown" past the last enumerator.
std::string_view to_string(RejectReason reason) noexcept;

}  // namespace hapticd::protocol
