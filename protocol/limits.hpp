#pragma once

// Every bound the wire enforces, in one place: the codec rejects what exceeds them, and the
// fixed-capacity message structs are sized by them so nothing on the hot path allocates.

#include <cstddef>
#include <cstdint>

namespace hapticd::protocol {

// Message.protocol_version written by this build and the only one it accepts.
inline constexpr std::uint16_t kProtocolVersion = 1;

// A glove tracks ~20 frames (palm + 5 x 3 phalanges + wrist); 32 leaves room without letting a
// datagram grow past one Ethernet frame: a full PoseSample is ~1.1 KB.
inline constexpr std::size_t kMaxFrames = 32;

// Largest datagram sent or accepted. The largest legal Hello (32 named frames, longest names and
// credentials) fits; the hot-path samples stay under the 1472-byte UDP payload of a 1500 MTU.
inline constexpr std::size_t kMaxDatagram = 2048;

// Root offset (4) + file identifier (4) + the smallest Message table with its vtable (>= 20)
// + a body table (>= 4): nothing shorter can carry a body.
inline constexpr std::size_t kMinDatagram = 32;

// Received bytes are read in place; 8 covers the widest scalar (u64) in the schema.
inline constexpr std::size_t kDatagramAlignment = 8;

// Bounded strings and bytes (lengths in bytes, UTF-8 allowed, no control characters). 31: a
// frame name then takes 36 bytes on the wire (length, text, NUL), which is what lets 32 of them
// and the longest client name and credentials fit kMaxDatagram.
inline constexpr std::size_t kMaxClientName = 64;
inline constexpr std::size_t kMaxFrameName = 31;
inline constexpr std::size_t kMaxErrorMessage = 256;
inline constexpr std::size_t kMaxCredentials = 128;

// Authentication (auth.hpp): a Hello's credentials and a Welcome's server_nonce are nonces of this
// many random bytes; the pre-shared key has as many.
inline constexpr std::size_t kNonceBytes = 32;

// Rates a device may request or a server may grant, Hz.
inline constexpr std::uint32_t kMinRateHz = 10;
inline constexpr std::uint32_t kMaxRateHz = 10000;

// "Absurd" bounds: finite numbers past these are faults, not motion or force (a device workspace
// is metres, a haptic motor tens of newtons).
inline constexpr float kMaxPositionM = 100.0f;
inline constexpr float kMaxForceN = 10000.0f;
inline constexpr float kMaxTorqueNm = 1000.0f;
inline constexpr float kMaxForceRateNPerS = 1.0e7f;

// Quaternion norms outside this range are garbage, not drift: rejected. Inside, normalized.
inline constexpr float kMinQuaternionNorm = 0.5f;
inline constexpr float kMaxQuaternionNorm = 2.0f;

// Stats.rejected_by_reason entries accepted from a (possibly newer) peer: room for three times
// today's reasons.
inline constexpr std::size_t kMaxStatsReasons = 64;

// FrameMapEntry.handle of a frame the server accepted but drives no handle with.
inline constexpr std::uint16_t kNoHandle = 0xFFFF;

// Session id 0 means "no session"; servers never grant it.
inline constexpr std::uint64_t kNoSession = 0;

}  // namespace hapticd::protocol
