#include "hand_models/press_scenario.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {

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

}  // namespace hapticd::hand
