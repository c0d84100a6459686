#include "clients/chaos/chaos_relay.hpp"

#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <ctime>
#include <mutex>
#include <optional>
#include <random>
#include <stdexcept>
#include <thread>
#include <vector>

namespace hapticd::chaos {

namespace {

std::uint64_t now_ns() {
  timespec t{};
  clock_gettime(CLOCK_MONOTONIC, &t);
  return static_cast<std::uint64_t>(t.tv_sec) * 1'000'000'000ull + static_cast<std::uint64_t>(t.tv_nsec);
}

constexpr std::size_t kMaxDatagram = 65536;
constexpr std::size_t kMaxQueued = 100000;
constexpr std::size_t kMaxClients = 64;

// Resolves host:port for UDP, IPv4 first (as the client library does).
sockaddr_storage resolve(const std::string& host, std::uint16_t port, socklen_t& length, bool passive) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_DGRAM;
  hints.ai_flags = passive ? AI_PASSIVE : 0;
  addrinfo* list = nullptr;
  const std::string service = std::to_string(port);
  if (const int rc = ::getaddrinfo(host.c_str(), service.c_str(), &hints, &list); rc != 0 || list == nullptr)
    throw std::runtime_error("cannot resolve '" + host + "': " + ::gai_strerror(rc));
  const addrinfo* pick = list;
  for (const addrinfo* a = list; a != nullptr; a = a->ai_next)
    if (a->ai_family == AF_INET) {
      pick = a;
      break;
    }
  sockaddr_storage out{};
  std::memcpy(&out, pick->ai_addr, pick->ai_addrlen);
  length = pick->ai_addrlen;
  ::freeaddrinfo(list);
  return out;
}

std::string describe(const sockaddr_storage& a) {
  char host[NI_MAXHOST] = "?", port[NI_MAXSERV] = "?";
  ::getnameinfo(reinterpret_cast<const sockaddr*>(&a), sizeof a, host, sizeof host, port, sizeof port,
                NI_NUMERICHOST | NI_NUMERICSERV);
  return a.ss_family == AF_INET6 ? "[" + std::string(host) + "]:" + port : std::string(host) + ":" + port;
}

struct Pending {
  std::uint64_t due_ns = 0;
  std::uint64_t order = 0;  // ties keep arrival order (a duplicate right after its original)
  bool to_server = true;
  std::size_t flow = 0;
  bool corrupted = false;
  bool duplicate = false;
  std::vector<std::uint8_t> bytes;
};

struct Later {
  bool operator()(const Pending& a, const Pending& b) const {
    return a.due_ns != b.due_ns ? a.due_ns > b.due_ns : a.order > b.order;
  }
};

struct Flow {
  sockaddr_storage client{};
  socklen_t client_length = 0;
  int upstream = -1;               // connected to the server
  std::optional<Pending> held[2];  // [to_server]
  std::uint64_t held_since_ns[2]{};
};

}  // namespace

void validate(const ChaosConfig& c) {
  const auto rate = [](double p, const char* name) {
    if (!(p >= 0.0 && p <= 1.0))
      throw std::invalid_argument(std::string(name) + ": a probability in [0, 1], got " + std::to_string(p));
  };
  rate(c.loss, "loss");
  rate(c.duplicate, "duplicate");
  rate(c.reorder, "reorder");
  rate(c.corrupt, "corrupt");
  const auto delay = [](double d, const char* name) {
    if (!(d >= 0.0 && d <= 60000.0))
      throw std::invalid_argument(std::string(name) + ": milliseconds in [0, 60000], got " + std::to_string(d));
  };
  delay(c.delay_ms, "delay_ms");
  delay(c.jitter_ms, "jitter_ms");
  delay(c.reorder_hold_ms, "reorder_hold_ms");
}

struct ChaosRelay::Impl {
  ChaosConfig config;
  std::mt19937_64 rng;
  std::uniform_real_distribution<double> unit{0.0, 1.0};
  int listen_fd = -1;
  sockaddr_storage server{};
  socklen_t server_length = 0;
  std::vector<Flow> flows;
  std::vector<Pending> queue;  // a heap under Later
  std::uint64_t order = 0;
  mutable std::mutex counts_mutex;
  ChaosCounts counts;
  std::vector<std::uint8_t> rx = std::vector<std::uint8_t>(kMaxDatagram);
  std::atomic<bool> thread_stop{false};
  std::thread thread;

  DirectionCounts& direction(bool to_server) { return to_server ? counts.to_server : counts.to_client; }

