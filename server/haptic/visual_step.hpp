#pragma once
// The visual step of hapticd (DESIGN.md section 1), without a clock: read the newest proxies, drive
// each hand's handles toward them and step the world up to the moment the step's model will be
// published, then build every hand's handle-space model of the coming step and publish it. Its
// only notion of time is what it is given (the publication time and the step lengths): the
// real-time runner (VisualLoop: the visual thread, pacing on the wall clock) and the lockstep runner
// (server/offline) drive this same object.
#include <cstdint>
#include <functional>

#include "server/haptic/haptic_core.hpp"
#include "server/haptic/tick_solver_preparer.hpp"
#include "server/world/world.hpp"

namespace hapticd::haptic {

// How the visual loop's handles follow the haptic proxies: almost kinematically
// (GO09: the visual loop's handle is the proxy's), so the handle-space model is
// the flesh's answer to the proxy's own motion.
constexpr hand::DriveParams kProxyDrive{1e6, 1e3, 1e3, 10.0};

// A served palm-driven hand's mass as a share of its material's (WorldOptions::palm_hand_mass_scale).
// A stylus renders what the hand touches and the give of its flesh; the avatar's own inertia would be
// felt on top of the user's real hand, the whole hand's on one point, times the workspace scale
// squared: at full density (skin, 1070 kg/m^3: ~0.4 kg, 1.6 kg on a stylus at scale 2) lifting the
// stylus off the bunny at 15 cm/s pulled it back 1.1-1.6 N, in free space as much, and the user's arm
// rang for a second after (0.02-0.16 N). At 0.03 (~12 g: 48 g at the stylus, a light pen) the same
// lifts pull 0.16-0.21 N, 0.15 N of it the coupling's damping, and nothing is felt a second later
// (Touch/PressHoldLiftForces); at 0.1 they still pulled up to 0.38 N. A glove keeps its fingers'
// mass: each frame feels only its segment's share, and with light flesh the tripod grasp at 15 Hz
// lifted the box 2.3 mm of 50 and gave the glove +0.10 J.
constexpr double kServedPalmHandMassScale = 0.03;

// The world a server steps: the scene's step is the visual period, hands are weightless (a device
// in free space feels no virtual hand weight) and light (kServedPalmHandMassScale), their handles
// follow the proxies (kProxyDrive), and the visual step builds the coming step's model itself (no
// in-step linearization).
world::WorldOptions served_world_options();

// What the visual step publishes for a hand between two steps.
enum class HandleModelKind {
  // hapticd (seed 004 section 3): the coming step's handle-space linearization
  // F*(x, v) = F0 + K (x - x0) + D (v - v0) with its constraint contacts as unilateral rows the
  // haptic tick solves (HandleContactModel, HapticModel::contacts; fill_haptic_model).
  linearized,
  // The same linearization with the last step's pushing contacts held bilaterally in K and D (GO09;
  // ContactLinearization::held): the model before contacts could release in the tick, the baseline
  // of the contact-change suite.
  bilateral,
  // The same pipeline with the model cut to its zeroth order, a baseline of the multirate suite:
  // the coupling wrench the last step ended with (the flesh on the handles, seed 004 eq. 4-5), held
  // until the next (K = D = 0). No linearization is built.
  zoh,
};
const char* to_string(HandleModelKind kind);

// Fills `out` with hand h's model for the coming interval (linearize_next_step:
// the step about to be taken from the world's current state; `lin` is scratch),
// in_contact from the hand's contacts; out.handles = 0 when it cannot.
void fill_haptic_model(world::World& world, int h, hand::HandleLinearization& lin, HapticModel& out,
                       hand::ContactLinearization contacts = hand::ContactLinearization::unilateral);
// A linearization's contact rows into the fixed capacity of the tick (the proxy's part prepared later,
// prepare_tick_solver); false when they do not fit or are not finite.
bool set_tick_contacts(const hand::HandleContactModel& in, int handles, TickContacts& out);
// Only its contact flags (in_contact: a contact of the last step inside or carrying force;
// handle_in_contact: inside) from the world's last contacts, and each
// handle's clearance planes (World::clearance) from its last collision, and its skin radius.
void fill_contact_flags(const world::World& world, int h, HapticModel& out);

// Handle j of hand h's target for a world that simulates up to `until_ns`: the proxy extrapolated
// at its velocity from the time it is of (targets.t_ns) to then, by at most kMaxProxyExtrapolation_s
// either way (a stalled haptic thread leaves old proxies). With the handle's state `from` and the
// clearance planes measured there (World::clearance), the extrapolation stops where it would close
// one of their gaps, its velocity scaled alike: the tick holds the proxy itself to them
// (ProxyHand::limit_to_clearance), but a proxy rushing after a device that jumped (4 m/s after a
// stall) extrapolated over a late 100 ms step put the hand's target 9 cm on, through the bunny.
// With the handle's skin radius (skin_radii) as well, it also stops where a skin point would go
// farther from `from` than the planes were looked for (hand::free_travel_share).
constexpr double kMaxProxyExtrapolation_s = 0.1;
hand::HandleTarget proxy_target(const ProxyTargets& targets, int h, int j, std::uint64_t until_ns,
                                const hand::HandleState* from = nullptr, const hand::ClearancePlane* planes = nullptr,
                                int planes_count = 0, double skin_radius_m = -1);

// Per handle of `hand` (at most kMaxHapticHandles), the farthest of its skin points from it, m.
void skin_radii(const hand::Hand& hand, double* radius_m);

class VisualStep {
 public:
  // `preparer`: the haptic side's tick-solver preparation for the models of glove-sized hands
  // (none: the tick solves them densely).
  VisualStep(world::World& world, TripleBuffer<HapticSnapshot>& snapshots, TripleBuffer<ProxyTargets>& targets,
             const TickSolverPreparer* preparer = nullptr, HandleModelKind kind = HandleModelKind::linearized);

