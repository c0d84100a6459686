// How the visual loop takes the haptic proxies as its handles' targets: from the time they are of
// (ProxyTargets::t_ns, the end of the haptic tick that integrated them), extrapolated to the
// moment its model will be published. Taking them as of the moment they are read instead, as it
// once did, runs the world up to one haptic period ahead of the proxies and puts energy into the
// device (test_loops_offline.cpp, OfflineOptions::targets_one_tick_stale: +6.8 % of the work).
#include <gtest/gtest.h>

#include <cmath>
#include <thread>

#include "haptic_server_test_util.hpp"
#include "server/haptic/visual_loop.hpp"

namespace hapticd {
namespace {

ProxyTargets moving_proxy(std::uint64_t t_ns) {
  ProxyTargets t;
  t.t_ns = t_ns;
  t.driven[0] = true;
  t.pose[0][1].p_W = {0.1, 0.2, 0.3};
  t.v_W[0][1] = {0.1, 0.0, -0.2};
  t.w_W[0][1] = {0.0, 0.0, 2.0};
  return t;
}

TEST(VisualLoopTargets, AProxyIsExtrapolatedFromTheTimeItIsOfToThePublication) {
  const std::uint64_t t = 5'000'000'000ull;
  const ProxyTargets targets = moving_proxy(t);
  // Published 3 ms after the proxies' time: 3 ms of their motion ahead.
  HandleTarget h = proxy_target(targets, 0, 1, t + 3'000'000);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.1003, 0.2, 0.2994)).norm(), 0.0, 1e-12);
  EXPECT_NEAR(h.q_W.angularDistance(Eigen::Quaterniond(Eigen::AngleAxisd(0.006, Eigen::Vector3d::UnitZ()))), 0.0,
              1e-12);
  EXPECT_EQ(h.v_W, targets.v_W[0][1]);
  EXPECT_EQ(h.w_W, targets.w_W[0][1]);
  // Proxies of the end of a tick still running (0.4 ms after the publication): taken back 0.4 ms.
  h = proxy_target(targets, 0, 1, t - 400'000);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.09996, 0.2, 0.30008)).norm(), 0.0, 1e-12);
  // Proxies left by a stalled haptic thread 2 s ago: at most 0.1 s of extrapolation.
  h = proxy_target(targets, 0, 1, t + 2'000'000'000ull);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.11, 0.2, 0.28)).norm(), 0.0, 1e-12);
}

TEST(VisualLoopTargets, TheServerStampsItsProxiesWithTheEndOfTheTickThatWroteThem) {
  test::RunningServer s(ServerOptions{}, false);
  test::TestClient c(s.server.port());
  ASSERT_NE(c.hello(), 0u);
  std::uint64_t seq = 0;
  for (int k = 0; k < 50; ++k) {
    c.press(0.0, ++seq);
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  int checked = 0;
  for (int k = 0; k < 200; ++k) {
    if (!s.targets.update()) {
      std::this_thread::sleep_for(std::chrono::microseconds(300));
      continue;
    }
    const std::uint64_t read = protocol::now_ns();
    const ProxyTargets& t = s.targets.front();
    ASSERT_TRUE(t.driven[0]);
    // Written by a tick that started at most a few periods ago (a loaded machine delays this
    // thread, not the stamp), and of the end of that tick: never more than one period ahead.
    EXPECT_LE(t.t_ns, read + 1'000'000) << "the proxies are of a time past the end of their tick";
    EXPECT_GE(t.t_ns + 20'000'000, read) << "the proxies' time is not their tick's";
    ++checked;
  }
  EXPECT_GT(checked, 20);
}

}  // namespace
}  // namespace hapticd
