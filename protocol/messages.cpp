#include "protocol/messages.hpp"

namespace hapticd::protocol {

std::string_view to_string(MessageType type) noexcept {
  switch (type) {
    case MessageType::kNone:
      return "none";
    case MessageType::kHello:
      return "hello";
    case MessageType::kWelcome:
      return "welcome";
    case MessageType::kError:
      return "error";
    case MessageType::kPoseSample:
      return "pose_sample";
    case MessageType::kForceSample:
      return "force_sample";
    case MessageType::kHeartbeat:
      return "heartbeat";
    case MessageType::kStatsRequest:
      return "stats_request";
    case MessageType::kStats:
      return "stats";
    case MessageType::kBye:
      return "bye";
  }
  return "unknown";
}

std::string_view to_string(DeviceKind kind) noexcept {
  switch (kind) {
    case DeviceKind::kUnspecified:
      return "unspecified";
    case DeviceKind::kStylus:
      return "stylus";
    case DeviceKind::kGlove:
      return "glove";
  }
  return "unknown";
}

std::string_view to_string(Hand hand) noexcept {
  switch (hand) {
    case Hand::kUnspecified:
      return "unspecified";
    case Hand::kLeft:
      return "left";
    case Hand::kRight:
      return "right";
  }
  return "unknown";
}

std::string_view to_string(ErrorCode code) noexcept {
  switch (code) {
    case ErrorCode::kUnspecified:
      return "unspecified";
    case ErrorCode::kVersionMismatch:
      return "version_mismatch";
    case ErrorCode::kMalformedHello:
      return "malformed_hello";
    case ErrorCode::kUnauthorized:
      return "unauthorized";
    case ErrorCode::kServerFull:
      return "server_full";
    case ErrorCode::kUnsupportedDevice:
      return "unsupported_device";
    case ErrorCode::kUnsupportedRate:
      return "unsupported_rate";
    case ErrorCode::kInternal:
      return "internal";
    case ErrorCode::kShuttingDown:
      return "shutting_down";
  }
  return "unknown";
}

}  // namespace hapticd::protocol
