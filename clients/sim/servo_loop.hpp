#pragma once

// The device's servo loop, shared by haptic-device (stylus and glove) and `haptic-bench latency`:
// at a fixed rate on absolute CLOCK_MONOTONIC deadlines, each tick
//   1. steps the simulated device under the wrenches last received (ServoDevice::advance),
//   2. sends its frames' poses (ServoDevice::write_pose, Client::send_pose),
//   3. waits for its ForceSample until the end of the period; replies to earlier poses met on the
//      way are applied too (the newest wrenches are the ones a device would render).
// The wrenches held fade out when no reply has come for ServoConfig::watchdog's hold (a stalled or
// dead server must not leave a motor pushing) and come back when replies do (client::ReplyWatchdog).
// A reply that arrives after its pose's period ended is late; a pose never answered is lost (a
// reply overtaken by a newer one is dropped as stale by the Client, so it counts as lost: an old
// force is never applied). A tick whose whole period passed before the loop woke up is missed:
// the tip is still stepped, no pose is sent.

#include <atomic>
#include <cstdint>
#include <vector>

#include "clients/cpp/client.hpp"
#include "clients/cpp/reply_watchdog.hpp"
#include "clients/sim/device_model.hpp"
#include "clients/sim/trajectory.hpp"

namespace hapticd::sim {

// One tick as the device saw it, for --trace: time, commanded and actual tip, the force held.
struct TraceRow {
  double t_s = 0.0;
  Vec3d p_DC_m;
  Vec3d p_DT_m;
  Vec3d v_DT_m_s;
  Vec3d f_DT_N;
  bool in_contact = false;
  bool sent = false;  // false: a missed tick
};

struct ServoConfig {
  double rate_hz = 1000.0;  // use the Welcome's negotiated rate
  double duration_s = 10.0;
  DeviceParams device;                      // the stylus only
  std::uint16_t frame_id = 0;               // the stylus only: the Hello's frame the tip pose is sent as
  double drain_s = 0.1;                     // after the last tick, how long outstanding replies may still arrive
  client::ReplyWatchdogOptions watchdog;    // a silent server's held wrenches fade out (reply_watchdog.hpp)
  const std::atomic<bool>* stop = nullptr;  // set from elsewhere (a signal) to end early
  // The stylus only: when set, one row per tick is appended (reserved by run_servo_loop before the
  // first tick).
  std::vector<TraceRow>* trace = nullptr;
};

struct ServoResult {
  std::uint64_t ticks = 0;         // periods run, sent or missed
  std::uint64_t missed_ticks = 0;  // woke up after the period had ended: nothing sent
  std::uint64_t samples_sent = 0;
  std::uint64_t send_failures = 0;  // send_pose() other than kSent
  std::uint64_t replies = 0;        // poses answered (each at most once)
  std::uint64_t late = 0;           // answered after the end of their period (included in replies)
  std::uint64_t lost = 0;           // samples_sent - replies
  std::uint64_t contact_ticks = 0;  // ticks whose latest reply reported InContact (any frame)
  std::uint64_t clamped_replies = 0;
  std::uint64_t stale_replies = 0;  // replies flagged Stale by the server (no fresh snapshot)
  // Ticks that rendered less than the wrenches held: the server had been silent past the
  // watchdog's hold (or the fade was coming back up).
  std::uint64_t faded_ticks = 0;
  std::vector<double> rtt_us;       // one per reply, in arrival order
  double force_max_n = 0.0;
  double force_rms_n = 0.0;
  double passivity_energy_j = 0.0;
  double penetration_max_m = 0.0;
  // The fastest change of any frame's force between replies to consecutive poses, |f_k - f_k-1| over
  // the server's time between the two poses' arrivals (server_receive_ns; at least 0.1 ms, the
  // server's shortest slew interval): at most the Welcome's max_force_rate_n_per_s.
  double force_rate_max_n_per_s = 0.0;
  double elapsed_s = 0.0;  // first tick to the end of the last period
  double rate_hz_achieved = 0.0;
  client::ClientCounters counters;

  [[nodiscard]] double late_fraction() const noexcept;
  [[nodiscard]] double loss_fraction() const noexcept;
  [[nodiscard]] double contact_fraction() const noexcept;
};

// The simulated device the loop drives. The loop calls begin() once, then per tick advance()
// (except the first), write_pose() when the tick is not missed, apply() for each reply accepted and
// end_tick(); summarize() after the last. Only begin() and summarize() may allocate.
class ServoDevice {
 public:
  virtual ~ServoDevice() = default;
  // Before the first tick, with the number of ticks the run will have: reserve what it needs.
  virtual void begin(std::uint64_t ticks) {}
  // One period of servo_period_s(rate) under the wrenches held, times `scale` (the loop's
  // client::ReplyWatchdog: 1 while the server answers).
  virtual void advance(double scale) noexcept = 0;
  // Sets pose.poses to the poses of the device's frames now, in the Hello's frame order.
  virtual void write_pose(protocol::PoseSample& pose) noexcept = 0;
  // The newest reply: hold its wrenches until the next.
  virtual void apply(const protocol::ForceSample& sample) noexcept = 0;
  // End of a tick; sent is false for a missed tick (no pose sent).
  virtual void end_tick(bool sent) noexcept = 0;
  // The device's figures of the run: contact_ticks, force_max_n, force_rms_n, passivity_energy_j,
  // penetration_max_m.
  virtual void summarize(ServoResult& result) const = 0;
};

// The period the loop runs at for a rate (rounded to whole ns): the step a ServoDevice must take.
double servo_period_s(double rate_hz) noexcept;

// Runs the loop on the calling thread over `client`'s open session, driving `device` (built to step
// by servo_period_s(config.rate_hz)). Allocates only before the first tick (the result's buffers
// are reserved for every tick). Sets this thread's timer slack to 1 ns so that waits end at their
// deadline rather than up to 50 us after it.
ServoResult run_servo_loop(client::Client& client, ServoDevice& device, const ServoConfig& config);
// The simulated stylus (DeviceSimulation with config.device) along `trajectory`, sent as frame
// config.frame_id with the identity orientation.
ServoResult run_servo_loop(client::Client& client, const Trajectory& trajectory, const ServoConfig& config);

// Percentiles of round trips by the one definition (protocol/percentile.hpp: linear interpolation
// between order statistics).
struct RttSummary {
  double p50_us = 0.0;
  double p90_us = 0.0;
  double p99_us = 0.0;
  double p999_us = 0.0;
  double max_us = 0.0;
};
// NaN everywhere for an empty sample.
RttSummary summarize_rtt(std::vector<double> rtt_us);

}  // namespace hapticd::sim
