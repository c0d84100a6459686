// How the visual loop takes the haptic proxies as its handles' targets: from the time they are of
// (ProxyTargets::t_ns, the end of the haptic tick that integrated them), extrapolated to the
// moment its model will be published. Taking them as of the moment they are read instead, as it
// once did, runs the world up to one haptic period ahead of the proxies and puts energy into the
// device (test_loops_offline.cpp, OfflineOptions::targets_one_tick_stale: +6.8 % of the work).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <new>
#include <thread>

#include "box_scene.hpp"
#include "hand_models/fem_hand.hpp"
#include "haptic_server_test_util.hpp"
#include "server/haptic/visual_loop.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::haptic {
namespace {

ProxyTargets moving_proxy(std::uint64_t t_ns) {
  ProxyTargets t;
  t.t_ns = t_ns;
  t.driven[0] = true;
  t.pose[0][1].p_W = {0.1, 0.2, 0.3};
  t.v_W[0][1] = {0.1, 0.0, -0.2};
  t.w_W[0][1] = {0.0, 0.0, 2.0};
  t.v_device_W[0][1] = {0.05, 0.0, -0.3};  // the device: the proxy lags it, pushed by a model
  t.w_device_W[0][1] = {0.0, 1.0, 0.0};
  return t;
}

// The visual loop's timing (detail::StepClock, which VisualLoop::run uses) on made-up times: a loop
// whose iterations take 5 ms at 60 Hz, one of them descheduled for 300 ms (a busy machine). Its world
// falls 0.3 s behind the clock; the steps catch that up, each the period plus half the lag, and come
// back to the period (to 1 %) within 20 iterations; from the second model after the stall on, every model
// reaches the haptic loop before the one before it has ended. Measured before the loop published at
// its pace rather than at its step's end: the lag never shrank and every step stayed at kMaxStep_s
// (150 ms) for the rest of the session (hapticd with a 300 ms stall injected into its visual
// thread: 6.7 Hz after it); and the stalled iteration's 300 ms, taken as the loop's latency, had it
// publish up to 0.3 s ahead of its reads for 1.5 s.
TEST(StepClock, AfterAStallTheWorldCatchesUpAndTheStepsComeBackToThePeriod) {
  const double period = 1.0 / 60, compute = 0.005, stall = 0.3;
  const int stalled = 60;
  const std::uint64_t start = 1'000'000'000ull;
  const auto ns = [](double s) { return static_cast<std::uint64_t>(1e9 * s); };
  detail::StepClock clock(period, start);
  std::uint64_t t = start, last_end = 0;
  double last_dt = period;
  int back_at = -1, gaps_after = 0;
  double longest = 0, latest_publish_ahead = 0;
  for (int i = 0; i < 240; ++i) {
    const std::uint64_t t0 = t, publish = clock.publish_ns(t0);
    const double taken = clock.world_step_s(publish);
    if (i == stalled + 1) {
      EXPECT_NEAR(taken, detail::kMaxStep_s, 1e-9);  // the step after the stall spans what it can of it
    } else if ((i >= 10 && i <= stalled) || back_at >= 0) {
      EXPECT_NEAR(taken, last_dt, 1e-9) << i;  // otherwise the step its model was built for
    } else if (i > stalled) {
      EXPECT_GE(taken, last_dt) << i;  // or longer while a period or more is to catch up
      EXPECT_LE(taken, detail::kMaxStep_s) << i;
    }
    const double dt = clock.plan(publish);
    const double took = compute + (i == stalled ? stall : 0.0);
    const std::uint64_t arrives = t0 + ns(took);
    longest = std::max(longest, dt);
    if (i > stalled) latest_publish_ahead = std::max(latest_publish_ahead, 1e-9 * static_cast<double>(publish - t0));
    if (i < stalled && i >= 10) {  // steady before it (the latency estimate starts at zero)
      EXPECT_NEAR(dt, period, 1e-9) << i;
      EXPECT_LE(arrives, last_end) << i;
    }
    if (i > stalled + 1) gaps_after += arrives > last_end;
    const bool at_period = std::abs(dt - period) < 0.01 * period && std::abs(clock.lag_s()) < 1e-3;
    if (i > stalled && back_at < 0 && at_period) back_at = i - stalled;
    if (back_at >= 0) {
      EXPECT_TRUE(at_period) << "iteration " << i << ": step " << dt << " s, lag " << clock.lag_s();
    }
    last_end = publish + ns(dt);
    last_dt = dt;
    clock.measured(took);
    t = std::max(arrives, clock.next_read_ns(publish));
  }
  std::printf(
      "a %.0f ms stall: the steps back at the period %d iterations after it, the longest %.0f ms; "
      "published at most %.1f ms ahead of a read after it; %d models after it came after the last ended\n",
      1e3 * stall, back_at, 1e3 * longest, 1e3 * latest_publish_ahead, gaps_after);
  EXPECT_GE(back_at, 1);
  EXPECT_LE(back_at, 20);  // a third of a second at 60 Hz
  EXPECT_LE(longest, detail::kMaxStep_s);
  EXPECT_LE(latest_publish_ahead, 0.05);
  EXPECT_EQ(gaps_after, 0);
}

TEST(VisualLoopTargets, AProxyIsExtrapolatedFromTheTimeItIsOfToThePublication) {
  const std::uint64_t t = 5'000'000'000ull;
  const ProxyTargets targets = moving_proxy(t);
  // Published 3 ms after the proxies' time: 3 ms of their motion ahead.
  hand::HandleTarget h = proxy_target(targets, 0, 1, t + 3'000'000);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.1003, 0.2, 0.2994)).norm(), 0.0, 1e-12);
  EXPECT_NEAR(h.q_W.angularDistance(Eigen::Quaterniond(Eigen::AngleAxisd(0.006, Eigen::Vector3d::UnitZ()))), 0.0,
              1e-12);
  EXPECT_EQ(h.v_W, targets.v_W[0][1]);
  EXPECT_EQ(h.w_W, targets.w_W[0][1]);
  // The device's own motion passes as it is (HandleTarget::v_device_W).
  EXPECT_EQ(h.v_device_W, targets.v_device_W[0][1]);
  EXPECT_EQ(h.w_device_W, targets.w_device_W[0][1]);
  // Proxies of the end of a tick still running (0.4 ms after the publication): taken back 0.4 ms.
  h = proxy_target(targets, 0, 1, t - 400'000);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.09996, 0.2, 0.30008)).norm(), 0.0, 1e-12);
  // Proxies left by a stalled haptic thread 2 s ago: at most 0.1 s of extrapolation.
  h = proxy_target(targets, 0, 1, t + 2'000'000'000ull);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.11, 0.2, 0.28)).norm(), 0.0, 1e-12);
}

TEST(VisualLoopTargets, TheExtrapolationStopsAtTheHandlesClearancePlanes) {
  const std::uint64_t t = 5'000'000'000ull;
  const ProxyTargets targets = moving_proxy(t);
  // The handle 2 mm above where the proxy is; a floor 1 cm under the handle (a skin point 5 mm below
  // it, 5 mm above the floor), and a wall far to the +x side. 100 ms ahead the proxy would be 2 cm
  // lower: the floor's plane leaves 5 mm - 2 mm = 3 mm of it, a share of 0.15 of the motion.
  hand::HandleState from;
  from.p_WH = {0.1, 0.2, 0.302};
  hand::ClearancePlane planes[2];
  planes[0] = {Eigen::Vector3d::UnitZ(), Eigen::Vector3d(0, 0, -0.005), 0.005};
  planes[1] = {-Eigen::Vector3d::UnitX(), Eigen::Vector3d::Zero(), 0.5};
  hand::HandleTarget h = proxy_target(targets, 0, 1, t + 100'000'000, &from, planes, 2);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.1 + 0.15 * 0.01, 0.2, 0.3 - 0.003)).norm(), 0.0, 1e-12);
  EXPECT_NEAR((h.v_W - 0.15 * targets.v_W[0][1]).norm(), 0.0, 1e-12);
  EXPECT_NEAR((h.w_W - 0.15 * targets.w_W[0][1]).norm(), 0.0, 1e-12);
  // The planes bound where the world takes the hand, not what the device is doing.
  EXPECT_EQ(h.v_device_W, targets.v_device_W[0][1]);
  // Moving away from the floor the planes leave it alone; a proxy already past a plane only comes back.
  ProxyTargets rising = targets;
  rising.v_W[0][1].z() = 0.2;
  h = proxy_target(rising, 0, 1, t + 100'000'000, &from, planes, 2);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.11, 0.2, 0.32)).norm(), 0.0, 1e-12);
  from.p_WH.z() = 0.31;  // the proxy 1 cm below the handle: past the floor's 5 mm
  h = proxy_target(targets, 0, 1, t + 100'000'000, &from, planes, 2);
  EXPECT_NEAR((h.p_W - targets.pose[0][1].p_W).norm(), 0.0, 1e-12);
}