  // The world up to `publish_ns`: the newest proxies are read, a hand whose driving session re-synced
  // is placed rigidly at its proxy, every driven hand's handles are driven toward their proxies
  // extrapolated to `publish_ns`, and the world steps by `dt_s`.
  void advance_world(std::uint64_t publish_ns, double dt_s);
  // Every hand's model of the coming step, `dt_s` long from `publish_ns`, into the snapshot's back
  // slot (not handed over yet). The world takes exactly that step next.
  void build_models(std::uint64_t publish_ns, double dt_s);
  // The haptic tick's prepared solvers of the models just built (a glove's; the preparer's).
  void prepare_tick_solvers();
  // Hands the models over to the haptic tick.
  void publish() { snapshots_.publish(); }
  // After a throw out of any of the above: nothing half-built is published (the models in use fade
  // to the safe model if no step succeeds within the watchdog's time), and every hand is reset
  // (counted in HandState::resets): one whose positions are finite stops where it is, keeping its
  // shape and contacts; any other is placed rigidly at its proxy, at rest, without contacts.
  void recover();

  world::World& world() { return world_; }
  const world::World& world() const { return world_; }
  // Tests only: called before each world step; whatever it throws is a fault of the step.
  void set_fault_injection(std::function<void()> inject) { inject_ = std::move(inject); }

 private:
  world::World& world_;
  TripleBuffer<HapticSnapshot>& snapshots_;
  TripleBuffer<ProxyTargets>& targets_;
  const TickSolverPreparer* preparer_;
  HandleModelKind kind_;
  hand::HandleLinearization scratch_;
  std::uint32_t resyncs_seen_[kMaxHands]{};
  std::function<void()> inject_;
  // Places hand h, whose proxies were re-synced onto their device, at the palm pose `palm`, or the
  // share of the way there its contacts and clearance planes leave free.
  void place_resynced(int h, const HapticPose& palm);
};

}  // namespace hapticd::haptic
