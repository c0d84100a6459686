#pragma once

// Authentication of datagrams with a pre-shared key (protocol/README.md, "Authentication").
//
// A datagram of an authenticating peer is the FlatBuffer followed by a fixed 40-byte trailer:
//
//   offset  bytes  field
//   n - 40  4      magic "HPTA"
//   n - 36  1      kind (TrailerKind)
//   n - 35  3      zero
//   n - 32  8      session id, u64 little-endian (0 in a Hello and in an Error)
//   n - 24  8      counter, u64 little-endian (per session and direction, from 1; 0 in the handshake)
//   n - 16  16     tag: keyed BLAKE2b-128 of bytes [0, n - 16) (the FlatBuffer and the trailer's head)
//
// Keys (all 32 bytes, from the pre-shared key K with libsodium's crypto_kdf, context "hapticd1"):
//   hello key     = kdf(K, 1)                              tags a Hello
//   reply key     = BLAKE2b(key = kdf(K, 2), Nc)           tags the Welcome or Error answering the
//                                                          Hello that carried client nonce Nc
//   session keys  = BLAKE2b-512(key = kdf(K, 3),           first half client -> server, second half
//                    Nc | Ns | session id LE)              server -> client
// Nc is the Hello's credentials, Ns the Welcome's server_nonce, each kNonceBytes random bytes.
//
// Nothing here allocates or throws after construction; the MAC of a 150-byte datagram costs about a
// microsecond (tests/protocol/test_auth.cpp prints it).

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "protocol/limits.hpp"
#include "protocol/reject_reason.hpp"
#include "protocol/sequence_window.hpp"

namespace hapticd::protocol {

inline constexpr std::size_t kKeyBytes = 32;
inline constexpr std::size_t kMacBytes = 16;
inline constexpr std::size_t kAuthTrailerBytes = 40;

using Key = std::array<std::uint8_t, kKeyBytes>;
using Nonce = std::array<std::uint8_t, kNonceBytes>;

enum class TrailerKind : std::uint8_t {
  kHello = 1,           // client -> server, hello key
  kHandshakeReply = 2,  // server -> client: Welcome or Error, reply key of the Hello's nonce
  kClientToServer = 3,  // a session's datagrams from the client, client -> server key
  kServerToClient = 4,  // a session's datagrams from the server, server -> client key
};

struct Trailer {
  TrailerKind kind = TrailerKind::kHello;
  std::uint64_t session_id = 0;
  std::uint64_t counter = 0;
};

struct SessionKeys {
  Key client_to_server{};
  Key server_to_client{};
};

// The keys derived from one pre-shared key, once. Initializes libsodium.
class AuthKeys {
 public:
  explicit AuthKeys(const Key& pre_shared_key);

  [[nodiscard]] const Key& hello_key() const noexcept { return hello_; }
  [[nodiscard]] Key reply_key(const Nonce& client_nonce) const noexcept;
  [[nodiscard]] SessionKeys session_keys(const Nonce& client_nonce, const Nonce& server_nonce,
                                         std::uint64_t session_id) const noexcept;

 private:
  Key hello_{}, reply_{}, session_{};
};

// kNonceBytes from the operating system's generator (getrandom); never allocates.
Nonce random_nonce() noexcept;

// Builds authenticated datagrams in its own aligned buffer of kMaxDatagram bytes.
class Sealer {
 public:
  // The message's bytes, then the trailer with its tag under `key`. Valid until the next seal();
  // empty when the message plus trailer exceeds kMaxDatagram.
  std::span<const std::uint8_t> seal(std::span<const std::uint8_t> message, const Trailer& trailer,
                                     const Key& key) noexcept;

 private:
  alignas(kDatagramAlignment) std::array<std::uint8_t, kMaxDatagram> buffer_{};
};

// Splits a received datagram into the message (the same bytes, aligned as received) and the
// trailer's fields, without checking the tag. kMissingMac when the datagram is too short for a
// trailer or has no magic; kBadMac for a kind no peer sends.
RejectReason split_trailer(std::span<const std::uint8_t> datagram, std::span<const std::uint8_t>& message,
                           Trailer& trailer) noexcept;

// Whether the last kMacBytes of `datagram` are the tag of the bytes before them under `key`
// (compared in constant time).
[[nodiscard]] bool verify_mac(std::span<const std::uint8_t> datagram, const Key& key) noexcept;

// Anti-replay on a verified counter: kNone (and recorded) when it is new, or older than the newest
// but within the window and not seen (reordered); kReplayed when it was seen, is 0, or is too old
// to tell (SequenceWindow::kWindow behind the newest).
RejectReason accept_counter(SequenceWindow& window, std::uint64_t counter) noexcept;

// Remembers the client nonces of the last kCapacity authentic Hellos, so a replayed Hello is
// refused (one recorded long ago may still open a session that nobody can use: see README).
class NonceCache {
 public:
  static constexpr std::size_t kCapacity = 256;
  // False when `nonce` is in the cache; otherwise records it (evicting the oldest) and returns true.
  bool insert(const Nonce& nonce) noexcept;

 private:
  // The first 16 bytes of each nonce: a collision among 256 random 128-bit prefixes is ~2^-113.
  std::array<std::array<std::uint8_t, 16>, kCapacity> entries_{};
  std::size_t next_ = 0, size_ = 0;
};

}  // namespace hapticd::protocol
