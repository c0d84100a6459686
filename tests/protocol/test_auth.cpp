// Authentication (protocol/auth.hpp, key_file.hpp): sealed datagrams verify and decode, every
// single-byte change and every other key fails, keys are separated by purpose, direction, nonce and
// session, the anti-replay window, the Hello nonce cache, key files and their refusals, the cost of
// a MAC, and no allocation.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <sodium.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cstring>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include "allocation_counter.hpp"
#include "protocol/auth.hpp"
#include "protocol/codec.hpp"
#include "protocol/key_file.hpp"
#include "protocol_test_util.hpp"

namespace hapticd::protocol {
namespace {

using test::AlignedBytes;

Key test_key(std::uint8_t seed) {
  Key k;
  for (std::size_t i = 0; i < k.size(); ++i) k[i] = static_cast<std::uint8_t>(seed + 13 * i);
  return k;
}

Nonce test_nonce(std::uint8_t seed) {
  Nonce n;
  for (std::size_t i = 0; i < n.size(); ++i) n[i] = static_cast<std::uint8_t>(seed * 3 + i);
  return n;
}

TEST(Auth, ASealedDatagramSplitsVerifiesAndDecodesToTheMessage) {
  Encoder encoder;
  Sealer sealer;
  const Key key = test_key(1);
  const PoseSample pose = test::sample_pose(1);
  const EncodeResult e = encoder.encode(pose);
  ASSERT_TRUE(e.ok());
  const auto sealed = sealer.seal(e.bytes, {TrailerKind::kClientToServer, 42, 0x0102030405060708ull}, key);
  ASSERT_EQ(sealed.size(), e.bytes.size() + kAuthTrailerBytes);
  EXPECT_EQ(sealed.size() % kDatagramAlignment, 0u);
  const AlignedBytes rx(sealed);
  std::span<const std::uint8_t> body;
  Trailer t;
  ASSERT_EQ(split_trailer(rx.span(), body, t), RejectReason::kNone);
  EXPECT_EQ(t.kind, TrailerKind::kClientToServer);
  EXPECT_EQ(t.session_id, 42u);
  EXPECT_EQ(t.counter, 0x0102030405060708ull);
  EXPECT_EQ(body.data(), rx.data());
  EXPECT_EQ(body.size(), e.bytes.size());
  EXPECT_TRUE(verify_mac(rx.span(), key));
  Message m;
  ASSERT_TRUE(decode(body, m).ok());
  EXPECT_EQ(m.pose_sample, pose);
  // Little-endian on the wire, whatever the host.
  EXPECT_EQ(rx.data()[rx.size() - 24], 0x08);
  EXPECT_EQ(rx.data()[rx.size() - 32], 42);
}

TEST(Auth, EverySingleByteChangeAndEveryOtherKeyFailVerification) {
  Encoder encoder;
  Sealer sealer;
  const Key key = test_key(1);
  const auto sealed =
      sealer.seal(encoder.encode(test::sample_pose(2)).bytes, {TrailerKind::kClientToServer, 7, 9}, key);
  AlignedBytes rx(sealed);
  std::size_t failed = 0, checks = 0;
  for (std::size_t i = 0; i < rx.size(); ++i) {
    for (const std::uint8_t flip : {0x01, 0x80, 0xFF}) {
      rx[i] ^= flip;
      std::span<const std::uint8_t> body;
      Trailer t;
      // Refused at the split (magic, kind) or by the tag: never accepted.
      const bool accepted = split_trailer(rx.span(), body, t) == RejectReason::kNone && verify_mac(rx.span(), key);
      failed += !accepted;
      ++checks;
      rx[i] ^= flip;
    }
  }
  EXPECT_EQ(failed, checks);
  EXPECT_TRUE(verify_mac(rx.span(), key));
  for (std::uint8_t seed = 2; seed < 50; ++seed) EXPECT_FALSE(verify_mac(rx.span(), test_key(seed)));
  Key one_bit = key;
  one_bit[31] ^= 1;
  EXPECT_FALSE(verify_mac(rx.span(), one_bit));
  // Truncated by any amount: a trailer no longer where it was.
  for (std::size_t cut = 1; cut < rx.size(); ++cut) {
    std::span<const std::uint8_t> body;
    Trailer t;
    const auto shorter = rx.span().first(rx.size() - cut);
    EXPECT_FALSE(split_trailer(shorter, body, t) == RejectReason::kNone && verify_mac(shorter, key)) << cut;
  }
}

TEST(Auth, APlainDatagramHasNoTrailerAndAnUnknownKindIsRefused) {
  Encoder encoder;
  const AlignedBytes plain(encoder.encode(test::sample_pose(1)).bytes);
  std::span<const std::uint8_t> body;
  Trailer t;
  EXPECT_EQ(split_trailer(plain.span(), body, t), RejectReason::kMissingMac);
  EXPECT_EQ(split_trailer({}, body, t), RejectReason::kMissingMac);
  Sealer sealer;
  AlignedBytes sealed(sealer.seal(plain.span(), {TrailerKind::kHello, 0, 0}, test_key(1)));
  sealed[sealed.size() - 36] = 9;  // kind
  EXPECT_EQ(split_trailer(sealed.span(), body, t), RejectReason::kBadMac);
  sealed[sealed.size() - 36] = 1;
  sealed[sealed.size() - 35] = 1;  // reserved
  EXPECT_EQ(split_trailer(sealed.span(), body, t), RejectReason::kBadMac);
  // Too long to seal: the trailer counts toward kMaxDatagram.
  std::vector<std::uint8_t> big(kMaxDatagram - kAuthTrailerBytes + 8, 0);
  EXPECT_TRUE(sealer.seal(big, {TrailerKind::kHello, 0, 0}, test_key(1)).empty());
  big.resize(kMaxDatagram - kAuthTrailerBytes);
  EXPECT_EQ(sealer.seal(big, {TrailerKind::kHello, 0, 0}, test_key(1)).size(), kMaxDatagram);
}

TEST(Auth, KeysAreSeparatedByPurposeDirectionNonceAndSession) {
  const AuthKeys a(test_key(1)), b(test_key(2));
  const Nonce nc = test_nonce(1), ns = test_nonce(2);
  const SessionKeys s = a.session_keys(nc, ns, 5);
  EXPECT_NE(s.client_to_server, s.server_to_client);
  EXPECT_EQ(a.session_keys(nc, ns, 5).client_to_server, s.client_to_server);  // deterministic: both ends agree
  EXPECT_NE(a.session_keys(nc, ns, 6).client_to_server, s.client_to_server);
  EXPECT_NE(a.session_keys(ns, nc, 5).client_to_server, s.client_to_server);
  EXPECT_NE(a.session_keys(test_nonce(3), ns, 5).server_to_client, s.server_to_client);
  EXPECT_NE(b.session_keys(nc, ns, 5).client_to_server, s.client_to_server);
  EXPECT_NE(a.reply_key(nc), a.reply_key(ns));
  EXPECT_NE(a.reply_key(nc), b.reply_key(nc));
  EXPECT_NE(a.hello_key(), b.hello_key());
  EXPECT_NE(a.hello_key(), test_key(1)) << "the pre-shared key itself never tags anything";
  for (const Key& k : {a.reply_key(nc), s.client_to_server, s.server_to_client}) EXPECT_NE(k, a.hello_key());
  EXPECT_NE(random_nonce(), random_nonce());
}

TEST(Auth, TheCounterWindowAcceptsEachCounterOnceAndReorderedOnesWithinTheWindow) {
  SequenceWindow w;
  EXPECT_EQ(accept_counter(w, 0), RejectReason::kReplayed) << "counters start at 1";
  EXPECT_EQ(accept_counter(w, 1), RejectReason::kNone);
  EXPECT_EQ(accept_counter(w, 1), RejectReason::kReplayed);
  EXPECT_EQ(accept_counter(w, 5), RejectReason::kNone);  // 2..4 late or lost
  EXPECT_EQ(accept_counter(w, 3), RejectReason::kNone);  // reordered: accepted once
  EXPECT_EQ(accept_counter(w, 3), RejectReason::kReplayed);
  EXPECT_EQ(accept_counter(w, 5), RejectReason::kReplayed);
  EXPECT_EQ(accept_counter(w, 200), RejectReason::kNone);
  EXPECT_EQ(accept_counter(w, 200 - SequenceWindow::kWindow + 1), RejectReason::kNone);  // the oldest it can tell
  EXPECT_EQ(accept_counter(w, 200 - SequenceWindow::kWindow), RejectReason::kReplayed);  // too old to tell
  EXPECT_EQ(accept_counter(w, 4), RejectReason::kReplayed);
}

TEST(Auth, TheNonceCacheRefusesARepeatedNonceUntilItIsEvicted) {
  NonceCache cache;
  EXPECT_TRUE(cache.insert(test_nonce(1)));
  EXPECT_FALSE(cache.insert(test_nonce(1)));
  for (std::size_t i = 0; i < NonceCache::kCapacity - 1; ++i) EXPECT_TRUE(cache.insert(random_nonce()));
  EXPECT_FALSE(cache.insert(test_nonce(1))) << "still one of the last kCapacity";
  EXPECT_TRUE(cache.insert(random_nonce()));
  EXPECT_TRUE(cache.insert(test_nonce(1))) << "evicted by the kCapacity newer ones";
}

TEST(Auth, AWelcomeWithALongerServerNonceIsRefused) {
  const auto bytes = test::craft([](flatbuffers::FlatBufferBuilder& b) {
    const wire::FrameMapEntry entry(0, 0);
    const auto map = b.CreateVectorOfStructs(&entry, 1);
    std::vector<std::uint8_t> nonce(kNonceBytes + 1, 1);
    const auto n = b.CreateVector(nonce);
    return std::pair{wire::Body::Welcome, wire::CreateWelcome(b, 5, 1000, 8.0f, 0.0f, 100.0f, map, n).Union()};
  });
  Message m;
  EXPECT_EQ(decode(bytes.span(), m).reason, RejectReason::kFieldTooLong);
}

TEST(Auth, SealVerifyAndTheWindowAllocateNothing) {
  Encoder encoder;
  Sealer sealer;
  const Key key = test_key(3);
  const EncodeResult e = encoder.encode(test::sample_pose(1));
  SequenceWindow w;
  NonceCache cache;
  const AuthKeys keys(key);
  const Nonce nc = test_nonce(1);
  int ok = 0;
  const long allocations = testing_util::allocations_in([&] {
    for (std::uint64_t c = 1; c <= 1000; ++c) {
      const auto sealed = sealer.seal(e.bytes, {TrailerKind::kClientToServer, 1, c}, key);
      std::span<const std::uint8_t> body;
      Trailer t;
      ok += split_trailer(sealed, body, t) == RejectReason::kNone && verify_mac(sealed, key) &&
            accept_counter(w, t.counter) == RejectReason::kNone;
    }
    ok += cache.insert(random_nonce());
    ok += keys.session_keys(nc, nc, 1).client_to_server[0] != 0 || true;
    ok += keys.reply_key(nc)[0] != 0 || true;
  });
  EXPECT_EQ(allocations, 0);
  EXPECT_EQ(ok, 1003);
}

// The figures the README quotes (protocol/README.md, Authentication, Cost), against baselines
// measured in the same run: verifying is one keyed BLAKE2b over the datagram ("an unauthenticated
// datagram costs one MAC and reaches nothing else"), sealing is a copy and that MAC. Each rep times
// every operation and its baseline back to back in turn, in blocks of 100 (tens of microseconds, shorter
// than a scheduler's slice, so most blocks run unpreempted) so a noisy neighbour slows both alike;
// medians of 301 reps. The absolute figures (about a microsecond) are printed: they are libsodium's on this machine.
TEST(Auth, AMacCostsAboutAMicrosecondPerDatagram) {
  ASSERT_GE(sodium_init(), 0);
  Encoder encoder;
  Sealer sealer;
  const Key key = test_key(4);
  constexpr int kReps = 301, kN = 100;
  const auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  for (const std::size_t frames : {std::size_t{1}, std::size_t{20}, kMaxFrames}) {
    const EncodeResult e = encoder.encode(test::sample_pose(frames));
    const std::span<const std::uint8_t> sealed_once =
        sealer.seal(e.bytes, {TrailerKind::kClientToServer, 1, 1}, key);
    const std::vector<std::uint8_t> sealed_copy(sealed_once.begin(), sealed_once.end());
    const std::size_t covered = sealed_copy.size() - kMacBytes;
    std::vector<std::uint8_t> copy_out(sealed_copy.size());
    std::vector<double> seal_ns, verify_ns, hash_ns, copy_hash_ns;
    std::size_t sink = 0, verified = 0;
    const auto per_op_ns = [](auto t0, auto t1) { return std::chrono::duration<double, std::nano>(t1 - t0).count() / kN; };
    std::uint8_t tag[kMacBytes];
    // The four timed operations: seal, verify, and their baselines.
    const std::array<std::function<void(int)>, 4> ops = {
        [&](int i) {
          const auto s = sealer.seal(e.bytes, {TrailerKind::kClientToServer, 1, static_cast<std::uint64_t>(i + 1)}, key);
          sink += s[s.size() - 1];
        },
        [&](int) { verified += verify_mac(sealed_copy, key); },
        // Baseline of verify: libsodium's keyed BLAKE2b (16-byte tag) over the same covered bytes.
        [&](int) {
          crypto_generichash(tag, kMacBytes, sealed_copy.data(), covered, key.data(), key.size());
          sink += tag[0];
        },
        // Baseline of seal: the message and the trailer's head copied, then the same MAC.
        [&](int i) {
          std::memcpy(copy_out.data(), e.bytes.data(), e.bytes.size());
          std::memcpy(copy_out.data() + e.bytes.size(), sealed_copy.data() + e.bytes.size(),
                      kAuthTrailerBytes - kMacBytes);
          copy_out[e.bytes.size() + 16] = static_cast<std::uint8_t>(i);
          crypto_generichash(copy_out.data() + covered, kMacBytes, copy_out.data(), covered, key.data(), key.size());
          sink += copy_out.back();
        }};
    std::array<std::vector<double>*, 4> times = {&seal_ns, &verify_ns, &hash_ns, &copy_hash_ns};
    for (int rep = 0; rep < kReps; ++rep) {
      for (int k = 0; k < 4; ++k) {
        const int op = (rep + k) % 4;  // each operation first, second, ... in turn
        const auto t0 = std::chrono::steady_clock::now();
        for (int i = 0; i < kN; ++i) ops[op](i);
        times[op]->push_back(per_op_ns(t0, std::chrono::steady_clock::now()));
      }
    }
    EXPECT_EQ(verified, static_cast<std::size_t>(kReps) * kN) << "every verify passed";
    EXPECT_NE(sink, 0u);
    const double seal = median(seal_ns), verify = median(verify_ns), hash = median(hash_ns),
                 copy_hash = median(copy_hash_ns);
    std::printf(
        "PoseSample, %zu frame(s), %zu B sealed: seal (copy + MAC) %.0f ns, verify %.0f ns; baselines: keyed "
        "BLAKE2b of the same bytes %.0f ns, copy + it %.0f ns (medians of %d x %d)\n",
        frames, sealed_copy.size(), seal, verify, hash, copy_hash, kReps, kN);
    // One MAC and nothing else: what verify and seal add to the BLAKE2b (a 24-byte trailer parsed or
    // written, a 16-byte constant-time compare) is a few tens of ns, under a quarter of the hash of the
    // smallest datagram (~400 ns); a second pass over the bytes would double the time.
    EXPECT_LT(verify, 1.25 * hash) << "verify is one MAC";
    EXPECT_LT(seal, 1.25 * copy_hash) << "seal is a copy and one MAC";
  }
}

// ---- key files ----------------------------------------------------------------------------------

class KeyFile : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() / ("hapticd_key_test_" + std::to_string(::getpid()) + "_" +
                                                     ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }
  std::string write(const std::string& name, const std::string& text, mode_t mode = 0600) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    ::chmod(path.c_str(), mode);
    return path;
  }
  static std::string error_of(const std::string& path) {
    try {
      load_key_file(path);
    } catch (const KeyFileError& e) {
      return e.what();
    }
    return "";
  }
  std::filesystem::path dir_;
};