TEST(VisualLoopTargets, TheExtrapolationStopsWhereTheSkinWouldLeaveWhereThePlanesLooked) {
  const std::uint64_t t = 5'000'000'000ull;
  const ProxyTargets targets = moving_proxy(t);
  // The proxy 9 cm along x from the handle, unturned, its skin reaching 2 cm: 1 cm of the 10 cm
  // (hand::kClearanceLook_m) left. 100 ms ahead it would move (1, 0, -2) cm and turn 0.2 rad, which
  // uses sqrt(5) cm + 2 cm x 0.2 of it (the bound's rate): a share of 1 / (sqrt(5) + 0.4).
  hand::HandleState from;
  from.p_WH = {0.01, 0.2, 0.3};
  hand::HandleTarget h = proxy_target(targets, 0, 1, t + 100'000'000, &from, nullptr, 0, 0.02);
  const double share = 1.0 / (std::sqrt(5.0) + 0.4);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.1 + share * 0.01, 0.2, 0.3 - share * 0.02)).norm(), 0.0, 1e-12);
  EXPECT_NEAR((h.w_W - share * targets.w_W[0][1]).norm(), 0.0, 1e-12);
  // With 5 cm of it left the whole extrapolation fits; without the skin's extent nothing is bounded.
  from.p_WH = {0.05, 0.2, 0.3};
  h = proxy_target(targets, 0, 1, t + 100'000'000, &from, nullptr, 0, 0.02);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.11, 0.2, 0.28)).norm(), 0.0, 1e-12);
  from.p_WH = {-0.2, 0.2, 0.3};
  h = proxy_target(targets, 0, 1, t + 100'000'000, &from);
  EXPECT_NEAR((h.p_W - Eigen::Vector3d(0.11, 0.2, 0.28)).norm(), 0.0, 1e-12);
  // A proxy already beyond the bound only comes back toward the handle.
  h = proxy_target(targets, 0, 1, t + 100'000'000, &from, nullptr, 0, 0.02);
  EXPECT_NEAR((h.p_W - targets.pose[0][1].p_W).norm(), 0.0, 1e-12);
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

