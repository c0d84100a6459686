#include "server/haptic/haptic_server.hpp"

#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <time.h>

#include <algorithm>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/address.hpp>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "protocol/clock.hpp"

namespace hapticd::haptic {

namespace asio = boost::asio;

// recvmmsg's batch: kRxBatch datagrams with their senders, per system call.
struct HapticServer::RxBatch {
  protocol::ReceiveBuffer buffers[kRxBatch];
  sockaddr_storage from[kRxBatch];
  iovec iov[kRxBatch];
  mmsghdr headers[kRxBatch];
  RxBatch() {
    for (int k = 0; k < kRxBatch; ++k) {
      iov[k] = {buffers[k].bytes.data(), buffers[k].bytes.size()};
      headers[k] = {};
      headers[k].msg_hdr.msg_name = &from[k];
      headers[k].msg_hdr.msg_namelen = sizeof(sockaddr_storage);
      headers[k].msg_hdr.msg_iov = &iov[k];
      headers[k].msg_hdr.msg_iovlen = 1;
    }
  }
};

struct HapticServer::Io {
  asio::io_context context;
  asio::ip::udp::socket socket{context};
  Endpoint peer;  // sender of the datagram being handled
};

// The core's replies go out on the socket, stamped with the wall clock.
struct HapticServer::Socket final : Transport {
  explicit Socket(Io& owner) : io(owner) {}
  bool send(std::span<const std::uint8_t> datagram, const Endpoint& to) override {
    const ssize_t n = ::sendto(io.socket.native_handle(), datagram.data(), datagram.size(), MSG_DONTWAIT, to.data(),
                               static_cast<socklen_t>(to.size()));
    return n == static_cast<ssize_t>(datagram.size());
  }
  std::uint64_t send_time_ns() override { return protocol::now_ns(); }
  Io& io;
};

namespace {

// The address policy of check_bind: an IP address, loopback unless there is a key or insecure_bind.
void refuse_unsafe_bind(const ServerOptions& options) {
  boost::system::error_code ec;
  const auto address = asio::ip::make_address(options.bind, ec);
  if (ec) throw std::runtime_error("--bind " + options.bind + ": not an IP address (" + ec.message() + ")");
  if (!options.key && !options.insecure_bind && !address.is_loopback())
    throw std::runtime_error("refusing to listen on " + options.bind +
                             " without a key: anyone who can reach it could open a session and move the device. Give "
                             "--key-file FILE (hapticd --generate-key FILE writes one), or --insecure-bind on a "
                             "network you trust");
}

// Opens `socket` and binds it to the options' address (checked by refuse_unsafe_bind) and port; throws
// std::runtime_error with the address and the reason.
void bind_socket(asio::ip::udp::socket& socket, const ServerOptions& options) {
  boost::system::error_code ec;
  const asio::ip::udp::endpoint endpoint(asio::ip::make_address(options.bind, ec), options.port);
  socket.open(endpoint.protocol(), ec);
  if (!ec) socket.bind(endpoint, ec);
  if (ec)
    throw std::runtime_error("cannot bind " + options.bind + ":" + std::to_string(options.port) + ": " + ec.message());
}

}  // namespace

HapticServer::HapticServer(std::vector<DeviceLink> links, const ServerOptions& options,
                           TripleBuffer<HapticSnapshot>& snapshots, TripleBuffer<ProxyTargets>& targets,
                           const VisualReport* visual)
    : options_(options),
      io_(std::make_unique<Io>()),
      socket_(std::make_unique<Socket>(*io_)),
      core_(std::move(links), options, snapshots, targets, *socket_, visual),
      rx_batch_(std::make_unique<RxBatch>()) {
  if (!(options_.source_rate_hz >= 0) || !(options_.source_burst >= 1))
    throw std::invalid_argument("source rate limit: the rate must be >= 0 and the burst >= 1");
  refuse_unsafe_bind(options_);  // check_bind's policy; the bind below is its probe
  // A device sends one pose per granted period: 4x that leaves room for duplicates, heartbeats,
  // stats requests and jitter, and a source past it is flooding.
  limiter_ = std::make_unique<SourceRateLimiter>(
      options_.source_rate_hz > 0 ? options_.source_rate_hz : 4.0 * options_.haptic_rate_hz, options_.source_burst);
  bind_socket(io_->socket, options_);
  boost::system::error_code ec;
  io_->socket.non_blocking(true, ec);
  // Room for ~8 ms of a one-core flood (~1M small datagrams/s): the loop is late now and then
  // (a softirq on its core, a wake-up), and a full buffer drops good datagrams with the flood's.
  // Beyond net.core.rmem_max only with CAP_NET_ADMIN (FORCE); else as much as it allows.
  const int fd = io_->socket.native_handle();
  int rcvbuf = kReceiveBufferBytes;
  if (setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &rcvbuf, sizeof rcvbuf) != 0)
    setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  socklen_t optlen = sizeof rcvbuf;
  if (getsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, &optlen) == 0) core_.stats().receive_buffer_bytes = rcvbuf;
}

HapticServer::~HapticServer() = default;