constexpr const char* kHex = "000102030405060708090a0b0c0d0e0f101112131415161718191A1B1C1D1E1F";

TEST_F(KeyFile, AGoodFileLoadsWithOrWithoutItsNewlineAndBlanks) {
  Key expected;
  for (std::size_t i = 0; i < expected.size(); ++i) expected[i] = static_cast<std::uint8_t>(i);
  EXPECT_EQ(load_key_file(write("a", std::string(kHex) + "\n")), expected);
  EXPECT_EQ(load_key_file(write("b", kHex)), expected);
  EXPECT_EQ(load_key_file(write("c", std::string("  ") + kHex + " \r\n")), expected);
}

TEST_F(KeyFile, BadFilesAreRefusedNamingTheFileAndTheFault) {
  const auto expect = [&](const std::string& path, const std::string& part) {
    const std::string e = error_of(path);
    EXPECT_NE(e.find(path), std::string::npos) << e;
    EXPECT_NE(e.find(part), std::string::npos) << "expected '" << part << "' in: " << e;
  };
  expect(write("short", std::string(kHex).substr(0, 62) + "\n"), "62 hexadecimal digits, expected 64");
  expect(write("long", std::string(kHex) + "00\n"), "66 hexadecimal digits, expected 64");
  std::string bad = kHex;
  bad[10] = 'g';
  expect(write("char", bad), "character 11 is not a hexadecimal digit");
  expect(write("lines", std::string(kHex) + "\n" + kHex + "\n"), "more than one line");
  expect(write("empty", ""), "0 hexadecimal digits");
  expect(write("zero", std::string(64, '0')), "all zeros");
  expect(write("world", std::string(kHex), 0644), "permissions 0644");
  expect(write("group", std::string(kHex), 0640), "chmod 600");
  expect((dir_ / "missing").string(), "cannot open the key file (No such file or directory)");
  expect(dir_.string(), "not a regular file");
  const std::string target = write("target", kHex);
  const std::string link = (dir_ / "link").string();
  ASSERT_EQ(::symlink(target.c_str(), link.c_str()), 0);
  expect(link, "symbolic link");
  expect(write("huge", std::string(5000, 'a')), "too large");
}

TEST_F(KeyFile, AGeneratedKeyIsPrivateLoadsBackAndIsNeverOverwritten) {
  const std::string path = (dir_ / "new.key").string();
  const mode_t old_umask = ::umask(0);  // the file is 0600 whatever the umask
  const Key key = generate_key_file(path);
  ::umask(old_umask);
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  EXPECT_EQ(st.st_size, 65);
  EXPECT_EQ(load_key_file(path), key);
  try {
    generate_key_file(path);
    ADD_FAILURE() << "overwrote " << path;
  } catch (const KeyFileError& e) {
    EXPECT_NE(std::string(e.what()).find("exists; not overwritten"), std::string::npos) << e.what();
  }
  EXPECT_EQ(load_key_file(path), key);
  EXPECT_NE(generate_key_file((dir_ / "other.key").string()), key);
  const std::string fp = key_fingerprint(key);
  EXPECT_EQ(fp.size(), 8u);
  EXPECT_EQ(fp, key_fingerprint(key));
  EXPECT_NE(fp, key_fingerprint(test_key(1)));
}

}  // namespace
}  // namespace hapticd::protocol