// How far below its start the pressing client holds the stylus at t (device space): at the handle
// for 0.2 s, then 1.5 cm down (3 cm in the world, the palm into the box) over 0.5 s, then held.
double press_depth_m(double t_s) { return 0.015 * std::clamp((t_s - 0.2) / 0.5, 0.0, 1.0); }

// hapticd's two real-time runners on their threads (HapticServer, VisualLoop around a VisualStep), on
// test::static_box_scene().
struct Threads {
  explicit Threads(double visual_hz = 60, const ServerOptions& options = {}) {
    world::SceneDesc scene = test::static_box_scene();
    scene.visual_rate_hz = visual_hz;
    scene.dt_s = 1.0 / visual_hz;
    world = std::make_unique<world::World>(scene, served_world_options());
    link = make_device_link(*world, scene.devices[0], 1000.0);
    server = std::make_unique<HapticServer>(std::vector<DeviceLink>{link}, options, *snapshots, *targets, &report);
    preparer = std::make_unique<TickSolverPreparer>(std::vector<DeviceLink>{link}, 1e-3);
    step = std::make_unique<VisualStep>(*world, *snapshots, *targets, preparer.get());
    step->build_models(protocol::now_ns(), 1.0 / visual_hz);
    step->publish();
    loop = std::make_unique<VisualLoop>(*step, visual_hz, &report, [this](const std::string&) { ++logged; });
    const hand::HandleState& h = hand::as_fem(world->hand(0)).state.handles[0];
    Eigen::Quaterniond q;
    link.map.to_device(0, {h.p_WH, h.q_WH}, start_D, q);
  }
  void start() {
    haptic = std::thread([this] { server->run(stop); });
    visual = std::thread([this] { loop->run(stop); });
  }
  void halt() {
    stop = true;
    if (haptic.joinable()) haptic.join();
    if (visual.joinable()) visual.join();
  }
  ~Threads() { halt(); }

