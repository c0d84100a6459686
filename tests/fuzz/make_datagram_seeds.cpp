// Writes the datagram seed corpus (tests/fuzz/corpus/datagram): one valid datagram of each message
// type, full and with one frame, and a sealed (authenticated) Hello and PoseSample.
// Usage: make_datagram_seeds <dir>. Run by hand when the wire changes; the output is committed.
#include <cstdio>
#include <fstream>
#include <string>

#include "protocol/auth.hpp"
#include "tests/protocol/protocol_test_util.hpp"

using namespace hapticd::protocol;

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s <dir>\n", argv[0]);
    return 2;
  }
  const std::string dir = argv[1];
  Encoder encoder;
  int written = 0;
  auto save = [&](const std::string& name, std::span<const std::uint8_t> bytes) {
    std::ofstream(dir + "/" + name, std::ios::binary)
        .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
    ++written;
  };
  auto emit = [&](const std::string& name, const Message& m) {
    const EncodeResult e = encoder.encode(m);
    if (!e.ok()) {
      std::fprintf(stderr, "%s: %s\n", name.c_str(), std::string(to_string(e.reason)).c_str());
      std::exit(1);
    }
    save(name, e.bytes);
  };
  for (const Message& m : test::sample_messages()) emit(std::string(to_string(m.type)), m);

  Message small;
  small.type = MessageType::kHello;
  small.hello = test::sample_hello(1);
  emit("Hello_1frame", small);
  small.type = MessageType::kPoseSample;
  small.pose_sample = test::sample_pose(1);
  emit("PoseSample_1frame", small);
  small.type = MessageType::kForceSample;
  small.force_sample = test::sample_force(1);
  emit("ForceSample_1frame", small);

  // Authenticated: the fuzz target's key is unknown here on purpose; these only carry a trailer.
  const AuthKeys keys(Key{9, 9, 9});
  Sealer sealer;
  small.type = MessageType::kHello;
  small.hello = test::sample_hello(1);
  small.hello.credentials.clear();
  for (std::size_t i = 0; i < kNonceBytes; ++i) small.hello.credentials.push_back(static_cast<std::uint8_t>(i));
  EncodeResult e = encoder.encode(small);
  save("Hello_sealed", sealer.seal(e.bytes, Trailer{TrailerKind::kHello, 0, 0}, keys.hello_key()));
  small.type = MessageType::kPoseSample;
  small.pose_sample = test::sample_pose(1);
  e = encoder.encode(small);
  save("PoseSample_sealed", sealer.seal(e.bytes, Trailer{TrailerKind::kClientToServer, 42, 7}, keys.hello_key()));
  std::printf("%d seeds in %s\n", written, dir.c_str());
  return 0;
}
