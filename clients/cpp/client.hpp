#pragma once

// hapticd::client: one device session with a hapticd server over UDP (protocol/README.md).
//
//   Client client;
//   Welcome w = client.connect("127.0.0.1", 7000, hello, 2s);   // throws ClientError
//   PoseSample pose = ...;                                        // poses filled by the caller
//   client.send_pose(pose);                                       // session, sequence, time filled
//   if (auto reply = client.poll_force(1ms)) apply(reply->sample);
//   client.bye();
//
// connect() may allocate and throws; after it, send_pose(), poll_force() and heartbeat() neither
// allocate nor throw (tests/clients/test_client_no_allocation.cpp proves it): they sit in a
// device's servo loop. A Client belongs to one thread.
//
// With set_key() (the server's pre-shared key, protocol/key_file.hpp) the session is authenticated
// (protocol/auth.hpp): the Hello carries a fresh nonce and a MAC, only answers whose MAC verifies
// are believed, and every datagram either way carries a MAC and a counter checked against replay.

#include <array>
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>

#include "protocol/auth.hpp"
#include "protocol/codec.hpp"
#include "protocol/messages.hpp"
#include "protocol/sequence_window.hpp"

namespace hapticd::client {

// What went wrong, for callers that branch on it; what() says it for people.
enum class ErrorKind : std::uint8_t {
  kBadAddress,    // host does not resolve, port 0, or an address the socket cannot use
  kSocket,        // a socket call failed (errno in the message)
  kRefused,       // nothing listens at the server's address (ICMP port unreachable)
  kTimeout,       // no answer before the deadline
  kRejected,      // the server answered the Hello with an Error: server_code(), server_message()
  kInvalid,       // the message handed in breaks a protocol rule (validate() names the reason)
  kNotConnected,  // a session call before connect() or after bye()
  // With a key: the server answered, but nothing it sent verified with this client's key (a server
  // without a key, or with another one); what it said is in the message.
  kUnauthenticated,
};

std::string_view to_string(ErrorKind kind) noexcept;

class ClientError : public std::runtime_error {
 public:
  ClientError(ErrorKind kind, const std::string& what,
              protocol::ErrorCode server_code = protocol::ErrorCode::kUnspecified, std::string server_message = {});

  [[nodiscard]] ErrorKind kind() const noexcept { return kind_; }
  // Set when kind() is kRejected: the code and text of the server's Error.
  [[nodiscard]] protocol::ErrorCode server_code() const noexcept { return server_code_; }
  [[nodiscard]] const std::string& server_message() const noexcept { return server_message_; }

 private:
  ErrorKind kind_;
  protocol::ErrorCode server_code_;
  std::string server_message_;
};

// Outcome of a hot-path send: no exception there, the caller's loop decides.
enum class SendResult : std::uint8_t {
  kSent,
  kInvalid,       // the encoder refused it (NaN, absurd value, bad frame list): nothing sent
  kWouldBlock,    // socket send buffer full: dropped, like a lost datagram
  kFailed,        // send() failed otherwise (e.g. ECONNREFUSED after the server went away)
  kNotConnected,  // no session
};

std::string_view to_string(SendResult result) noexcept;

// A ForceSample accepted by poll_force(), with the client-clock time its datagram was read.
struct ForceReply {
  protocol::ForceSample sample;
  std::uint64_t received_ns = 0;  // protocol::now_ns() right after recv()

  // Round trip of the pose it answers: both ends on this machine's clock (the echoed timestamp).
  [[nodiscard]] std::uint64_t rtt_ns() const noexcept { return received_ns - sample.client_timestamp_ns; }
};

// Datagram bookkeeping since connect(); what a device's report and a bench read.
struct ClientCounters {
  std::uint64_t poses_sent = 0;
  std::uint64_t frames_dropped = 0;  // non-finite frame poses left out of samples (lost tracking)
  std::uint64_t send_failures = 0;  // kInvalid, kWouldBlock, kFailed
  std::uint64_t forces_accepted = 0;
  // ForceSamples not newer than the newest accepted one (late or duplicated): an old force is
  // never worth applying.
  std::uint64_t forces_stale = 0;
  std::uint64_t datagrams_rejected = 0;  // failed decode(): dropped, never answered
  // Verified, but not for this session or not expected now (another session id, a sequence
  // never sent, a message type a server does not send mid-session).
  std::uint64_t datagrams_unexpected = 0;
  std::uint64_t refused = 0;  // ICMP port unreachable reported by the socket (server gone)
  // With a key: datagrams without a MAC, whose MAC does not verify, or replayed (a counter seen
  // before or too old): dropped, never answered.
  std::uint64_t datagrams_unauthenticated = 0;
};

class Client {
 public:
  // Allocates the encoder, the receive buffer and the decode target: everything the hot path
  // needs, once.
  Client();
  ~Client();  // sends Bye if a session is open
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;

  // Authenticate the next sessions with this pre-shared key (the server's --key-file). Not while
  // connected (throws ClientError kInvalid).
  void set_key(const protocol::Key& key);
  void clear_key();
  [[nodiscard]] bool authenticating() const noexcept { return auth_ != nullptr; }

