#pragma once
// The scripted interaction of the hand demo and `haptic-bench hand`: a procedural
// hand lying on a static floor, pressed into it by its handle(s) and stroked
// sideways. Every handle target moves by the same rigid offset.
#include <memory>

#include "hand_models/hand_model.hpp"
#include "hand_models/procedural_handles.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {

struct PressScenarioOptions {
  int target_tets = 1700;
  int handles = 1;
  double press_depth_m = 0.01;  // how far the targets go below the touching pose
  double press_time_s = 0.5;
  double stroke_amplitude_m = 0.02;
  double stroke_period_s = 2.0;
};

struct PressScenario {
  std::unique_ptr<HandModel> model;
  HandState state;
  ProceduralHand hand;
  PressScenarioOptions options;
  // Sets every handle's target for simulated time t (s).
  void drive(double t);
};

PressScenario make_press_scenario(const PressScenarioOptions& options, HandConfig config = {});

}  // namespace hapticd::hand
