#include "clients/cpp/client.hpp"

#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/udp.hpp>
#include <cerrno>
#include <cstring>
#include <utility>

#include "protocol/clock.hpp"

namespace hapticd::client {

namespace asio = boost::asio;
using asio::ip::udp;
using protocol::MessageType;
using protocol::now_ns;

std::string_view to_string(ErrorKind kind) noexcept {
  switch (kind) {
    case ErrorKind::kBadAddress:
      return "bad_address";
    case ErrorKind::kSocket:
      return "socket";
    case ErrorKind::kRefused:
      return "refused";
    case ErrorKind::kTimeout:
      return "timeout";
    case ErrorKind::kRejected:
      return "rejected";
    case ErrorKind::kInvalid:
      return "invalid";
    case ErrorKind::kNotConnected:
      return "not_connected";
    case ErrorKind::kUnauthenticated:
      return "unauthenticated";
  }
  return "unknown";
}

std::string_view to_string(SendResult result) noexcept {
  switch (result) {
    case SendResult::kSent:
      return "sent";
    case SendResult::kInvalid:
      return "invalid";
    case SendResult::kWouldBlock:
      return "would_block";
    case SendResult::kFailed:
      return "failed";
    case SendResult::kNotConnected:
      return "not_connected";
  }
  return "unknown";
}

ClientError::ClientError(ErrorKind kind, const std::string& what, protocol::ErrorCode server_code,
                         std::string server_message)
    : std::runtime_error(what), kind_(kind), server_code_(server_code), server_message_(std::move(server_message)) {}

namespace {

std::string describe(const udp::endpoint& endpoint) {
  const std::string address = endpoint.address().to_string();
  const std::string port = std::to_string(endpoint.port());
  return endpoint.address().is_v6() ? "[" + address + "]:" + port : address + ":" + port;
}

std::string milliseconds(std::chrono::nanoseconds d) {
  return std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(d).count()) + " ms";
}

timespec to_timespec(std::uint64_t ns) {
  return {static_cast<time_t>(ns / 1'000'000'000ull), static_cast<long>(ns % 1'000'000'000ull)};
}

std::uint64_t deadline_after(std::chrono::nanoseconds timeout) {
  return now_ns() + static_cast<std::uint64_t>(std::max<std::int64_t>(0, timeout.count()));
}

}  // namespace

Client::Client() {
  // The Encoder reserves its builder in the constructor; one throwaway encode also settles
  // anything FlatBuffers sets up lazily, so the first send_pose() is like every other one.
  protocol::Bye warm_up;
  warm_up.session_id = 1;
  (void)encoder_.encode(warm_up);
}

Client::~Client() { bye(); }

void Client::set_key(const protocol::Key& key) {
  if (connected()) throw ClientError(ErrorKind::kInvalid, "set_key() while connected: bye() first");
  auth_ = std::make_unique<protocol::AuthKeys>(key);
  if (!sealer_) sealer_ = std::make_unique<protocol::Sealer>();
}

void Client::clear_key() {
  if (connected()) throw ClientError(ErrorKind::kInvalid, "clear_key() while connected: bye() first");
  auth_.reset();
}

