#pragma once
// Deterministic offline mode, the lockstep runner: hapticd's own pipeline (HapticCore, VisualStep,
// the world) on simulated time, in lockstep, on one thread, without sockets. Each haptic tick of
// period T the device moves and sends its frames' poses as a PoseSample datagram, the core answers
// it with a ForceSample from the proxies and integrates them under the last published model; every
// k ticks the visual step drives the world's handles to the proxies, steps the world by k T and
// builds the model of the coming step, handed over `model_delay_ticks` later (the visual step's
// compute time). Nothing reads a clock except to time the stages: the same inputs give
// bit-identical outputs.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <functional>
#include <memory>
#include <optional>
#include <utility>
#include <vector>

#include "clients/cpp/reply_watchdog.hpp"
#include "clients/sim/device_model.hpp"
#include "clients/sim/glove_model.hpp"
#include "clients/sim/glove_simulation.hpp"
#include "protocol/codec.hpp"
#include "server/haptic/device_link.hpp"
#include "server/haptic/haptic_core.hpp"
#include "server/haptic/visual_step.hpp"
#include "server/world/world.hpp"

namespace hapticd::offline {

struct OfflineOptions {
  double haptic_period_s = 1e-3;
  // The world steps every this many haptic ticks, by that many periods (1: at
  // every tick, the reference of the multi-rate error).
  int visual_every_ticks = 17;
  // How long after its step a model reaches the haptic loop (the visual step's
  // compute time); the world then simulates up to that publication, as VisualLoop does.
  // Less than visual_every_ticks.
  int model_delay_ticks = 0;
  // A machine under load deschedules the visual thread mid-step: its model then reaches the haptic
  // loop later than the world planned (the world simulated up to the planned publication). With this
  // > 0, each step's model comes a further 0 .. late_model_max_ticks - 1 ticks late, drawn per step
  // by a generator seeded with late_model_seed (the same run every time). model_delay_ticks +
  // late_model_max_ticks <= visual_every_ticks.
  int late_model_max_ticks = 0;
  std::uint64_t late_model_seed = 12345;
  // Every model's stiffness K scaled by this before it is prepared: a perturbation far above rounding
  // (1 +- 1e-6 .. 1e-4), to tell an outcome the rendering gives from one a run happens to give
  // (the glove tests read HAPTICD_STIFFNESS_SCALE into it: tests/server/offline/stiffness_scale.hpp).
  double model_stiffness_scale = 1.0;
  // Windows [from, to) of simulated time, s, in which the device's samples never reach the server (a
  // device whose servo loop or link stalled): the core ticks on without them, and the device, sent
  // no reply, holds the last one it received. The first tick's sample always arrives.
  std::vector<std::pair<double, double>> withheld_samples_s;
  // Windows [from, to) of simulated time, s, in which the visual thread does not run (descheduled on a
  // busy machine): no visual step, and a model due meanwhile is handed over at the window's end; the
  // haptic core ticks on with the model it has, late and then faded by its watchdog. The visual steps
  // resume at the window's end, k ticks apart, the first one's world step spanning the time since the
  // last, up to haptic::detail::kMaxStep_s, as VisualLoop's; the world does not make up the rest
  // (VisualLoop lengthens its next steps to).
  std::vector<std::pair<double, double>> visual_stalls_s;
  // Windows [from, to) of simulated time, s, in which hapticd's haptic thread does not run (its core
  // descheduled on a busy machine; HapticServer::run): no tick, and the device's samples queue unread
  // while the device, sent no reply, holds the last one. At the first tick after a window the core
  // reads the queue and answers each sample in turn, then ticks late, as HapticServer::run does; the
  // device feels the answer to its newest. The visual loop runs on.
  std::vector<std::pair<double, double>> haptic_stalls_s;
  // The whole machine stopped over [from, to) (a paused virtual machine: hapticd and the device's
  // client together): the device's samples withheld, and hapticd's haptic and visual threads stopped
  // from kMachineStopSocketWait_s before, so that the device's last sample before the gap waits unread
  // in the socket and is read late, just before the first after it.
  static constexpr double kMachineStopSocketWait_s = 0.0025;
  void stop_machine(double from_s, double to_s) {
    withheld_samples_s.emplace_back(from_s, to_s);
    haptic_stalls_s.emplace_back(from_s - kMachineStopSocketWait_s, to_s);
    visual_stalls_s.emplace_back(from_s - kMachineStopSocketWait_s, to_s);
  }
  haptic::HandleModelKind model = haptic::HandleModelKind::linearized;
  int device = 0;  // the scene device served
  // Before the first tick, the scene's rigid bodies (ODE alone) settle this long
  // in steps of one haptic period. Runs at different visual rates then start
  // from the same world: a body placed a little off its rest pose otherwise
  // settles differently at each step length (the stylus scene's bunny comes to
  // rest 5 mm apart after 1 s at 1 ms and at 33 ms steps).
  double settle_s = 0;
  // The proxies a visual step reads were integrated to the end of their tick
  // (t + T, ProxyTargets::t_ns), and the world and the model's step end are timed
  // from there. True: the model's step is timed from the tick's start instead (one
  // period early), as hapticd's VisualLoop timed it before ProxyTargets carried
  // their time (the bias was up to one period, by the phase of the two threads). Measured with that bias:
  // a free-space sweep at 60 Hz puts energy into the device, and at 240 Hz the loops
  // go unstable.
  bool targets_one_tick_stale = false;
  // The sessions' passivity controller (ServerOptions::passivity_control), on as in hapticd.
  bool passivity_control = true;
  // The tick contact solve's sweeps at most (HapticCoreOptions::tick_contact_sweeps), as in hapticd.
  int tick_contact_sweeps = haptic::kDefaultTickContactSweeps;
  // The hands' contact model (WorldOptions::contact; unset: the scene's, as hapticd).
  std::optional<world::ContactModel> contact;
  // A palm-driven hand's mass as a share of its material's (WorldOptions::palm_hand_mass_scale;
  // unset: hapticd's, haptic::kServedPalmHandMassScale). 1: the full-mass hand, a baseline.
  std::optional<double> palm_hand_mass_scale;
};

// A device's frames in device space, per tick.
struct DeviceFrames {
  int frames = 0;
  Eigen::Vector3d p_D[haptic::kMaxHapticHandles];
  Eigen::Quaterniond q_D[haptic::kMaxHapticHandles];
};

// What a device receives at a tick: the reply's wrench per frame (device
// space, about the frame's origin) and its contact flag.
struct DeviceReply {
  int frames = 0;
  haptic::ReplyWrench wrench[haptic::kMaxHapticHandles];
  bool in_contact[haptic::kMaxHapticHandles]{};
};

// Median and 99th percentile of the stage timings of a run (wall clock; they do
// not feed back into the simulation).
struct OfflineTimings {
  double haptic_us_median = 0, haptic_us_p99 = 0;  // one tick: sample, reply, proxy integration
  double visual_ms_median = 0, visual_ms_p99 = 0;  // one visual step: world step and the model it publishes
  long visual_steps = 0;
};

// The lockstep runner: hapticd's haptic tick (HapticCore) and visual step (VisualStep) on simulated
// time, one scene device served through the wire's own messages (a Hello, then a PoseSample each
// tick, answered by a ForceSample), on one thread. The same objects hapticd's threads drive.
class OfflineLoops {
 public:
  // Builds the world as hapticd does (served_world_options) with the scene's step set to k T, and
  // opens the device's session. Throws std::runtime_error when the scene's device cannot be served.
  OfflineLoops(world::SceneDesc scene, const OfflineOptions& options);
  ~OfflineLoops();
  OfflineLoops(const OfflineLoops&) = delete;
  OfflineLoops& operator=(const OfflineLoops&) = delete;

