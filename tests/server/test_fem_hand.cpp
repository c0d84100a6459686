// The FEM hand behind the Hand interface (hand_models/hand.hpp), as the world builds it: what the
// interface reports against the procedural hand it was built from.
#include <gtest/gtest.h>

#include <string>

#include "hand_models/fem_hand.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::world {
namespace {

TEST(FemHand, SkinPointsAreTheRestSkinPlacedByTheScenePoseAndCarryTheirHandles) {
  const SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json");
  const World world(scene);
  const hand::FemHand& fem = hand::as_fem(world.hand(0));
  const hand::Hand& hand = fem;
  EXPECT_EQ(hand.model_name(), "fem");
  ASSERT_EQ(hand.num_skin_points(), static_cast<int>(fem.shape.skin_vertices.size()));
  ASSERT_GT(hand.num_skin_points(), 100);
  // Before any step the flesh is its rest shape moved rigidly by the scene's hand pose, and a skin
  // vertex's barycentric weights in its tet reproduce it exactly.
  const Pose& pose = scene.hands[0].pose;
  double worst = 0;
  for (int i = 0; i < hand.num_skin_points(); ++i)
    worst =
        std::max(worst, (hand.skin_point(i) - (pose.p_W + pose.q_W.normalized() * fem.shape.skin_vertices[i])).norm());
  EXPECT_LT(worst, 1e-12);
  // 16 handles (phalanges): every skin point on some handle, every handle with skin.
  ASSERT_EQ(hand.num_handles(), 16);
  std::vector<int> count(16, 0);
  for (int i = 0; i < hand.num_skin_points(); ++i) {
    const int j = hand.skin_handle(i);
    ASSERT_GE(j, 0);
    ASSERT_LT(j, 16);
    ++count[static_cast<std::size_t>(j)];
  }
  for (int j = 0; j < 16; ++j) EXPECT_GT(count[static_cast<std::size_t>(j)], 0) << "handle " << j;
  EXPECT_EQ(hand.skin_handle(-1), -1);
  EXPECT_EQ(hand.skin_handle(hand.num_skin_points()), -1);
}

}  // namespace
}  // namespace hapticd::world