protocol::Welcome Client::connect(const std::string& host, std::uint16_t port, const protocol::Hello& hello,
                                  std::chrono::nanoseconds timeout, std::chrono::nanoseconds resend_interval) {
  bye();
  if (host.empty()) throw ClientError(ErrorKind::kBadAddress, "server host is empty (a name or an address is needed)");
  if (port == 0)
    throw ClientError(ErrorKind::kBadAddress, "server port 0 is not a port a server listens on (1..65535)");
  if (const protocol::RejectReason r = protocol::validate(hello); r != protocol::RejectReason::kNone)
    throw ClientError(ErrorKind::kInvalid, "the Hello breaks a protocol rule: " + std::string(protocol::to_string(r)));

  asio::io_context io;
  boost::system::error_code ec;
  udp::resolver resolver(io);
  const auto results = resolver.resolve(host, std::to_string(port), udp::resolver::numeric_service, ec);
  if (ec || results.empty())
    throw ClientError(ErrorKind::kBadAddress,
                      "cannot resolve server host '" + host + "': " + (ec ? ec.message() : std::string("no address")));
  // IPv4 first: "localhost" also resolves to ::1, which a server bound to 127.0.0.1 never hears.
  udp::endpoint server = results.begin()->endpoint();
  for (const auto& entry : results)
    if (entry.endpoint().address().is_v4()) {
      server = entry.endpoint();
      break;
    }

  udp::socket socket(io);
  socket.open(server.protocol(), ec);
  if (ec) throw ClientError(ErrorKind::kSocket, "cannot open a UDP socket: " + ec.message());
  // A connected UDP socket: the kernel drops datagrams from other sources, and an ICMP port
  // unreachable comes back as ECONNREFUSED instead of a silent timeout.
  socket.connect(server, ec);
  if (ec)
    throw ClientError(ErrorKind::kBadAddress, "cannot use server address " + describe(server) + ": " + ec.message());
  local_port_ = socket.local_endpoint(ec).port();
  server_address_ = describe(server);
  fd_ = socket.release(ec);
  if (ec) throw ClientError(ErrorKind::kSocket, "cannot take over the UDP socket: " + ec.message());

  counters_ = {};
  newest_force_sequence_ = 0;
  next_sequence_ = 1;
  force_pending_ = false;
  stats_received_ = false;
  last_peer_heartbeat_ns_ = 0;
  handshake_answered_ = false;
  hellos_sent_ = 0;
  session_keys_ = {};
  counters_in_.reset();
  counter_out_ = 0;
  unverified_ = Unverified::kNothing;
  protocol::Hello sealed_hello = hello;  // with a key: a fresh nonce as credentials for each send

  const auto refused = [this] {
    close_socket();
    throw ClientError(ErrorKind::kRefused,
                      "no hapticd at " + server_address_ + ": connection refused (nothing listens on that UDP port)");
  };
  const std::uint64_t deadline = deadline_after(timeout);
  const auto resend_ns = static_cast<std::uint64_t>(std::max<std::int64_t>(1'000'000, resend_interval.count()));
  std::uint64_t next_send = now_ns();
  while (!handshake_answered_) {
    const std::uint64_t now = now_ns();
    if (now >= deadline) {
      close_socket();
      const std::string waited = " within " + milliseconds(timeout);
      switch (unverified_) {
        case Unverified::kNothing:
          break;
        case Unverified::kPlainWelcome:
          throw ClientError(ErrorKind::kUnauthenticated,
                            "hapticd at " + server_address_ +
                                " answered the Hello without a MAC (it runs without --key-file), and this client "
                                "has a key: no unauthenticated session" +
                                waited);
        case Unverified::kPlainError:
        case Unverified::kBadMac: {
          const std::string code(protocol::to_string(unverified_error_.code));
          throw ClientError(ErrorKind::kUnauthenticated,
                            "hapticd at " + server_address_ + " answered the Hello with " +
                                (unverified_ == Unverified::kPlainError ? "an Error without a MAC"
                                                                        : "a reply whose MAC does not verify") +
                                (unverified_ == Unverified::kPlainError
                                     ? ": " + code + ": " + std::string(unverified_error_.message.view())
                                     : std::string()) +
                                " (is the key file the server's?), and nothing authentic" + waited);
        }
      }
      throw ClientError(ErrorKind::kTimeout, "no answer from hapticd at " + server_address_ + " to the Hello within " +
                                                 milliseconds(timeout) + " (is the server running on that port?)");
    }
    if (now >= next_send) {
      const std::uint64_t refused_before = counters_.refused;
      std::span<const std::uint8_t> bytes;
      if (auth_) {
        protocol::Nonce& nonce = hello_nonces_[static_cast<std::size_t>(hellos_sent_) % kHelloNonces];
        nonce = protocol::random_nonce();
        sealed_hello.credentials.assign(std::span<const std::uint8_t>(nonce));
        bytes = sealer_->seal(encoder_.encode(sealed_hello).bytes, {protocol::TrailerKind::kHello, 0, 0},
                              auth_->hello_key());
      } else {
        bytes = encoder_.encode(hello).bytes;
      }
      const SendResult sent = send_bytes(bytes);
      const int err = errno;
      ++hellos_sent_;
      if (counters_.refused != refused_before) refused();
      if (sent == SendResult::kFailed) {
        close_socket();
        throw ClientError(ErrorKind::kSocket,
                          "cannot send the Hello to " + server_address_ + ": " + std::strerror(err));
      }
      next_send = now + resend_ns;
    }
    if (receive_one(std::min(deadline, next_send)) == Received::kRefused) refused();
  }
  if (welcome_.session_id == protocol::kNoSession) {
    close_socket();
    const std::string code(protocol::to_string(handshake_error_.code));
    throw ClientError(ErrorKind::kRejected,
                      "hapticd at " + server_address_ + " refused the session: " + code + " (" +
                          std::to_string(static_cast<unsigned>(handshake_error_.code)) +
                          "): " + std::string(handshake_error_.message.view()),
                      handshake_error_.code, std::string(handshake_error_.message.view()));
  }
  session_id_ = welcome_.session_id;
  return welcome_;
}