  // Where tracked frame j sits in device space when it carries its handle at the
  // handle's current pose (a device starting there starts without force).
  void frame_pose_at_handle(int j, Eigen::Vector3d& p_D, Eigen::Quaterniond& q_D) const;

  // One haptic tick at t = ticks() T with the device's poses of this tick: a model due now is
  // handed over, the sample is sent and answered (a first one re-syncs the proxies; a withheld one,
  // OfflineOptions::withheld_samples_s, is neither, and `reply` has no frames), the haptic tick
  // integrates the proxies, and the visual step runs when one is due.
  void tick(const DeviceFrames& sample, DeviceReply& reply);

  long ticks() const { return ticks_; }
  double time_s() const { return static_cast<double>(ticks_) * options_.haptic_period_s; }
  world::World& world() { return *world_; }
  const world::World& world() const { return *world_; }
  // What the models' preparation did (its stiffness counters: TickSolverPreparer).
  const haptic::TickSolverPreparer& preparer() const { return *preparer_; }
  const haptic::DeviceLink& link() const { return link_; }
  // The session's proxies (as the haptic tick left them).
  const haptic::ProxyHand& proxy() const;
  const OfflineOptions& options() const { return options_; }
  // Proxy resets plus world resets.
  long resets() const;
  // Timings so far (sorts copies of the samples: not for the hot path).
  OfflineTimings timings() const;

