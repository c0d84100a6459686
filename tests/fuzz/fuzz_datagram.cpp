// libFuzzer target: every datagram a peer can send, as hapticd's haptic thread receives it.
//
// Each input is taken three ways: (1) as a plain datagram, protocol::decode; (2) as an
// authenticated one, split_trailer + verify_mac + accept_counter + decode of the message part;
// (3) sealed with a fixed key, which must then split and verify (and fail to verify with one bit
// of the tag flipped). decode never throws (noexcept: an exception would terminate, a finding).
// Oracles: whatever decode accepts passes validate() and survives Encoder::encode -> decode
// unchanged (quaternions to float rounding, as decode normalizes them).
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <span>

#include "protocol/auth.hpp"
#include "protocol/codec.hpp"
#include "protocol/sequence_window.hpp"

namespace {

using namespace hapticd::protocol;

void check(bool ok) {
  if (!ok) std::abort();  // an oracle failed: libFuzzer reports the input as a crash
}

bool same_pose(const PoseSample& a, const PoseSample& b) {
  if (a.session_id != b.session_id || a.sequence != b.sequence || a.client_timestamp_ns != b.client_timestamp_ns ||
      a.buttons != b.buttons || a.poses.size() != b.poses.size())
    return false;
  for (std::size_t i = 0; i < a.poses.size(); ++i) {
    const FramePose& p = a.poses[i];
    const FramePose& q = b.poses[i];
    // Decoding normalizes a unit quaternion again: a few float ulps.
    const float tol = 4e-7f;
    if (p.frame != q.frame || !(p.position_m == q.position_m) || std::fabs(p.orientation.w - q.orientation.w) > tol ||
        std::fabs(p.orientation.x - q.orientation.x) > tol || std::fabs(p.orientation.y - q.orientation.y) > tol ||
        std::fabs(p.orientation.z - q.orientation.z) > tol)
      return false;
  }
  return true;
}

bool same_body(const Message& a, const Message& b) {
  switch (a.type) {
    case MessageType::kHello: return a.hello == b.hello;
    case MessageType::kWelcome: return a.welcome == b.welcome;
    case MessageType::kError: return a.error == b.error;
    case MessageType::kPoseSample: return same_pose(a.pose_sample, b.pose_sample);
    case MessageType::kForceSample: return a.force_sample == b.force_sample;
    case MessageType::kHeartbeat: return a.heartbeat == b.heartbeat;
    case MessageType::kStatsRequest: return a.stats_request == b.stats_request;
    case MessageType::kStats: return a.stats == b.stats;
    case MessageType::kBye: return a.bye == b.bye;
    default: return false;
  }
}

// Decodes `bytes` from an aligned buffer, as the server receives them; checks the oracles.
void decode_and_check(std::span<const std::uint8_t> bytes) {
  static ReceiveBuffer buffer;  // static: 2 KiB, as the server keeps one
  static Message message, again;
  static Encoder encoder;
  const std::size_t n = std::min(bytes.size(), buffer.bytes.size());
  std::memcpy(buffer.bytes.data(), bytes.data(), n);
  const DecodeResult r = decode(std::span<const std::uint8_t>(buffer.bytes.data(), n), message);
  (void)error_reply_allowed(r);
  if (!r.ok()) {
    check(message.type == MessageType::kNone);
    return;
  }
  check(message.type == r.type);
  const EncodeResult e = encoder.encode(message);
  check(e.ok());
  const DecodeResult r2 = decode(e.bytes, again);
  check(r2.ok() && again.type == message.type && same_body(message, again));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::uint8_t> input(data, size);

  // (1) a plain datagram.
  decode_and_check(input);

  // (2) an authenticated datagram as received (the tag almost never verifies: the key is secret).
  static const AuthKeys keys(Key{1, 2, 3, 4, 5, 6, 7, 8});
  alignas(kDatagramAlignment) static std::uint8_t received[kMaxDatagram + 1];
  const std::size_t n = std::min(size, sizeof received);
  std::memcpy(received, data, n);
  const std::span<const std::uint8_t> datagram(received, n);
  std::span<const std::uint8_t> body;
  Trailer trailer;
  if (split_trailer(datagram, body, trailer) == RejectReason::kNone) {
    check(body.size() + kAuthTrailerBytes == datagram.size() && body.data() == datagram.data());
    (void)verify_mac(datagram, keys.hello_key());
    SequenceWindow window;
    (void)accept_counter(window, trailer.counter);
    (void)accept_counter(window, trailer.counter - SequenceWindow::kWindow);
    (void)accept_counter(window, trailer.session_id);
    decode_and_check(body);
  }

  // (3) the input sealed as a client's datagram: it must split back and verify, and not verify
  // once tampered with.
  if (size + kAuthTrailerBytes <= kMaxDatagram) {
    static Sealer sealer;
    Trailer t;
    t.kind = TrailerKind::kClientToServer;
    t.session_id = size;
    t.counter = size + 1;
    const Key& key = keys.hello_key();
    const std::span<const std::uint8_t> sealed = sealer.seal(input, t, key);
    check(sealed.size() == size + kAuthTrailerBytes);
    std::memcpy(received, sealed.data(), sealed.size());
    const std::span<const std::uint8_t> copy(received, sealed.size());
    Trailer back;
    check(split_trailer(copy, body, back) == RejectReason::kNone);
    check(back.kind == t.kind && back.session_id == t.session_id && back.counter == t.counter);
    check(body.size() == size && (size == 0 || std::memcmp(body.data(), data, size) == 0));
    check(verify_mac(copy, key));
    received[copy.size() - 1 - size % kMacBytes] ^= 0x01;
    check(!verify_mac(copy, key));
  }
  return 0;
}