SendResult Client::send_pose(protocol::PoseSample& pose) noexcept {
  if (!connected()) return SendResult::kNotConnected;
  // A frame whose tracking failed (a non-finite pose) is left out: the server holds its last pose
  // and ramps its force to zero while the other frames keep working.
  std::size_t kept = 0;
  for (std::size_t i = 0; i < pose.poses.size(); ++i) {
    const protocol::FramePose& f = pose.poses[i];
    const bool finite = std::isfinite(f.position_m.x) && std::isfinite(f.position_m.y) &&
                        std::isfinite(f.position_m.z) && std::isfinite(f.orientation.w) &&
                        std::isfinite(f.orientation.x) && std::isfinite(f.orientation.y) &&
                        std::isfinite(f.orientation.z);
    if (finite) pose.poses[kept++] = f;
  }
  counters_.frames_dropped += pose.poses.size() - kept;
  pose.poses.resize(kept);
  pose.session_id = session_id_;
  pose.sequence = next_sequence_;
  if (pose.client_timestamp_ns == 0) pose.client_timestamp_ns = now_ns();
  const protocol::EncodeResult e = encoder_.encode(pose);
  if (!e.ok()) {
    ++counters_.send_failures;
    return SendResult::kInvalid;
  }
  // A sequence is spent once a valid pose was handed to the socket, sent or not: the server then
  // sees a failed send as the lost datagram it is.
  ++next_sequence_;
  const SendResult sent = send_message(e);
  if (sent == SendResult::kSent) ++counters_.poses_sent;
  return sent;
}

std::optional<ForceReply> Client::poll_force(std::chrono::nanoseconds timeout) noexcept {
  return poll_force_until(deadline_after(timeout));
}

std::optional<ForceReply> Client::poll_force_until(std::uint64_t deadline_ns) noexcept {
  if (!connected()) return std::nullopt;
  for (;;) {
    if (force_pending_) {
      force_pending_ = false;
      return pending_force_;
    }
    if (receive_one(deadline_ns) == Received::kNothing) return std::nullopt;
  }
}

SendResult Client::heartbeat() noexcept {
  if (!connected()) return SendResult::kNotConnected;
  protocol::Heartbeat h;
  h.session_id = session_id_;
  h.timestamp_ns = now_ns();
  h.echo_timestamp_ns = last_peer_heartbeat_ns_;
  const protocol::EncodeResult e = encoder_.encode(h);
  if (!e.ok()) return SendResult::kInvalid;
  return send_message(e);
}

