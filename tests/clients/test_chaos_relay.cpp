// The chaos relay (clients/chaos): traffic through it both ways, intact without damage; loss,
// duplication, corruption and reordering at their configured rates and counted exactly as a receiver
// sees them; delay and jitter bounding the one-way time; the same seed making the same decisions;
// the haptic-chaos tool's listening line, counts and refusals.
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <thread>
#include <vector>

#include "clients/chaos/chaos_relay.hpp"
#include "clients/sim/child_process.hpp"
#include "protocol/clock.hpp"

namespace hapticd::chaos {
namespace {

constexpr std::size_t kPayload = 64;

// A datagram that names its index and proves it intact: bytes 4.. are a function of the index.
std::array<std::uint8_t, kPayload> datagram_for(std::uint32_t index) {
  std::array<std::uint8_t, kPayload> d{};
  std::memcpy(d.data(), &index, 4);
  for (std::size_t i = 4; i < d.size(); ++i) {
    std::uint64_t h = index * 0x9E3779B97F4A7C15ull + i;  // splitmix64: every index bit reaches every byte
    h = (h ^ (h >> 30)) * 0xBF58476D1CE4E5B9ull;
    h = (h ^ (h >> 27)) * 0x94D049BB133111EBull;
    d[i] = static_cast<std::uint8_t>(h ^ (h >> 31));
  }
  return d;
}
// The index of an intact datagram, or -1 for a damaged one.
long index_of(const std::uint8_t* data, std::size_t n) {
  if (n != kPayload) return -1;
  std::uint32_t index;
  std::memcpy(&index, data, 4);
  return std::memcmp(datagram_for(index).data(), data, kPayload) == 0 ? static_cast<long>(index) : -1L;
}

struct Socket {
  Socket() {
    fd = ::socket(AF_INET, SOCK_DGRAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a);
    socklen_t n = sizeof a;
    ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &n);
    port = ntohs(a.sin_port);
    int big = 4 << 20;
    ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &big, sizeof big);
  }
  ~Socket() { ::close(fd); }
  void send_to(std::uint16_t to, const void* data, std::size_t n) const {
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    a.sin_port = htons(to);
    ::sendto(fd, data, n, 0, reinterpret_cast<sockaddr*>(&a), sizeof a);
  }
  // Bytes of the next datagram within timeout_ms (empty on timeout), and its sender's port.
  std::vector<std::uint8_t> receive(int timeout_ms, std::uint16_t* from_port = nullptr) const {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, timeout_ms) <= 0) return {};
    std::vector<std::uint8_t> b(2048);
    sockaddr_in a{};
    socklen_t n = sizeof a;
    const ssize_t got = ::recvfrom(fd, b.data(), b.size(), 0, reinterpret_cast<sockaddr*>(&a), &n);
    b.resize(got > 0 ? static_cast<std::size_t>(got) : 0);
    if (from_port) *from_port = ntohs(a.sin_port);
    return b;
  }
  int fd = -1;
  std::uint16_t port = 0;
};

// What reached one end: datagrams, the damaged ones, duplicates, and how many came after a newer
// one (inversions).
struct Tally {
  void record(const std::vector<std::uint8_t>& b) {
    const long i = index_of(b.data(), b.size());
    ++received;
    if (i < 0) {
      ++damaged;
      return;
    }
    duplicates += !seen.insert(i).second;
    inversions += i < newest;
    newest = std::max(newest, i);
  }
  std::size_t received = 0, damaged = 0, duplicates = 0, inversions = 0;
  long newest = -1;
  std::set<long> seen;
};

// A server that answers every datagram with a fresh intact one of its own numbering, and tallies
// what reached it (written by its thread, read after it stopped).
struct Responder : Tally {
  Responder() {
    thread = std::thread([this] {
      std::uint32_t next = 0;
      while (!stop) {
        std::uint16_t from = 0;
        const auto b = socket.receive(10, &from);
        if (b.empty()) continue;
        record(b);
        const auto reply = datagram_for(next++);
        socket.send_to(from, reply.data(), reply.size());
      }
    });
  }
  ~Responder() {
    stop = true;
    thread.join();
  }
  Socket socket;
  std::atomic<bool> stop{false};
  std::thread thread;
};


// Sends `n` numbered datagrams through the relay, `gap_us` apart, collecting the answers until
// `settle_ms` after the last.
Tally exchange(ChaosRelay& relay, std::uint32_t n, int gap_us, int settle_ms = 100) {
  Socket client;
  Tally tally;
  for (std::uint32_t i = 0; i < n; ++i) {
    const auto d = datagram_for(i);
    client.send_to(relay.port(), d.data(), d.size());
    const std::uint64_t until = protocol::now_ns() + static_cast<std::uint64_t>(gap_us) * 1000u;
    while (protocol::now_ns() < until) {
      const auto b = client.receive(0);
      if (!b.empty()) tally.record(b);
    }
  }
  for (auto b = client.receive(settle_ms); !b.empty(); b = client.receive(settle_ms)) tally.record(b);
  return tally;
}

