#pragma once

// A servo run as JSON: the figures haptic-device writes to --report and haptic-bench latency
// stores per phase. Field names carry their units.

#include <nlohmann/json.hpp>

#include "protocol/messages.hpp"

#include "clients/sim/servo_loop.hpp"

namespace hapticd::sim {

// rtt_us {p50, p90, p99, p999, max}, late_fraction, loss_fraction, force_n {max, rms},
// passivity_energy_j, penetration_mm_max, rate_hz_achieved, samples_sent, replies, late, lost,
// contact_fraction, and the remaining counters of ServoResult and the Client.
nlohmann::json to_json(const ServoResult& result);
nlohmann::json to_json(const RttSummary& rtt);
// The server's Stats message (what a client can ask a running hapticd).
nlohmann::json to_json(const protocol::Stats& stats);

}  // namespace hapticd::sim