 private:
  struct Wire;
  std::uint64_t now_ns() const;
  std::uint64_t tick_ns(long tick) const;  // the simulated time of tick `tick`
  void visual_step();
  // A sample taken at tick `tick` (sent at its time), read by the core at `read_ns`, and the core's
  // reply decoded into `reply`.
  void answer(const DeviceFrames& sample, long tick, std::uint64_t read_ns, DeviceReply& reply);
  void send(const protocol::EncodeResult& encoded);

  OfflineOptions options_;
  std::uint64_t period_ns_ = 0;
  std::unique_ptr<world::World> world_;
  haptic::DeviceLink link_;
  std::unique_ptr<haptic::TripleBuffer<haptic::HapticSnapshot>> snapshots_;
  std::unique_ptr<haptic::TripleBuffer<haptic::ProxyTargets>> targets_;
  std::unique_ptr<Wire> wire_;
  std::unique_ptr<haptic::HapticCore> core_;
  std::unique_ptr<haptic::TickSolverPreparer> preparer_;
  std::unique_ptr<haptic::VisualStep> visual_;
  protocol::Encoder encoder_;
  std::unique_ptr<protocol::Message> pose_, received_;
  std::uint64_t session_ = 0;
  bool pending_ = false;
  long publish_at_ = 0, ticks_ = 0, next_visual_tick_ = 0;
  std::uint64_t late_draws_;  // the late models' generator (a 64-bit LCG), from late_model_seed
  std::vector<double> haptic_us_, visual_ms_;
  std::vector<std::pair<DeviceFrames, long>> queued_;  // samples sent while the haptic thread stalled
};

// --- Devices -------------------------------------------------------------------------------------

// The device side of an offline run, ticked with the loops.
class OfflineDevice {
 public:
  virtual ~OfflineDevice() = default;
  virtual int frames() const = 0;
  // Tick `tick` (t = tick T): move over the last period under the reply last
  // received (not at tick 0: the device starts where it is), then write the
  // frames' poses.
  virtual void advance(long tick, double t_s, DeviceFrames& out) = 0;
  // This tick's reply, held until the next (a device's DAC holds its command). The simulated stylus
  // and glove fade a held reply once none has come for 20 ms, over 50 ms, as haptic-device's servo
  // loop does (client::ReplyWatchdog, DESIGN section 5): a stopped server's stylus holding its last
  // force for 300 ms was no device hapticd serves.
  virtual void receive(const DeviceReply& reply) = 0;
};

// The simulated stylus (clients/sim/device_model.hpp: the tip and the arm that
// holds it) following `start_D + command(t)`, with its velocity by a central
// difference of 1 us. Sends its tip with the identity orientation.
class SimulatedStylus final : public OfflineDevice {
 public:
  using Command = std::function<Eigen::Vector3d(double t_s)>;
  SimulatedStylus(const Eigen::Vector3d& start_D, Command command, double period_s,
                  const sim::DeviceParams& params = {});
  int frames() const override { return 1; }
  void advance(long tick, double t_s, DeviceFrames& out) override;
  void receive(const DeviceReply& reply) override;
  const sim::DeviceState& state() const { return state_; }
  // Work of the received forces on the tip so far, J (> 0: the rendering put energy in).
  double energy_j() const { return energy_j_; }