  std::unique_ptr<TripleBuffer<HapticSnapshot>> snapshots = std::make_unique<TripleBuffer<HapticSnapshot>>();
  std::unique_ptr<TripleBuffer<ProxyTargets>> targets = std::make_unique<TripleBuffer<ProxyTargets>>();
  VisualReport report;
  std::unique_ptr<world::World> world;
  DeviceLink link;
  std::unique_ptr<HapticServer> server;
  std::unique_ptr<TickSolverPreparer> preparer;
  std::unique_ptr<VisualStep> step;
  std::unique_ptr<VisualLoop> loop;
  std::atomic<bool> stop{false};
  std::atomic<int> logged{0};
  std::thread haptic, visual;
  Eigen::Vector3d start_D = Eigen::Vector3d::Zero();  // the device pose that carries the handle where it is
};

// One reply of a press, with its time since the client started.
struct Reply {
  double t_s = 0, f_z = NAN;
  bool stale = false, answered = false;
};

// A stylus client at 1 kHz (paced by its round trips) pressing as press_depth_m says until `seconds`.
std::vector<Reply> press_and_hold(Threads& t, double seconds) {
  test::TestClient c(t.server->port());
  EXPECT_NE(c.hello(), 0u);
  std::vector<Reply> out;
  const std::uint64_t t0 = protocol::now_ns();
  for (std::uint64_t seq = 1;; ++seq) {
    const double now = 1e-9 * static_cast<double>(protocol::now_ns() - t0);
    if (now > seconds) break;
    protocol::PoseSample p = c.pose_at(0, seq);
    const double down = press_depth_m(now);
    p.poses[0].position_m = {static_cast<float>(t.start_D.x()), static_cast<float>(t.start_D.y()),
                             static_cast<float>(t.start_D.z() - down)};
    c.send(p);
    const protocol::Message m = c.receive();
    Reply r;
    r.t_s = now;
    r.answered = m.type == protocol::MessageType::kForceSample && m.force_sample.sequence == seq;
    if (r.answered) {
      r.f_z = m.force_sample.wrenches[0].wrench.force_n.z;
      r.stale = m.force_sample.flags & protocol::ForceFlags::kStale;
    }
    out.push_back(r);
    std::this_thread::sleep_for(std::chrono::microseconds(900));
  }
  return out;
}

