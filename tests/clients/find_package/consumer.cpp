// Built against the installed hapticd_client package: the headers resolve, the library links, and a
// Client reports a refused connection as such.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>

#include "clients/cpp/client.hpp"
#include "protocol/limits.hpp"

int main() {
  using namespace hapticd;
  // A port that was just free, so nothing answers: ICMP port unreachable, ErrorKind::kRefused.
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof a;
  ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &length);
  ::close(fd);

  protocol::Hello hello;
  hello.client_name = "consumer";
  hello.device_kind = protocol::DeviceKind::kStylus;
  protocol::TrackedFrame frame;
  frame.name = "stylus";
  hello.frames.push_back(frame);
  client::Client c;
  try {
    c.connect("127.0.0.1", ntohs(a.sin_port), hello, std::chrono::seconds(2));
  } catch (const client::ClientError& e) {
    if (e.kind() == client::ErrorKind::kRefused) {
      std::printf("consumer: ok (protocol version %u): %s\n", protocol::kProtocolVersion, e.what());
      return 0;
    }
    std::printf("consumer: unexpected error: %s\n", e.what());
    return 1;
  }
  std::printf("consumer: connected to nothing?\n");
  return 1;
}