TEST(ChaosRelay, WithoutDamageEveryDatagramGoesBothWaysIntactAndInOrder) {
  Responder server;
  ChaosRelay relay({}, "127.0.0.1", server.socket.port);
  relay.start();
  const Tally back = exchange(relay, 500, 200);
  relay.stop();
  server.stop = true;
  server.thread.join();
  server.thread = std::thread([] {});
  const ChaosCounts c = relay.counts();
  EXPECT_EQ(server.received, 500u);
  EXPECT_EQ(server.damaged + server.duplicates + server.inversions, 0u);
  EXPECT_EQ(back.received, 500u);
  EXPECT_EQ(back.damaged + back.duplicates + back.inversions, 0u);
  EXPECT_EQ(c.to_server.received, 500u);
  EXPECT_EQ(c.to_server.sent, 500u);
  EXPECT_EQ(c.to_client.sent, 500u);
  EXPECT_EQ(c.clients, 1u);
}

// A count drawn with probability p out of n lies within 5 standard deviations of n p.
void expect_binomial(std::uint64_t count, std::uint64_t n, double p, const char* what) {
  const double sigma = std::sqrt(static_cast<double>(n) * p * (1 - p));
  EXPECT_NEAR(static_cast<double>(count), static_cast<double>(n) * p, 5 * sigma + 1) << what << " of " << n;
}

TEST(ChaosRelay, LossDuplicationAndCorruptionHappenAtTheirRatesAndAreCountedAsTheReceiverSeesThem) {
  Responder server;
  ChaosConfig config;
  config.loss = 0.1;
  config.duplicate = 0.05;
  config.corrupt = 0.05;
  config.seed = 7;
  ChaosRelay relay(config, "127.0.0.1", server.socket.port);
  relay.start();
  const Tally back = exchange(relay, 4000, 100);
  relay.stop();
  server.stop = true;
  server.thread.join();
  server.thread = std::thread([] {});
  const ChaosCounts c = relay.counts();
  std::printf("to server: %s\n", to_json(c, config)["to_server"].dump().c_str());
  std::printf("to client: %s\n", to_json(c, config)["to_client"].dump().c_str());
  EXPECT_EQ(c.to_server.received, 4000u);
  expect_binomial(c.to_server.lost, 4000, 0.1, "lost");
  expect_binomial(c.to_server.corrupted, 4000 - c.to_server.lost, 0.05, "corrupted");
  expect_binomial(c.to_server.duplicated, 4000 - c.to_server.lost, 0.05, "duplicated");
  // Exactly what the receivers saw: every datagram sent arrived, each corrupted one damaged.
  EXPECT_EQ(server.received, c.to_server.sent);
  EXPECT_EQ(c.to_server.sent, c.to_server.received - c.to_server.lost + c.to_server.duplicated);
  EXPECT_EQ(server.damaged, c.to_server.corrupted);
  EXPECT_EQ(c.to_client.received, server.received);
  EXPECT_EQ(back.received, c.to_client.sent);
  EXPECT_EQ(back.damaged, c.to_client.corrupted);
  // The responder's replies are numbered afresh: every repeat is a duplicate, except where the
  // original of a duplicated one was corrupted (its intact copy then arrives alone).
  EXPECT_LE(back.duplicates, c.to_client.duplicated);
  EXPECT_GE(back.duplicates + c.to_client.corrupted, c.to_client.duplicated);
  EXPECT_EQ(back.inversions, 0u);
  expect_binomial(c.to_client.lost, c.to_client.received, 0.1, "lost on the way back");
}

TEST(ChaosRelay, EachReorderedDatagramIsOvertakenByExactlyTheNextOne) {
  Responder server;
  ChaosConfig config;
  config.reorder = 0.05;
  config.seed = 11;
  ChaosRelay relay(config, "127.0.0.1", server.socket.port);
  relay.start();
  const Tally back = exchange(relay, 3000, 100);
  relay.stop();
  server.stop = true;
  server.thread.join();
  server.thread = std::thread([] {});
  const ChaosCounts c = relay.counts();
  expect_binomial(c.to_server.reordered, 3000, 0.05, "reordered");
  EXPECT_EQ(server.received, 3000u);
  EXPECT_EQ(server.inversions, c.to_server.reordered);
  EXPECT_EQ(back.received, 3000u);
  EXPECT_EQ(back.inversions, c.to_client.reordered);
  EXPECT_GT(c.to_client.reordered, 0u);
}

