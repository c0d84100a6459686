#pragma once
// The perturbed runs the glove tests' comments cite (OfflineOptions::model_stiffness_scale): every
// model's K scaled by HAPTICD_STIFFNESS_SCALE when it is set, e.g. 1.000001; a value that is not a
// positive number fails the test instead of scaling by zero.
#include <gtest/gtest.h>

#include <cstdlib>

#include "server/offline/offline_run.hpp"

namespace hapticd::offline {

inline void apply_stiffness_scale_from_env(OfflineOptions& options) {
  const char* scale = std::getenv("HAPTICD_STIFFNESS_SCALE");
  if (!scale) return;
  options.model_stiffness_scale = std::strtod(scale, nullptr);
  EXPECT_GT(options.model_stiffness_scale, 0.0) << "HAPTICD_STIFFNESS_SCALE=" << scale << " is not a scale";
}

}  // namespace hapticd::offline