TEST(VisualLoopThreads, TheRealTimeRunnersServeAPressOnTheWorldWithFreshModels) {
  Threads t;
  t.start();
  const std::vector<Reply> replies = press_and_hold(t, 1.5);
  t.halt();
  long unanswered = 0, stale_late = 0;
  double f_hold = 0;
  int held = 0;
  for (const Reply& r : replies) {
    unanswered += !r.answered;
    if (r.t_s > 1.0 && r.answered) stale_late += r.stale, f_hold += r.f_z, ++held;
  }
  ASSERT_GT(held, 100);
  f_hold /= held;
  std::printf("%zu poses, %ld unanswered; held force %.3f N; visual %ld steps (%.1f Hz), %ld late\n", replies.size(),
              unanswered, f_hold, t.loop->stats().steps, t.report.rate_hz.load(), t.loop->stats().late_steps);
  EXPECT_EQ(unanswered, 0);
  EXPECT_EQ(stale_late, 0) << "models stopped flowing while the visual loop ran";
  EXPECT_GT(f_hold, 0.3) << "the box does not push the stylus back up";
  EXPECT_GT(t.loop->stats().steps, 30);  // 60 Hz for 1.5 s: 90 on time, fewer on a loaded machine
  EXPECT_EQ(t.loop->stats().faults, 0);
  EXPECT_GT(t.report.rate_hz.load(), 15.0);
}

TEST(VisualLoopThreads, AThrowInTheWorldStepIsAFaultTheServerKeepsAnsweringAndFadesToTheSafeModel) {
  // While the press is held (from 1.2 s) the world step throws (an allocation fails) for 0.6 s, then
  // works again. The box's surfaces stay felt for 0.1 s past the model's fade (the default 0.5 s would
  // outlast the faults).
  ServerOptions o;
  o.model_contacts_hold_s = 0.1;
  Threads t(60, o);
  std::atomic<std::uint64_t> first_ns{0}, last_ns{0};
  const std::uint64_t t0 = protocol::now_ns();
  t.step->set_fault_injection([&] {
    const std::uint64_t now = protocol::now_ns();
    if (now < t0 + 1'200'000'000ull || now > t0 + 1'800'000'000ull) return;
    if (!first_ns) first_ns = now;
    last_ns = now;
    throw std::bad_alloc();
  });
  t.start();
  const std::vector<Reply> replies = press_and_hold(t, 3.0);
  t.halt();
  ASSERT_NE(first_ns.load(), 0u) << "no fault was injected";
  const double fault_from = 1e-9 * static_cast<double>(first_ns - t0),
               fault_to = 1e-9 * static_cast<double>(last_ns - t0);
  // The safe model is reached within the watchdog's delay, the surfaces' hold and the fade, plus a
  // visual period for the last good model's step to end.
  const double safe_by =
      fault_from + o.model_stale_after_s + o.model_contacts_hold_s + o.model_fade_s + 1.0 / 60 + 0.02;
  long unanswered = 0, not_stale = 0, safe_samples = 0;
  double f_before = 0, f_safe_max = 0, f_after_max = 0;
  int before = 0;
  for (const Reply& r : replies) {
    unanswered += !r.answered;
    if (!r.answered) continue;
    if (r.t_s > fault_from - 0.2 && r.t_s < fault_from) f_before += r.f_z, ++before;
    if (r.t_s > safe_by && r.t_s < fault_to) {
      ++safe_samples;
      not_stale += !r.stale;
      f_safe_max = std::max(f_safe_max, std::abs(r.f_z));
    }
    if (r.t_s > fault_to) f_after_max = std::max(f_after_max, std::abs(r.f_z));
  }
  ASSERT_GT(before, 50);
  f_before /= before;
  std::printf(
      "faults %ld (logged %d) from %.2f to %.2f s; force before %.3f N, max while safe %.4f N, max after %.3f N\n",
      t.loop->stats().faults, t.logged.load(), fault_from, fault_to, f_before, f_safe_max, f_after_max);
  EXPECT_EQ(unanswered, 0) << "the server stopped answering while the visual step failed";
  EXPECT_GT(t.loop->stats().faults, 10);
  EXPECT_EQ(t.loop->stats().faults, t.logged.load());
  ASSERT_GT(f_before, 0.3) << "the stylus was not pressing before the faults";
  ASSERT_GT(safe_samples, 100);
  EXPECT_EQ(not_stale, 0) << "replies under the safe model must be flagged stale";
  // The safe model holds the proxy on the device: the device feels (almost) nothing.
  EXPECT_LT(f_safe_max, 0.05 * f_before);
  // Steps succeed again: the press is felt again, without a spike above the force before.
  EXPECT_GT(replies.back().f_z, 0.5 * f_before);
  EXPECT_FALSE(replies.back().stale);
  EXPECT_LT(f_after_max, 1.5 * f_before);
}