TEST(ChaosRelay, DelayAndJitterBoundTheRoundTrip) {
  Responder server;
  ChaosConfig config;
  config.delay_ms = 5;
  config.jitter_ms = 2;
  ChaosRelay relay(config, "127.0.0.1", server.socket.port);
  relay.start();
  Socket client;
  std::vector<double> rtt_ms;
  for (std::uint32_t i = 0; i < 100; ++i) {
    const auto d = datagram_for(i);
    const std::uint64_t t0 = protocol::now_ns();
    client.send_to(relay.port(), d.data(), d.size());
    if (!client.receive(1000).empty()) rtt_ms.push_back(1e-6 * static_cast<double>(protocol::now_ns() - t0));
  }
  relay.stop();
  ASSERT_EQ(rtt_ms.size(), 100u);
  std::sort(rtt_ms.begin(), rtt_ms.end());
  std::printf("round trip through 2 x (5 ms + U[0, 2] ms): min %.2f, median %.2f, max %.2f ms\n", rtt_ms.front(),
              rtt_ms[50], rtt_ms.back());
  EXPECT_GE(rtt_ms.front(), 10.0);
  EXPECT_LT(rtt_ms[50], 14.0 + 2.0);  // 2 ms of scheduling slack on a shared VM
  EXPECT_GT(rtt_ms[90] - rtt_ms[10], 1.0) << "jittered";
}

// Which of n datagrams sent one at a time (each awaited) came through, damaged or not.
std::string pattern_for(std::uint64_t seed) {
  Responder server;
  ChaosConfig config;
  config.loss = 0.2;
  config.corrupt = 0.2;
  config.seed = seed;
  ChaosRelay relay(config, "127.0.0.1", server.socket.port);
  relay.start();
  Socket client;
  std::string pattern;
  for (std::uint32_t i = 0; i < 120; ++i) {
    const auto d = datagram_for(i);
    client.send_to(relay.port(), d.data(), d.size());
    const auto b = client.receive(20);
    pattern += b.empty() ? '-' : index_of(b.data(), b.size()) < 0 ? 'x' : 'o';
  }
  relay.stop();
  return pattern;
}

TEST(ChaosRelay, TheSameSeedMakesTheSameDecisions) {
  const std::string a = pattern_for(3), b = pattern_for(3), c = pattern_for(4);
  EXPECT_EQ(a, b);
  EXPECT_NE(a, c);
  EXPECT_NE(a.find('-'), std::string::npos);
  EXPECT_NE(a.find('x'), std::string::npos);
}

TEST(ChaosRelay, BadConfigurationsAreRefusedNamingTheField) {
  ChaosConfig config;
  config.loss = 1.5;
  EXPECT_THROW(validate(config), std::invalid_argument);
  config.loss = 0;
  config.jitter_ms = -1;
  try {
    validate(config);
    ADD_FAILURE();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("jitter_ms"), std::string::npos);
  }
}

TEST(HapticChaosTool, PrintsWhereItListensRelaysAndPrintsItsCountsOnSigterm) {
  Responder server;
  sim::ChildProcess tool(HAPTICD_CHAOS_BIN,
                         {"--listen", "0", "--forward", "127.0.0.1:" + std::to_string(server.socket.port), "--loss",
                          "0.5", "--seed", "5"});
  const sim::ListenAddress at =
      sim::parse_listening_line(tool.wait_for_line(sim::listening_line_pattern(), std::chrono::seconds(10)));
  EXPECT_EQ(at.host, "127.0.0.1");
  Socket client;
  for (std::uint32_t i = 0; i < 200; ++i) {
    const auto d = datagram_for(i);
    client.send_to(at.port, d.data(), d.size());
    (void)client.receive(5);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_EQ(tool.stop(), 0);
  const std::string out = tool.output();
  const auto json = nlohmann::json::parse(out.substr(out.find('{')));
  EXPECT_EQ(json["to_server"]["received"].get<int>(), 200);
  expect_binomial(json["to_server"]["lost"].get<std::uint64_t>(), 200, 0.5, "lost");
  EXPECT_EQ(json["config"]["seed"].get<int>(), 5);
  EXPECT_EQ(json["clients"].get<int>(), 1);
}

TEST(HapticChaosTool, RefusesBadFlags) {
  for (const std::vector<std::string>& args : {std::vector<std::string>{"--forward", "nowhere"},
                                               {"--forward", "127.0.0.1:0"},
                                               {"--forward", "127.0.0.1:7000", "--loss", "2"},
                                               {"--listen", "0"}}) {
    sim::ChildProcess tool(HAPTICD_CHAOS_BIN, args);
    const auto status = tool.wait(std::chrono::seconds(10));
    ASSERT_TRUE(status.has_value());
    EXPECT_NE(*status, 0) << args[0] << " " << args[1];
  }
}

}  // namespace
}  // namespace hapticd::chaos
