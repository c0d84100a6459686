#include "protocol/reject_reason.hpp"

#include <array>

namespace hapticd::protocol {

std::string_view to_string(RejectReason reason) noexcept {
  // Indexed by value: the enumerators are dense from 0.
  static constexpr std::array<std::string_view, kRejectReasonCount> kNames = {
      "none",
      "empty",
      "too_short",
      "too_long",
      "odd_size",
      "misaligned",
      "bad_identifier",
      "verify_failed",
      "version_mismatch",
      "missing_body",
      "unknown_message_type",
      "bad_count",
      "frame_ids_not_increasing",
      "bad_dof",
      "non_finite",
      "bad_quaternion",
      "out_of_range",
      "bad_rate",
      "bad_device_kind",
      "field_too_long",
      "bad_string",
      "bad_session",
      "missing_mac",
      "bad_mac",
      "replayed",
      "wrong_peer",
      "unknown_session",
      "bad_nonce",
      "rate_limited",
  };
  const auto i = static_cast<std::size_t>(reason);
  return i < kNames.size() ? kNames[i] : "unknown";
}

}  // namespace hapticd::protocol