TEST(VisualLoopThreads, TheRealTimeAndTheLockstepRunnersRenderTheSamePress) {
  // The same press, once through hapticd's threads on the wall clock and once through the lockstep
  // runner on simulated time (the world every 17 ms, as 60 Hz). Both drive the same HapticCore and
  // VisualStep, so they must render the same force; only the threads' timing (the visual loop's
  // achieved rate and phase, the client's pacing) differs, so the traces agree to a tolerance: the
  // held force within 2 %, the whole trace within 10 % RMS of the held force.
  Threads t;
  t.start();
  const std::vector<Reply> threaded = press_and_hold(t, 2.0);
  t.halt();

  offline::OfflineOptions options;
  options.visual_every_ticks = 17;
  offline::OfflineLoops loops(test::static_box_scene(), options);
  Eigen::Vector3d start_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  EXPECT_LT((start_D - t.start_D).norm(), 1e-12) << "the two runners' hands start apart";
  std::vector<offline::DeviceFrames> poses(2000);
  for (std::size_t k = 0; k < poses.size(); ++k) {
    poses[k].frames = 1;
    poses[k].p_D[0] = start_D - Eigen::Vector3d(0, 0, press_depth_m(1e-3 * static_cast<double>(k)));
    poses[k].q_D[0].setIdentity();
  }
  offline::RecordedDevice device(poses);
  const offline::OfflineTrace lockstep = offline::run_offline(loops, device, static_cast<long>(poses.size()));

  auto held = [](auto time_of, auto force_of, std::size_t n) {
    double sum = 0;
    int count = 0;
    for (std::size_t k = 0; k < n; ++k)
      if (time_of(k) > 1.2) sum += force_of(k), ++count;
    return sum / std::max(count, 1);
  };
  const double f_threaded = held([&](std::size_t k) { return threaded[k].t_s; },
                                 [&](std::size_t k) { return threaded[k].f_z; }, threaded.size());
  const double f_lockstep =
      held([](std::size_t k) { return 1e-3 * static_cast<double>(k); },
           [&](std::size_t k) { return lockstep.replies[k].wrench[0].f_D.z(); }, lockstep.replies.size());
  double sq = 0;
  int n = 0;
  for (const Reply& r : threaded) {
    if (!r.answered || r.t_s >= 1.999) continue;
    const auto k = static_cast<std::size_t>(std::lround(1e3 * r.t_s));
    sq += std::pow(r.f_z - lockstep.replies[k].wrench[0].f_D.z(), 2);
    ++n;
  }
  const double rms_diff = std::sqrt(sq / std::max(n, 1));
  std::printf("held force: threaded %.4f N, lockstep %.4f N; RMS difference over the trace %.4f N (%d samples)\n",
              f_threaded, f_lockstep, rms_diff, n);
  ASSERT_GT(f_lockstep, 0.3) << "the box does not push back";
  EXPECT_NEAR(f_threaded, f_lockstep, 0.02 * f_lockstep);
  EXPECT_LT(rms_diff, 0.1 * f_lockstep);
  EXPECT_EQ(lockstep.resets, 0);
}

}  // namespace
}  // namespace hapticd::haptic
