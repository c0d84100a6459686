#pragma once

// A servo run as JSON: the figures haptic-device writes to --report and haptic-bench latency
// stores per phase. Field names carry their units.

#include <nlohmann/json.hpp>

#include "protocol/messages.hpp"

#include "clients/sim/glove_simulation.hpp"
#include "clients/sim/servo_loop.hpp"

namespace hapticd::sim {

// rtt_us {p50, p90, p99, p999, max}, late_fraction, loss_fraction, force_n {max, rms},
// passivity_energy_j, penetration_mm_max, rate_hz_achieved, samples_sent, replies, late, lost,
// contact_fraction, and the remaining counters of ServoResult and the Client.
nlohmann::json to_json(const ServoResult& result);
nlohmann::json to_json(const RttSummary& rtt);
// A glove run's per-finger figures, added to the ServoResult's (whose force_n, contact_fraction,
// penetration_mm_max and passivity_energy_j then cover the whole hand: |sum of every frame's
// force|, any frame in contact, the farthest frame in contact from its commanded pose, the work of
// every frame's wrench):
//   fingers: {thumb, index, middle, ring, little} each {force_n {max, rms} of |sum of the finger's
//            frames' forces| (3 frames with 16, the distal one with 6) over ticks,
//            contact_fraction (ticks any of its frames reported InContact), joint_lag_deg_max
//            (largest |commanded - actual| angle over its 4 joints and the ticks)}
//   palm:    {force_n {max, rms}, contact_fraction} of frame 0.
nlohmann::json glove_figures_to_json(const GloveSimulation& sim);
// The server's Stats message (what a client can ask a running hapticd).
nlohmann::json to_json(const protocol::Stats& stats);

}  // namespace hapticd::sim