  std::size_t flow_of(const sockaddr_storage& from, socklen_t length) {
    for (std::size_t i = 0; i < flows.size(); ++i)
      if (flows[i].client_length == length && std::memcmp(&flows[i].client, &from, length) == 0) return i;
    if (flows.size() >= kMaxClients) return flows.size();
    Flow f;
    f.client = from;
    f.client_length = length;
    f.upstream = ::socket(server.ss_family, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (f.upstream < 0 || ::connect(f.upstream, reinterpret_cast<const sockaddr*>(&server), server_length) != 0) {
      if (f.upstream >= 0) ::close(f.upstream);
      return flows.size();
    }
    flows.push_back(f);
    const std::lock_guard lock(counts_mutex);
    counts.clients = flows.size();
    return flows.size() - 1;
  }

  void transmit(const Pending& p) {
    Flow& f = flows[p.flow];
    const ssize_t n = p.to_server ? ::send(f.upstream, p.bytes.data(), p.bytes.size(), MSG_DONTWAIT)
                                  : ::sendto(listen_fd, p.bytes.data(), p.bytes.size(), MSG_DONTWAIT,
                                             reinterpret_cast<const sockaddr*>(&f.client), f.client_length);
    const std::lock_guard lock(counts_mutex);
    DirectionCounts& d = direction(p.to_server);
    if (n != static_cast<ssize_t>(p.bytes.size())) {
      ++d.send_errors;
      return;
    }
    ++d.sent;
    d.corrupted += p.corrupted;
    d.duplicated += p.duplicate;
  }

  // Sends a due datagram, then the one held back for it to overtake, if it arrived before it.
  void release(const Pending& p) {
    transmit(p);
    std::optional<Pending>& held = flows[p.flow].held[p.to_server];
    if (held && held->order < p.order) {
      transmit(*held);
      held.reset();
      const std::lock_guard lock(counts_mutex);
      ++direction(p.to_server).reordered;
    }
  }

  void arrive(bool to_server, std::size_t flow, const std::uint8_t* data, std::size_t size, std::uint64_t now) {
    // Every decision draws the same numbers whatever the outcome, so the pattern depends only on
    // the order datagrams arrive in.
    const bool lose = unit(rng) < config.loss;
    const bool corrupt = unit(rng) < config.corrupt;
    const bool duplicate = unit(rng) < config.duplicate;
    const bool reorder = unit(rng) < config.reorder;
    const double delay_ms = config.delay_ms + config.jitter_ms * unit(rng);
    const std::size_t at = static_cast<std::size_t>(rng() % std::max<std::size_t>(size, 1));
    const auto flip = static_cast<std::uint8_t>(1 + rng() % 255);
    {
      const std::lock_guard lock(counts_mutex);
      DirectionCounts& d = direction(to_server);
      ++d.received;
      if (flow >= flows.size() || queue.size() + 2 > kMaxQueued) {
        ++d.overflow;
        return;
      }
      if (lose) {
        ++d.lost;
        return;
      }
    }
    Pending p;
    p.due_ns = now + static_cast<std::uint64_t>(delay_ms * 1e6);
    p.order = order++;
    p.to_server = to_server;
    p.flow = flow;
    p.bytes.assign(data, data + size);
    if (duplicate) {
      Pending copy = p;
      copy.order = order++;
      copy.duplicate = true;
      queue.push_back(std::move(copy));
      std::push_heap(queue.begin(), queue.end(), Later{});
    }
    if (corrupt && size > 0) {
      p.bytes[at] ^= flip;
      p.corrupted = true;
    }
    Flow& f = flows[flow];
    if (reorder && !f.held[to_server]) {
      f.held[to_server] = std::move(p);
      f.held_since_ns[to_server] = now;
      return;
    }
    queue.push_back(std::move(p));
    std::push_heap(queue.begin(), queue.end(), Later{});
  }

  void drain(int fd, bool to_server, std::size_t flow) {
    for (;;) {
      sockaddr_storage from{};
      socklen_t length = sizeof from;
      const ssize_t n = ::recvfrom(fd, rx.data(), rx.size(), MSG_DONTWAIT, reinterpret_cast<sockaddr*>(&from), &length);
      if (n < 0) {
        if (errno == EINTR) continue;
        return;  // EAGAIN, or ECONNREFUSED from a server not (yet) there
      }
      const std::uint64_t now = now_ns();
      if (to_server) flow = flow_of(from, length);
      arrive(to_server, flow, rx.data(), static_cast<std::size_t>(n), now);
    }
  }

  void run(const std::atomic<bool>& stop) {
    const auto hold_ns = static_cast<std::uint64_t>(config.reorder_hold_ms * 1e6);
    std::vector<pollfd> fds;
    while (!stop.load(std::memory_order_relaxed)) {
      std::uint64_t now = now_ns();
      while (!queue.empty() && queue.front().due_ns <= now) {
        std::pop_heap(queue.begin(), queue.end(), Later{});
        const Pending p = std::move(queue.back());
        queue.pop_back();
        release(p);
      }
      // Held back with nothing to overtake it: sent late, in order after all.
      std::uint64_t wake = now + 10'000'000ull;
      for (Flow& f : flows)
        for (int d = 0; d < 2; ++d) {
          if (!f.held[d]) continue;
          if (now - f.held_since_ns[d] >= hold_ns) {
            transmit(*f.held[d]);
            f.held[d].reset();
          } else {
            wake = std::min(wake, f.held_since_ns[d] + hold_ns);
          }
        }
      if (!queue.empty()) wake = std::min(wake, queue.front().due_ns);
      fds.clear();
      fds.push_back({listen_fd, POLLIN, 0});
      for (const Flow& f : flows) fds.push_back({f.upstream, POLLIN, 0});
      now = now_ns();
      const std::uint64_t wait = wake > now ? wake - now : 0;
      const timespec timeout{static_cast<time_t>(wait / 1'000'000'000ull), static_cast<long>(wait % 1'000'000'000ull)};
      if (::ppoll(fds.data(), fds.size(), &timeout, nullptr) <= 0) continue;
      if (fds[0].revents) drain(listen_fd, true, 0);
      for (std::size_t i = 1; i < fds.size(); ++i)
        if (fds[i].revents) drain(flows[i - 1].upstream, false, i - 1);
    }
  }
};

ChaosRelay::ChaosRelay(const ChaosConfig& config, const std::string& forward_host, std::uint16_t forward_port,
                       const std::string& listen_address, std::uint16_t listen_port)
    : impl_(std::make_unique<Impl>()) {
  validate(config);
  if (forward_port == 0) throw std::runtime_error("forward port 0: the server's port is needed");
  impl_->config = config;
  impl_->rng.seed(config.seed);
  impl_->server = resolve(forward_host, forward_port, impl_->server_length, false);
  socklen_t length = 0;
  const sockaddr_storage local = resolve(listen_address, listen_port, length, true);
  impl_->listen_fd = ::socket(local.ss_family, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  if (impl_->listen_fd < 0 || ::bind(impl_->listen_fd, reinterpret_cast<const sockaddr*>(&local), length) != 0)
    throw std::runtime_error("cannot bind " + describe(local) + ": " + std::strerror(errno));
}

ChaosRelay::~ChaosRelay() {
  stop();
  for (const Flow& f : impl_->flows) ::close(f.upstream);
  if (impl_->listen_fd >= 0) ::close(impl_->listen_fd);
}

std::uint16_t ChaosRelay::port() const {
  sockaddr_storage a{};
  socklen_t length = sizeof a;
  ::getsockname(impl_->listen_fd, reinterpret_cast<sockaddr*>(&a), &length);
  return a.ss_family == AF_INET6 ? ntohs(reinterpret_cast<const sockaddr_in6&>(a).sin6_port)
                                 : ntohs(reinterpret_cast<const sockaddr_in&>(a).sin_port);
}

std::string ChaosRelay::address() const {
  sockaddr_storage a{};
  socklen_t length = sizeof a;
  ::getsockname(impl_->listen_fd, reinterpret_cast<sockaddr*>(&a), &length);
  return describe(a);
}

void ChaosRelay::run(const std::atomic<bool>& stop) { impl_->run(stop); }

void ChaosRelay::start() {
  if (impl_->thread.joinable()) return;
  impl_->thread_stop = false;
  impl_->thread = std::thread([this] { impl_->run(impl_->thread_stop); });
}

void ChaosRelay::stop() {
  impl_->thread_stop = true;
  if (impl_->thread.joinable()) impl_->thread.join();
}

ChaosCounts ChaosRelay::counts() const {
  const std::lock_guard lock(impl_->counts_mutex);
  return impl_->counts;
}

const ChaosConfig& ChaosRelay::config() const { return impl_->config; }

nlohmann::json to_json(const ChaosCounts& counts, const ChaosConfig& c) {
  const auto direction = [](const DirectionCounts& d) {
    return nlohmann::json{{"received", d.received},       {"sent", d.sent},           {"lost", d.lost},
                          {"duplicated", d.duplicated},   {"reordered", d.reordered}, {"corrupted", d.corrupted},
                          {"send_errors", d.send_errors}, {"overflow", d.overflow}};
  };
  return {{"config",
           {{"loss", c.loss},
            {"duplicate", c.duplicate},
            {"reorder", c.reorder},
            {"corrupt", c.corrupt},
            {"delay_ms", c.delay_ms},
            {"jitter_ms", c.jitter_ms},
            {"reorder_hold_ms", c.reorder_hold_ms},
            {"seed", c.seed}}},
          {"to_server", direction(counts.to_server)},
          {"to_client", direction(counts.to_client)},
          {"clients", counts.clients}};
}

}  // namespace hapticd::chaos
