#pragma once
// Shared by the haptic tests that press on a world: the shipped stylus scene with one static box
// under the hand instead of its objects (top face 1 cm below the hand's lowest point).
#include <string>

#include "server/world/scene_loader.hpp"

namespace hapticd::test {

inline world::SceneDesc static_box_scene() {
  world::SceneDesc scene = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  scene.objects.clear();
  world::ObjectDesc box;
  box.name = "box";
  box.kind = world::BodyKind::static_body;
  box.shape.type = world::ShapeType::box;
  box.shape.size = {0.3, 0.3, 0.04};
  box.pose.p_W = {0.08, 0.1, 0.847};
  scene.objects.push_back(box);
  return scene;
}

}  // namespace hapticd::test