HapticServer::Drained HapticServer::drain(std::uint64_t deadline) {
  // A batch per system call (under a flood the calls, not the datagrams, cost the most); each
  // datagram is answered before the next one of the batch is looked at.
  ServerStats& st = core_.stats();
  const int fd = io_->socket.native_handle();
  RxBatch& rx = *rx_batch_;
  Drained d;
  for (int round = 0; round < kRxRounds; ++round) {
    for (int k = 0; k < kRxBatch; ++k) rx.headers[k].msg_hdr.msg_namelen = sizeof(sockaddr_storage);
    const int n = ::recvmmsg(fd, rx.headers, kRxBatch, MSG_DONTWAIT, nullptr);
    d.backlog = n == kRxBatch;
    if (n <= 0) break;
    const std::uint64_t received = protocol::now_ns();
    for (int k = 0; k < n; ++k) {
      const socklen_t len = rx.headers[k].msg_hdr.msg_namelen;
      // A source over its allowance is dropped here, before it costs a MAC or a decode.
      if (!limiter_->allow(rx.from[k], len, received)) {
        d.flooded = true;
        ++st.packets_in;
        ++st.rate_limited;
        core_.reject(protocol::RejectReason::kRateLimited);
        continue;
      }
      const std::size_t bytes = rx.headers[k].msg_len;
      io_->peer.resize(len);
      std::copy_n(reinterpret_cast<const char*>(&rx.from[k]), len, reinterpret_cast<char*>(io_->peer.data()));
      core_.handle({rx.buffers[k].bytes.data(), bytes}, io_->peer, protocol::now_ns());
    }
    if (n < kRxBatch || protocol::now_ns() >= deadline) break;
  }
  return d;
}

std::size_t HapticServer::memory_bytes() const {
  // The core sits inside *this: counted once, by its own memory_bytes().
  return sizeof(*this) - sizeof(HapticCore) + core_.memory_bytes() + sizeof(Io) + sizeof(Socket) + sizeof(RxBatch) +
         sizeof(SourceRateLimiter);
}

void HapticServer::check_bind(const ServerOptions& options) {
  refuse_unsafe_bind(options);
  // The address and port can be bound (a probe, closed at once): an address this host does not have
  // or a port in use fails here, before hapticd builds the scene (48 s for the bunny under ASan).
  asio::io_context io;
  asio::ip::udp::socket probe(io);
  bind_socket(probe, options);
}

std::uint16_t HapticServer::port() const { return io_->socket.local_endpoint().port(); }
std::string HapticServer::address() const { return io_->socket.local_endpoint().address().to_string(); }

void HapticServer::run(const std::atomic<bool>& stop) {
  ServerStats& st = core_.stats();
  // Spinning at real-time priority would starve every other thread of its core.
  if (options_.realtime && !options_.busy_poll) {
    sched_param param{};
    param.sched_priority = kRealtimePriority;
    st.realtime = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param) == 0;
  }
  const auto period_ns = static_cast<std::uint64_t>(1e9 / options_.haptic_rate_hz);
  const int fd = io_->socket.native_handle();
  const std::uint64_t start_ns = protocol::now_ns();
  core_.start(start_ns);
  std::uint64_t deadline = start_ns + period_ns;
  Drained drained;  // what the last drain found
  while (!stop.load(std::memory_order_relaxed)) {
    std::uint64_t now = protocol::now_ns();
    if (now >= deadline) {
      st.tick_jitter_us.add(1e-3 * static_cast<double>(now - deadline));
      // A whole period late (the thread was descheduled): the samples that waited meanwhile are
      // read first, so that the core integrates the proxies through the missed periods along them
      // and answers each where it was taken (HapticCore::catch_up).
      if (now >= deadline + period_ns) {
        const Drained d = drain(std::numeric_limits<std::uint64_t>::max());
        drained = {drained.flooded || d.flooded, d.backlog};
        now = protocol::now_ns();  // the tick comes after every sample it read
      }
      core_.tick(now);
      st.tick_compute_us.add(1e-3 * static_cast<double>(protocol::now_ns() - now));
      deadline += period_ns;
      if (protocol::now_ns() >= deadline) {
        // Missed a whole period: count it and re-anchor instead of bursting ticks.
        ++st.overruns;
        deadline = protocol::now_ns() + period_ns;
      }
      continue;
    }
    if (drained.backlog) {
      // The socket was not emptied: read on at once. A pause now would let a flood (~1M datagrams/s
      // from one core) outrun the reads, queue the others' datagrams behind milliseconds of it and,
      // with the buffer full, drop them.
    } else if (!options_.busy_poll && drained.flooded) {
      // A source is over its allowance: waking for each of its datagrams would cost this thread
      // (and the sender's core) a context switch each, so the loop reads what arrived in the
      // next kFloodCoalesce_ns at once. Others' round trips grow by at most that while it lasts.
      const std::uint64_t until = std::min(deadline, now + kFloodCoalesce_ns);
      const timespec ts{static_cast<time_t>(until / 1000000000ull), static_cast<long>(until % 1000000000ull)};
      clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
    } else if (!options_.busy_poll) {
      const std::uint64_t wait = deadline - now;
      timespec timeout{static_cast<time_t>(wait / 1000000000ull), static_cast<long>(wait % 1000000000ull)};
      pollfd p{fd, POLLIN, 0};
      if (ppoll(&p, 1, &timeout, nullptr) <= 0) continue;
    }
    drained = drain(deadline);
  }
  st.elapsed_s = 1e-9 * static_cast<double>(protocol::now_ns() - start_ns);
  rusage usage{};
  if (getrusage(RUSAGE_THREAD, &usage) == 0)
    st.cpu_s = static_cast<double>(usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) +
               1e-6 * static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
  core_.finish();
  st.rate_sources_evicted = limiter_->evictions();
}

}  // namespace hapticd::haptic
