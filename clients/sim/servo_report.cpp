#include "clients/sim/servo_report.hpp"

#include <numbers>

namespace hapticd::sim {

nlohmann::json to_json(const RttSummary& rtt) {
  return {{"p50", rtt.p50_us}, {"p90", rtt.p90_us}, {"p99", rtt.p99_us}, {"p999", rtt.p999_us}, {"max", rtt.max_us}};
}

nlohmann::json to_json(const ServoResult& r) {
  const client::ClientCounters& c = r.counters;
  return {{"rtt_us", to_json(summarize_rtt(r.rtt_us))},
          {"late_fraction", r.late_fraction()},
          {"loss_fraction", r.loss_fraction()},
          {"force_n", {{"max", r.force_max_n}, {"rms", r.force_rms_n}}},
          {"passivity_energy_j", r.passivity_energy_j},
          {"penetration_mm_max", 1e3 * r.penetration_max_m},
          {"force_rate_max_n_per_s", r.force_rate_max_n_per_s},
          {"rate_hz_achieved", r.rate_hz_achieved},
          {"elapsed_s", r.elapsed_s},
          {"ticks", r.ticks},
          {"missed_ticks", r.missed_ticks},
          {"samples_sent", r.samples_sent},
          {"send_failures", r.send_failures},
          {"replies", r.replies},
          {"late", r.late},
          {"lost", r.lost},
          {"contact_fraction", r.contact_fraction()},
          {"clamped_replies", r.clamped_replies},
          {"stale_replies", r.stale_replies},
          {"faded_ticks", r.faded_ticks},
          {"client",
           {{"forces_stale_dropped", c.forces_stale},
            {"datagrams_rejected", c.datagrams_rejected},
            {"datagrams_unexpected", c.datagrams_unexpected},
            {"refused", c.refused},
            {"datagrams_unauthenticated", c.datagrams_unauthenticated}}}};
}

nlohmann::json glove_figures_to_json(const GloveSimulation& sim) {
  constexpr double kDegPerRad = 180.0 / std::numbers::pi;
  nlohmann::json fingers = nlohmann::json::object();
  for (int f = 0; f < hand::kHandFingers; ++f) {
    const GloveGroupFigures g = sim.group_figures(f);
    fingers[hand::finger_name(f)] = {{"force_n", {{"max", g.force_max_n}, {"rms", g.force_rms_n}}},
                               {"contact_fraction", g.contact_fraction},
                               {"joint_lag_deg_max", kDegPerRad * g.joint_lag_max_rad}};
  }
  const GloveGroupFigures palm = sim.group_figures(kPalmGroup);
  return {{"fingers", fingers},
          {"palm",
           {{"force_n", {{"max", palm.force_max_n}, {"rms", palm.force_rms_n}}},
            {"contact_fraction", palm.contact_fraction}}}};
}

nlohmann::json to_json(const protocol::Stats& s) {
  return {{"packets_in", s.packets_in},
          {"packets_out", s.packets_out},
          {"packets_dropped", s.packets_dropped},
          {"clamps", s.clamps},
          {"resets", s.resets},
          {"overruns", s.overruns},
          {"tick_compute_p50_us", s.tick_compute_p50_us},
          {"tick_compute_p99_us", s.tick_compute_p99_us},
          {"tick_jitter_p99_us", s.tick_jitter_p99_us},
          {"visual_step_median_ms", s.visual_step_median_ms},
          {"haptic_rate_hz", s.haptic_rate_hz},
          {"visual_rate_hz", s.visual_rate_hz},
          {"sessions_active", s.sessions_active},
          {"passivity_energy_j", s.passivity_energy_j},
          {"passivity_damped_j", s.passivity_damped_j},
          {"passivity_actions", s.passivity_actions}};
}

}  // namespace hapticd::sim
