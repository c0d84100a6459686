#include <gtest/gtest.h>

#include <array>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "protocol/codec.hpp"
#include "protocol_test_util.hpp"

// Decoding never crashes and never lets through what validate() would refuse, whatever the bytes:
// random buffers, random buffers behind a valid header, every truncation and thousands of bit
// flips and byte overwrites of a valid message of each type. (Run under -fsanitize=address,undefined
// as well: a read outside the datagram then fails loudly instead of by luck.)

namespace hapticd::protocol {
namespace {

using test::AlignedBytes;

struct Tally {
  std::size_t accepted = 0;
  std::size_t rejected = 0;
  std::array<std::size_t, kRejectReasonCount> by_reason{};

  void print(const char* what) const {
    std::printf("%s: %zu accepted, %zu rejected:", what, accepted, rejected);
    for (std::size_t i = 0; i < by_reason.size(); ++i) {
      if (by_reason[i] > 0) std::printf(" %s %zu", to_string(static_cast<RejectReason>(i)).data(), by_reason[i]);
    }
    std::printf("\n");
  }
};

// One decode, and everything that must hold of its result.
void check_decode(std::span<const std::uint8_t> bytes, Tally& tally) {
  Message out;
  const DecodeResult r = decode(bytes, out);
  if (!r.ok()) {
    const auto reason = static_cast<std::size_t>(r.reason);
    ASSERT_LT(reason, kRejectReasonCount);
    ASSERT_EQ(out.type, MessageType::kNone);
    ++tally.rejected;
    ++tally.by_reason[reason];
    return;
  }
  ++tally.accepted;
  ASSERT_GE(static_cast<int>(r.type), static_cast<int>(MessageType::kHello));
  ASSERT_LE(static_cast<int>(r.type), static_cast<int>(MessageType::kBye));
  ASSERT_EQ(out.type, r.type);
  ASSERT_EQ(r.peer_version, kProtocolVersion);
  // What decode accepts, the encoder accepts, and it decodes again to the same thing.
  Encoder encoder;
  const EncodeResult again = encoder.encode(out);
  ASSERT_TRUE(again.ok()) << to_string(again.reason) << " for an accepted " << to_string(out.type);
  Message twice;
  ASSERT_TRUE(decode(again.bytes, twice).ok());
  if (out.type != MessageType::kPoseSample) {
    ASSERT_TRUE(test::same_body(out, twice)) << to_string(out.type);
  } else {
    // Quaternions were normalized once already; a second pass may move them by an ulp.
    ASSERT_EQ(twice.pose_sample.poses.size(), out.pose_sample.poses.size());
    for (std::size_t i = 0; i < out.pose_sample.poses.size(); ++i) {
      ASSERT_EQ(twice.pose_sample.poses[i].position_m, out.pose_sample.poses[i].position_m);
      ASSERT_NEAR(twice.pose_sample.poses[i].orientation.w, out.pose_sample.poses[i].orientation.w, 1e-6f);
    }
  }
}

std::vector<AlignedBytes> valid_datagrams() {
  std::vector<AlignedBytes> all;
  Encoder encoder;
  for (const Message& m : test::sample_messages()) all.emplace_back(encoder.encode(m).bytes);
  return all;
}

TEST(CodecRobustness, RandomBuffersAreRejectedWithoutCrashing) {
  std::mt19937_64 rng(20240611);
  std::uniform_int_distribution<std::size_t> length(0, kMaxDatagram + 64);
  std::uniform_int_distribution<int> byte(0, 255);
  Tally tally;
  AlignedBytes bytes;
  for (int i = 0; i < 5000; ++i) {
    bytes.resize(length(rng));
    for (std::size_t k = 0; k < bytes.size(); ++k) bytes[k] = static_cast<std::uint8_t>(byte(rng));
    check_decode(bytes.span(), tally);
    if (HasFatalFailure()) return;
  }
  tally.print("random");
  EXPECT_EQ(tally.rejected, 5000u);
  EXPECT_GT(tally.by_reason[static_cast<std::size_t>(RejectReason::kBadIdentifier)], 0u);
}

// Random bytes that pass the cheap checks (length multiple of 4, identifier, a root offset inside
// the buffer) so the Verifier and the field checks see them.
TEST(CodecRobustness, RandomBuffersBehindAValidHeaderReachTheVerifierAndFail) {
  std::mt19937_64 rng(7);
  std::uniform_int_distribution<std::size_t> words(kMinDatagram / 4, kMaxDatagram / 4);
  std::uniform_int_distribution<int> byte(0, 255);
  Tally tally;
  AlignedBytes bytes;
  for (int i = 0; i < 5000; ++i) {
    bytes.resize(4 * words(rng));
    for (std::size_t k = 0; k < bytes.size(); ++k) bytes[k] = static_cast<std::uint8_t>(byte(rng));
    const auto root = static_cast<std::uint32_t>(std::uniform_int_distribution<std::size_t>(8, bytes.size() - 4)(rng));
    std::memcpy(bytes.data(), &root, 4);
    std::memcpy(bytes.data() + 4, "HPTD", 4);
    check_decode(bytes.span(), tally);
    if (HasFatalFailure()) return;
  }
  tally.print("random behind a header");
  EXPECT_EQ(tally.accepted + tally.rejected, 5000u);
  EXPECT_EQ(tally.by_reason[static_cast<std::size_t>(RejectReason::kBadIdentifier)], 0u);
  EXPECT_GT(tally.by_reason[static_cast<std::size_t>(RejectReason::kVerifyFailed)], 4000u);
}

TEST(CodecRobustness, EveryTruncationOfEveryMessageTypeIsHandled) {
  Tally tally;
  std::size_t cases = 0;
  std::size_t total_bytes = 0;
  for (const AlignedBytes& valid : valid_datagrams()) {
    total_bytes += valid.size();
    Message original;
    ASSERT_TRUE(decode(valid.span(), original).ok());
    for (std::size_t n = 0; n < valid.size(); ++n) {
      const AlignedBytes cut(valid.span().first(n));
      Message out;
      const DecodeResult r = decode(cut.span(), out);
      ++cases;
      check_decode(cut.span(), tally);
      if (HasFatalFailure()) return;
      // FlatBuffers writes leaves last at the end: a cut either breaks an offset (rejected) or only
      // drops trailing padding, and then it is the same message.
      if (r.ok()) {
        EXPECT_TRUE(test::same_body(original, out)) << to_string(original.type) << " cut to " << n;
      } else {
        EXPECT_TRUE(r.reason == RejectReason::kEmpty || r.reason == RejectReason::kTooShort ||
                    r.reason == RejectReason::kOddSize || r.reason == RejectReason::kVerifyFailed)
            << to_string(r.reason) << " for " << to_string(original.type) << " cut to " << n;
      }
    }
  }
  tally.print("truncations");
  EXPECT_EQ(cases, total_bytes);
  EXPECT_GT(tally.rejected, tally.accepted * 20) << "almost every cut breaks the buffer";
}

TEST(CodecRobustness, BitFlipsOfValidMessagesAreAcceptedOrRejectedNeverMisread) {
  std::mt19937_64 rng(99);
  Tally tally;
  for (const AlignedBytes& valid : valid_datagrams()) {
    std::uniform_int_distribution<std::size_t> bit(0, 8 * valid.size() - 1);
    std::uniform_int_distribution<int> flips(1, 4);
    for (int i = 0; i < 2000; ++i) {
      AlignedBytes mutated = valid;
      for (int f = flips(rng); f > 0; --f) {
        const std::size_t b = bit(rng);
        mutated[b / 8] ^= static_cast<std::uint8_t>(1u << (b % 8));
      }
      check_decode(mutated.span(), tally);
      if (HasFatalFailure()) return;
    }
  }
  tally.print("bit flips");
  EXPECT_EQ(tally.accepted + tally.rejected, 9u * 2000u);
  // Flips in payload floats and counters still make valid messages; flips in offsets do not.
  EXPECT_GT(tally.accepted, 1000u);
  EXPECT_GT(tally.rejected, 1000u);
  EXPECT_GT(tally.by_reason[static_cast<std::size_t>(RejectReason::kVerifyFailed)], 0u);
  EXPECT_GT(tally.by_reason[static_cast<std::size_t>(RejectReason::kBadIdentifier)], 0u);
}

TEST(CodecRobustness, ByteOverwritesWithBoundaryValuesAreHandled) {
  std::mt19937_64 rng(12345);
  constexpr std::array<std::uint8_t, 8> kValues = {0x00, 0xFF, 0x7F, 0x80, 0x01, 0xFE, 0x7F, 0xC0};
  Tally tally;
  for (const AlignedBytes& valid : valid_datagrams()) {
    std::uniform_int_distribution<std::size_t> at(0, valid.size() - 1);
    std::uniform_int_distribution<std::size_t> value(0, kValues.size() - 1);
    for (int i = 0; i < 1000; ++i) {
      AlignedBytes mutated = valid;
      // 1 to 4 consecutive bytes: a whole offset, count or float exponent at once.
      const std::size_t start = at(rng);
      const std::size_t n = std::uniform_int_distribution<std::size_t>(1, 4)(rng);
      for (std::size_t k = start; k < std::min(start + n, valid.size()); ++k) mutated[k] = kValues[value(rng)];
      check_decode(mutated.span(), tally);
      if (HasFatalFailure()) return;
    }
  }
  tally.print("byte overwrites");
  EXPECT_EQ(tally.accepted + tally.rejected, 9000u);
  EXPECT_GT(tally.rejected, 0u);
  EXPECT_GT(tally.accepted, 0u);
}

}  // namespace
}  // namespace hapticd::protocol