 private:
  Eigen::Vector3d start_D_;
  Command command_;
  double period_s_;
  sim::DeviceParams params_;
  sim::DeviceState state_;
  Eigen::Vector3d f_D_ = Eigen::Vector3d::Zero();
  double energy_j_ = 0;
  client::ReplyWatchdog watchdog_;
  std::uint64_t t_ns_ = 0;  // this tick's time (advance), when its reply came (receive)
};

// The simulated glove (clients/sim/glove_simulation.hpp: 20 joints on their
// impedance, the palm on the arm model) along a glove trajectory.
class SimulatedGlove final : public OfflineDevice {
 public:
  SimulatedGlove(sim::GloveTrajectory trajectory, int frames, bool left, double period_s,
                 const sim::GloveParams& params = {});
  int frames() const override { return sim_.frames(); }
  void advance(long tick, double t_s, DeviceFrames& out) override;
  void receive(const DeviceReply& reply) override;
  const sim::GloveSimulation& simulation() const { return sim_; }

 private:
  sim::GloveSimulation sim_;
  client::ReplyWatchdog watchdog_;
  std::uint64_t t_ns_ = 0;  // as SimulatedStylus's
};

// Poses recorded from another run, replayed tick by tick whatever the replies:
// the open-loop input of a comparison (every run sees the same device motion).
class RecordedDevice final : public OfflineDevice {
 public:
  explicit RecordedDevice(const std::vector<DeviceFrames>& poses) : poses_(poses) {}
  int frames() const override { return poses_.empty() ? 0 : poses_[0].frames; }
  void advance(long tick, double t_s, DeviceFrames& out) override;
  void receive(const DeviceReply&) override {}

 private:
  const std::vector<DeviceFrames>& poses_;
};

// --- Whole runs ----------------------------------------------------------------------------------

// The haptic tick's contact solves over a run (ProxyHand's counters, read at its end): the work,
// counted, that the tick's wall time measures with the machine's noise in it.
struct OfflineContactSolves {
  long solves = 0;       // ticks that solved contact rows (and lookahead fallbacks)
  long unconverged = 0;  // of them, those that ended at the sweep limit without an exact answer
  long sweeps = 0;       // Gauss-Seidel sweeps, summed
};

// A run's per-tick record: the device's poses and what it received.
struct OfflineTrace {
  std::vector<DeviceFrames> poses;
  std::vector<DeviceReply> replies;
  OfflineTimings timings;
  OfflineContactSolves contact_solves;
  long resets = 0;
};

// Runs `loops` with `device` for `ticks` ticks (device advance, loops tick, device
// receives) and records every tick. Deterministic: no clock reaches the simulation.
OfflineTrace run_offline(OfflineLoops& loops, OfflineDevice& device, long ticks);
// The same, calling `after_tick(tick)` after each tick (the loops' tick count before it), e.g. to
// read the world after a visual step.
OfflineTrace run_offline(OfflineLoops& loops, OfflineDevice& device, long ticks,
                         const std::function<void(long tick)>& after_tick);

}  // namespace hapticd::offline
