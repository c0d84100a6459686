#include "protocol/auth.hpp"

#include <sodium.h>

#include <algorithm>
#include <cstring>
#include <stdexcept>

namespace hapticd::protocol {

namespace {

constexpr std::uint8_t kMagic[4] = {'H', 'P', 'T', 'A'};
constexpr char kKdfContext[crypto_kdf_CONTEXTBYTES + 1] = "hapticd1";
constexpr std::size_t kHeadBytes = kAuthTrailerBytes - kMacBytes;  // magic, kind, zero, session, counter
static_assert(kKeyBytes == crypto_kdf_KEYBYTES && kKeyBytes == crypto_generichash_KEYBYTES);
static_assert(kMacBytes >= crypto_generichash_BYTES_MIN);
static_assert(kAuthTrailerBytes % kDatagramAlignment == 0, "a sealed datagram keeps the encoder's 8-byte size");

void put_u64(std::uint8_t* out, std::uint64_t v) noexcept {
  for (int i = 0; i < 8; ++i) out[i] = static_cast<std::uint8_t>(v >> (8 * i));
}

std::uint64_t get_u64(const std::uint8_t* in) noexcept {
  std::uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v |= static_cast<std::uint64_t>(in[i]) << (8 * i);
  return v;
}

void tag_of(std::span<const std::uint8_t> bytes, const Key& key, std::uint8_t* tag) noexcept {
  crypto_generichash(tag, kMacBytes, bytes.data(), bytes.size(), key.data(), key.size());
}

}  // namespace

AuthKeys::AuthKeys(const Key& pre_shared_key) {
  if (sodium_init() < 0) throw std::runtime_error("libsodium failed to initialize");
  crypto_kdf_derive_from_key(hello_.data(), hello_.size(), 1, kKdfContext, pre_shared_key.data());
  crypto_kdf_derive_from_key(reply_.data(), reply_.size(), 2, kKdfContext, pre_shared_key.data());
  crypto_kdf_derive_from_key(session_.data(), session_.size(), 3, kKdfContext, pre_shared_key.data());
}

Key AuthKeys::reply_key(const Nonce& client_nonce) const noexcept {
  Key k;
  crypto_generichash(k.data(), k.size(), client_nonce.data(), client_nonce.size(), reply_.data(), reply_.size());
  return k;
}

SessionKeys AuthKeys::session_keys(const Nonce& client_nonce, const Nonce& server_nonce,
                                   std::uint64_t session_id) const noexcept {
  std::array<std::uint8_t, 2 * kNonceBytes + 8> input;
  std::memcpy(input.data(), client_nonce.data(), kNonceBytes);
  std::memcpy(input.data() + kNonceBytes, server_nonce.data(), kNonceBytes);
  put_u64(input.data() + 2 * kNonceBytes, session_id);
  std::array<std::uint8_t, 2 * kKeyBytes> both;
  crypto_generichash(both.data(), both.size(), input.data(), input.size(), session_.data(), session_.size());
  SessionKeys keys;
  std::memcpy(keys.client_to_server.data(), both.data(), kKeyBytes);
  std::memcpy(keys.server_to_client.data(), both.data() + kKeyBytes, kKeyBytes);
  sodium_memzero(both.data(), both.size());
  return keys;
}

Nonce random_nonce() noexcept {
  Nonce n;
  randombytes_buf(n.data(), n.size());
  return n;
}

std::span<const std::uint8_t> Sealer::seal(std::span<const std::uint8_t> message, const Trailer& trailer,
                                           const Key& key) noexcept {
  const std::size_t n = message.size() + kAuthTrailerBytes;
  if (n > buffer_.size()) return {};
  std::uint8_t* out = buffer_.data();
  std::memcpy(out, message.data(), message.size());
  std::uint8_t* head = out + message.size();
  std::memcpy(head, kMagic, 4);
  head[4] = static_cast<std::uint8_t>(trailer.kind);
  head[5] = head[6] = head[7] = 0;
  put_u64(head + 8, trailer.session_id);
  put_u64(head + 16, trailer.counter);
  tag_of({out, n - kMacBytes}, key, out + n - kMacBytes);
  return {out, n};
}

RejectReason split_trailer(std::span<const std::uint8_t> datagram, std::span<const std::uint8_t>& message,
                           Trailer& trailer) noexcept {
  if (datagram.size() < kAuthTrailerBytes) return RejectReason::kMissingMac;
  const std::uint8_t* head = datagram.data() + datagram.size() - kAuthTrailerBytes;
  if (std::memcmp(head, kMagic, 4) != 0) return RejectReason::kMissingMac;
  const std::uint8_t kind = head[4];
  if (kind < static_cast<std::uint8_t>(TrailerKind::kHello) ||
      kind > static_cast<std::uint8_t>(TrailerKind::kServerToClient) || head[5] != 0 || head[6] != 0 || head[7] != 0)
    return RejectReason::kBadMac;
  trailer.kind = static_cast<TrailerKind>(kind);
  trailer.session_id = get_u64(head + 8);
  trailer.counter = get_u64(head + 16);
  message = datagram.first(datagram.size() - kAuthTrailerBytes);
  static_assert(kHeadBytes == 24);
  return RejectReason::kNone;
}

bool verify_mac(std::span<const std::uint8_t> datagram, const Key& key) noexcept {
  if (datagram.size() < kMacBytes) return false;
  std::uint8_t tag[kMacBytes];
  const std::size_t covered = datagram.size() - kMacBytes;
  tag_of(datagram.first(covered), key, tag);
  static_assert(kMacBytes == 16, "crypto_verify_16");
  return crypto_verify_16(tag, datagram.data() + covered) == 0;
}

RejectReason accept_counter(SequenceWindow& window, std::uint64_t counter) noexcept {
  if (counter == 0) return RejectReason::kReplayed;
  if (window.started() && counter < window.newest() && window.newest() - counter >= SequenceWindow::kWindow)
    return RejectReason::kReplayed;
  return window.observe(counter) == SequenceClass::kDuplicate ? RejectReason::kReplayed : RejectReason::kNone;
}

bool NonceCache::insert(const Nonce& nonce) noexcept {
  for (std::size_t i = 0; i < size_; ++i)
    if (std::memcmp(entries_[i].data(), nonce.data(), entries_[i].size()) == 0) return false;
  std::memcpy(entries_[next_].data(), nonce.data(), entries_[next_].size());
  next_ = (next_ + 1) % kCapacity;
  size_ = std::min(size_ + 1, kCapacity);
  return true;
}

}  // namespace hapticd::protocol