protocol::Stats Client::request_stats(std::chrono::nanoseconds timeout) {
  if (!connected()) throw ClientError(ErrorKind::kNotConnected, "request_stats() needs a session: connect() first");
  protocol::StatsRequest request;
  request.session_id = session_id_;
  stats_received_ = false;
  if (const SendResult r = send_message(encoder_.encode(request)); r != SendResult::kSent)
    throw ClientError(ErrorKind::kSocket,
                      "cannot send a StatsRequest to " + server_address_ + ": " + std::string(to_string(r)));
  const std::uint64_t deadline = deadline_after(timeout);
  while (!stats_received_) {
    const Received got = receive_one(deadline);
    if (got == Received::kNothing)
      throw ClientError(ErrorKind::kTimeout,
                        "no Stats from hapticd at " + server_address_ + " within " + milliseconds(timeout));
    if (got == Received::kRefused)
      throw ClientError(ErrorKind::kRefused, "hapticd at " + server_address_ + " is gone: connection refused");
  }
  return stats_;
}

void Client::bye() noexcept {
  if (connected()) {
    protocol::Bye b;
    b.session_id = session_id_;
    const protocol::EncodeResult e = encoder_.encode(b);
    if (e.ok()) (void)send_message(e);
    session_id_ = protocol::kNoSession;
  }
  close_socket();
}

