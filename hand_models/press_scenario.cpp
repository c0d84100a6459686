#include "hand_models/press_scenario.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

namespace hapticd {
namespace {

// Phalanx indices of handles 1 .. m - 1.
std::vector<int> handle_phalanges(int m) {
  if (m < 1 || m > 16) throw std::invalid_argument("handles: must be in [1, 16], got " + std::to_string(m));
  std::vector<int> order;
  if (m == 6) {
    for (int f = 0; f < 5; ++f) order.push_back(3 * f + 2);
  } else {
    for (int i = 0; i < m - 1; ++i) order.push_back(i);
  }
  return order;
}

}  // namespace

std::vector<HandFrame> procedural_handle_frames(const ProceduralHand& hand, int m) {
  std::vector<HandFrame> frames{hand.palm};
  for (int i : handle_phalanges(m)) frames.push_back(hand.phalanges[i]);
  return frames;
}

std::vector<HandleSpec> procedural_handles(const ProceduralHand& hand, int m) {
  // The palm handle grabs the palm's core (seed 004: 79 nodes at 350 tets); every
  // handle reaches at least the nearest grid nodes whatever the resolution.
  const double reach = 1.2 * hand.spacing;
  std::vector<HandleSpec> specs{{hand.palm.name, hand.palm.p, std::max({hand.palm.radius, 0.03, reach})}};
  for (int i : handle_phalanges(m))
    specs.push_back({hand.phalanges[i].name, hand.phalanges[i].p, std::max(hand.phalanges[i].radius, reach)});
  return specs;
}

PressScenario make_press_scenario(const PressScenarioOptions& options, HandConfig config) {
  PressScenario s;
  ProceduralHandOptions hand_options;
  hand_options.target_tets = options.target_tets;
  s.hand = make_procedural_hand(hand_options);
  config.handles = procedural_handles(s.hand, options.handles);
  config.material.density_kg_m3 = embedding_density(s.hand, config.material.density_kg_m3);
  double lowest = 1e300;
  for (const Eigen::Vector3d& X : s.hand.mesh.X) lowest = std::min(lowest, X.z());
  config.floor.enabled = true;
  config.floor.height_m = lowest;
  s.model = std::make_unique<HandModel>(s.hand.mesh, config);
  s.state = make_rest_state(*s.model);
  s.options = options;
  return s;
}

void PressScenario::drive(double t) {
  const double press = options.press_depth_m * std::min(1.0, t / options.press_time_s);
  const double phase = 2 * std::numbers::pi * std::max(0.0, t - options.press_time_s) / options.stroke_period_s;
  const Eigen::Vector3d offset(options.stroke_amplitude_m * std::sin(phase), 0, -press);
  for (int j = 0; j < model->num_handles(); ++j) {
    HandleTarget target;
    target.p_W = model->handles()[j].p_WH_rest + offset;
    set_target(state, j, target);
  }
}

}  // namespace hapticd