  // Resolves host (name or address), opens a UDP socket connected to it (the kernel then drops
  // datagrams from any other source), sends `hello` and waits for the Welcome. The Hello is
  // re-sent every `resend_interval` until `timeout`, so one lost datagram does not fail the
  // handshake (a server replaces a peer's session when it says hello again, so a Welcome to a
  // re-sent Hello arriving later is adopted as the live session). Throws ClientError: kBadAddress, kSocket, kRefused,
  // kTimeout, kRejected (with the server's code and message), kInvalid. A Client already connected says Bye first.
  // With a key every Hello sent (re-sends too) carries a fresh nonce in place of hello.credentials;
  // the first Welcome that verifies is the session (the server confirms it on the first pose and
  // drops the others), and a timeout after answers that did not verify throws kUnauthenticated.
  protocol::Welcome connect(const std::string& host, std::uint16_t port, const protocol::Hello& hello,
                            std::chrono::nanoseconds timeout,
                            std::chrono::nanoseconds resend_interval = std::chrono::milliseconds(500));

  // Fills pose.session_id and pose.sequence (previous + 1, the first is 1) and, when it is 0,
  // pose.client_timestamp_ns (now), then sends it. The caller owns the poses and buttons. A frame
  // whose pose is not finite (lost tracking) is removed from pose.poses and counted
  // (ClientCounters::frames_dropped): the server holds that frame and ramps its force to zero
  // while the others keep working. With no finite frame left the sample is kInvalid.
  SendResult send_pose(protocol::PoseSample& pose) noexcept;

  // The next ForceSample of this session newer than every one accepted so far, waiting at most
  // `timeout` (0: only what is already queued). Older or duplicated ones are dropped and counted;
  // Heartbeats and Stats met on the way are kept for heartbeat() / request_stats().
  std::optional<ForceReply> poll_force(std::chrono::nanoseconds timeout) noexcept;
  // The same with an absolute deadline on protocol::now_ns()'s clock (CLOCK_MONOTONIC).
  std::optional<ForceReply> poll_force_until(std::uint64_t deadline_ns) noexcept;

  // Keeps the session alive while no poses flow; echoes the server's last heartbeat timestamp.
  SendResult heartbeat() noexcept;

  // Asks for the server's Stats and waits for them. ForceSamples arriving meanwhile are kept for
  // the next poll_force() (the newest one). Throws ClientError kNotConnected, kTimeout, kRefused.
  protocol::Stats request_stats(std::chrono::nanoseconds timeout);

  // Ends the session (the server ramps its force to zero). Idempotent; never throws.
  void bye() noexcept;

  [[nodiscard]] bool connected() const noexcept { return session_id_ != protocol::kNoSession; }
  [[nodiscard]] std::uint64_t session_id() const noexcept { return session_id_; }
  [[nodiscard]] const protocol::Welcome& welcome() const noexcept { return welcome_; }
  [[nodiscard]] std::uint64_t last_sequence_sent() const noexcept { return next_sequence_ - 1; }
  [[nodiscard]] const ClientCounters& counters() const noexcept { return counters_; }
  // "address:port" of the server and of this socket, once connected.
  [[nodiscard]] const std::string& server_address() const noexcept { return server_address_; }
  [[nodiscard]] std::uint16_t local_port() const noexcept { return local_port_; }
  // The UDP socket (-1 when closed), for callers that multiplex it with poll().
  [[nodiscard]] int native_handle() const noexcept { return fd_; }

 private:
  enum class Received : std::uint8_t { kNothing, kForce, kStats, kHandshake, kRefused, kOther };

  // Reads at most one datagram until deadline_ns and files it; never allocates.
  Received receive_one(std::uint64_t deadline_ns) noexcept;
  SendResult send_bytes(std::span<const std::uint8_t> bytes) noexcept;
  // A session message: sealed with the client -> server key and the next counter when authenticating.
  SendResult send_message(const protocol::EncodeResult& encoded) noexcept;
  // With a key: the trailer of a received datagram checked; false (counted) when not authentic.
  // `body` is then the message's bytes.
  bool authenticate(std::span<const std::uint8_t> datagram, std::span<const std::uint8_t>& body) noexcept;
  void close_socket() noexcept;

  // What answered the Hello without verifying (with a key), to explain a timeout.
  enum class Unverified : std::uint8_t { kNothing, kPlainWelcome, kPlainError, kBadMac };

  protocol::Encoder encoder_;
  protocol::ReceiveBuffer rx_;
  protocol::Message message_;  // decode target, reused
  protocol::Welcome welcome_;
  protocol::Error handshake_error_;
  bool handshake_answered_ = false;
  int hellos_sent_ = 0;
  protocol::Stats stats_;
  bool stats_received_ = false;
  ForceReply pending_force_;  // newest accepted ForceSample not yet returned by poll_force()
  bool force_pending_ = false;
  std::uint64_t newest_force_sequence_ = 0;
  std::uint64_t last_peer_heartbeat_ns_ = 0;
  std::uint64_t session_id_ = protocol::kNoSession;
  std::uint64_t next_sequence_ = 1;
  ClientCounters counters_;
  std::unique_ptr<protocol::AuthKeys> auth_;
  std::unique_ptr<protocol::Sealer> sealer_;
  static constexpr std::size_t kHelloNonces = 8;  // re-sent Hellos whose answers are still believed
  std::array<protocol::Nonce, kHelloNonces> hello_nonces_{};
  protocol::SessionKeys session_keys_;
  protocol::SequenceWindow counters_in_;  // server -> client trailer counters seen
  std::uint64_t counter_out_ = 0;
  Unverified unverified_ = Unverified::kNothing;
  protocol::Error unverified_error_;
  std::string server_address_;
  std::uint16_t local_port_ = 0;
  int fd_ = -1;
};

}  // namespace hapticd::client