void Client::close_socket() noexcept {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

SendResult Client::send_bytes(std::span<const std::uint8_t> bytes) noexcept {
  if (fd_ < 0) return SendResult::kNotConnected;
  for (;;) {
    // MSG_NOSIGNAL: a vanished peer must not kill the device process.
    const ssize_t n = ::send(fd_, bytes.data(), bytes.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
    if (n >= 0) return SendResult::kSent;
    if (errno == EINTR) continue;
    ++counters_.send_failures;
    if (errno == EAGAIN || errno == EWOULDBLOCK) return SendResult::kWouldBlock;
    if (errno == ECONNREFUSED) ++counters_.refused;
    return SendResult::kFailed;
  }
}

SendResult Client::send_message(const protocol::EncodeResult& encoded) noexcept {
  if (!encoded.ok()) return SendResult::kInvalid;
  if (!auth_) return send_bytes(encoded.bytes);
  // A counter is spent like a sequence: a failed send looks like a lost datagram.
  const auto sealed =
      sealer_->seal(encoded.bytes, {protocol::TrailerKind::kClientToServer, session_id_, ++counter_out_},
                    session_keys_.client_to_server);
  if (sealed.empty()) return SendResult::kInvalid;
  return send_bytes(sealed);
}

bool Client::authenticate(std::span<const std::uint8_t> datagram, std::span<const std::uint8_t>& body) noexcept {
  protocol::Trailer trailer;
  const bool awaiting_handshake = !connected() && !handshake_answered_;
  if (protocol::split_trailer(datagram, body, trailer) != protocol::RejectReason::kNone) {
    // A plain answer to the Hello: a server without a key, or one saying ours is missing or wrong.
    // Not believed (anyone can send it), only remembered to explain a timeout.
    if (awaiting_handshake && protocol::decode(datagram, message_).ok()) {
      if (message_.type == MessageType::kWelcome && unverified_ == Unverified::kNothing)
        unverified_ = Unverified::kPlainWelcome;
      if (message_.type == MessageType::kError) {
        unverified_ = Unverified::kPlainError;
        unverified_error_ = message_.error;
      }
    }
    ++counters_.datagrams_unauthenticated;
    return false;
  }
  switch (trailer.kind) {
    case protocol::TrailerKind::kHandshakeReply: {
      // Late answers to re-sent Hellos once a Welcome verified: the server drops their sessions.
      if (!awaiting_handshake) break;
      const auto sent = static_cast<std::size_t>(std::min<int>(hellos_sent_, static_cast<int>(kHelloNonces)));
      for (std::size_t i = 0; i < sent; ++i) {
        if (!protocol::verify_mac(datagram, auth_->reply_key(hello_nonces_[i]))) continue;
        if (!protocol::decode(body, message_).ok()) break;
        if (message_.type == MessageType::kWelcome) {
          const protocol::Welcome& w = message_.welcome;
          if (w.session_id != trailer.session_id || w.server_nonce.size() != protocol::kNonceBytes) break;
          protocol::Nonce server_nonce;
          std::copy_n(w.server_nonce.span().begin(), server_nonce.size(), server_nonce.begin());
          session_keys_ = auth_->session_keys(hello_nonces_[i], server_nonce, w.session_id);
        } else if (message_.type != MessageType::kError) {
          break;
        }
        return true;
      }
      if (unverified_ == Unverified::kNothing) unverified_ = Unverified::kBadMac;
      break;
    }
    case protocol::TrailerKind::kServerToClient:
      if (connected() && trailer.session_id == session_id_ &&
          protocol::verify_mac(datagram, session_keys_.server_to_client) &&
          protocol::accept_counter(counters_in_, trailer.counter) == protocol::RejectReason::kNone)
        return true;
      break;
    default:
      break;
  }
  ++counters_.datagrams_unauthenticated;
  return false;
}

Client::Received Client::receive_one(std::uint64_t deadline_ns) noexcept {
  if (fd_ < 0) return Received::kNothing;
  ssize_t n = -1;
  for (;;) {
    n = ::recv(fd_, rx_.bytes.data(), rx_.bytes.size(), MSG_DONTWAIT);
    if (n >= 0) break;
    if (errno == EINTR) continue;
    if (errno == ECONNREFUSED) {
      ++counters_.refused;
      return Received::kRefused;
    }
    if (errno != EAGAIN && errno != EWOULDBLOCK) return Received::kNothing;
    const std::uint64_t now = now_ns();
    if (now >= deadline_ns) return Received::kNothing;
    // ppoll, not poll: a servo period is 1 ms, poll()'s millisecond timeout would round it away.
    pollfd p{fd_, POLLIN, 0};
    const timespec wait = to_timespec(deadline_ns - now);
    if (::ppoll(&p, 1, &wait, nullptr) < 0 && errno != EINTR) return Received::kNothing;
  }
  const std::uint64_t received_ns = now_ns();

  std::span<const std::uint8_t> body{rx_.bytes.data(), static_cast<std::size_t>(n)};
  if (auth_ && !authenticate(body, body)) return Received::kOther;
  const protocol::DecodeResult r = protocol::decode(body, message_);
  if (!r.ok()) {
    ++counters_.datagrams_rejected;
    return Received::kOther;
  }
  const bool ours = connected() && r.session_id == session_id_;
  switch (r.type) {
    case MessageType::kForceSample: {
      const std::uint64_t sequence = message_.force_sample.sequence;
      if (!ours || sequence >= next_sequence_) break;  // another session's, or a pose never sent
      if (sequence <= newest_force_sequence_) {
        ++counters_.forces_stale;
        return Received::kOther;
      }
      newest_force_sequence_ = sequence;
      pending_force_.sample = message_.force_sample;
      pending_force_.received_ns = received_ns;
      force_pending_ = true;
      ++counters_.forces_accepted;
      return Received::kForce;
    }
    case MessageType::kWelcome:
    case MessageType::kError:
      if (!auth_ && connected() && r.type == MessageType::kWelcome && hellos_sent_ > 1 &&
          message_.welcome.session_id != session_id_) {
        // The answer to a re-sent Hello: a server replaces a peer's session when it says hello
        // again, so the newest Welcome names the live one.
        welcome_ = message_.welcome;
        session_id_ = welcome_.session_id;
        return Received::kHandshake;
      }
      if (connected() || handshake_answered_) break;
      handshake_answered_ = true;
      if (r.type == MessageType::kWelcome) {
        welcome_ = message_.welcome;
      } else {
        welcome_ = {};
        handshake_error_ = message_.error;
      }
      return Received::kHandshake;
    case MessageType::kHeartbeat:
      if (!ours) break;
      last_peer_heartbeat_ns_ = message_.heartbeat.timestamp_ns;
      return Received::kOther;
    case MessageType::kStats:
      if (!ours) break;
      stats_ = message_.stats;
      stats_received_ = true;
      return Received::kStats;
    default:
      break;
  }
  ++counters_.datagrams_unexpected;
  return Received::kOther;
}

}  // namespace hapticd::client
