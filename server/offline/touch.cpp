#include "server/offline/touch.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>
#include <utility>
#include <vector>

#include "hand_models/rigid_handle.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

world::SceneDesc scene_file(const std::string& name) {
  return world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/" + name + ".json");
}

// The first hand (and its device's workspace) moved to `p` (world).
void move_hand(world::SceneDesc& s, const Eigen::Vector3d& p) {
  const Eigen::Vector3d shift = p - s.hands[0].pose.p_W;
  s.hands[0].pose.p_W = p;
  s.devices[0].workspace.offset_W += shift;
}

// The deepest skin point after each visual step (the world's snapshot), into `deepest`.
auto penetration_probe(OfflineLoops& loops, double& deepest) {
  return [&loops, &deepest](long tick) {
    if (tick % loops.options().visual_every_ticks != 0) return;
    deepest = std::max(deepest, loops.world().snapshot().max_penetration_m);
  };
}

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kBoxYaw = -30 * kDeg;
// The box's centre in the palm frame (fingers +y, palmar side -z) when grasped, and the closed
// posture (degrees; per finger abduction, flexion 1, 2, 3): test_world_glove.cpp's box_grasp.
const Eigen::Vector3d kBoxInHand(-0.040, 0.050, -0.052);
constexpr double kClosedDeg[hand::kHandJointDofs] = {-30, 30, 20, 60, -4, 5, 70, 65, 0, 15,
                                                     95,  40, 8,  0,  6,  6, 16, 0,  6, 6};
// The commanded tripod curls the thumb, index and middle kTripodSqueeze times as far, into the box,
// so the hand grips it. At box_grasp's posture itself (1.0) the world stepped every tick (a 1 kHz
// visual rate) lifted the box 12.9 mm of the palm's 50 (its contacts squeezed it by 2.6 N); at 1.1,
// 47.9 mm (4.4 N): haptic-bench touch's reference row. The lockstep runner at 30 and 60 Hz
// lifted it 40-60 mm at 1.0 only while the tick's contact rows let the proxies sink past them late
// in each step (the world's contacts squeezed it by 7.5-10.9 N).
constexpr int kTripodFingers = 3;
constexpr double kTripodSqueeze = 1.1;
// The ball's power grasp, fitted on the skeleton's capsules (hand_skeleton.hpp's geometry, the
// rigid hands' phalanges): the ball 2.5 mm under the palm; each finger, at its abduction, curled with
// its flexions in the ratio 60 : 70 : 40 (the thumb's 30 : 30 : 40) until a phalanx touches the ball;
// the ball's place and the abductions chosen so the contacts push it back from every horizontal
// direction with every fingertip below its centre. The commanded grasp curls each finger
// kBallSqueeze times as far, into the ball, so the hand grips it.
const Eigen::Vector3d kBallInHand(-0.015, 0.035, -0.045);
constexpr double kBallTouchDeg[hand::kHandJointDofs] = {-30,  24.5, 24.5, 32.6, -21,  43.5, 50.8, 29.0, -3,   45.9,
                                                        53.6, 30.6, 15,   49.8, 58.1, 33.2, 33,   60.3, 70.4, 40.2};
constexpr double kBallSqueeze = 1.2;
// The plate of the pinch: 10 x 8 cm, 4 mm thick, 4 cm over the table's +x edge (its centre 1 cm in);
// the pads 1.2 cm in from its edge.
constexpr double kPlateLength = 0.10, kPlateWidth = 0.08, kPlateThickness = 0.004;  // along x, y, z
constexpr double kPlateOverhang = 0.04, kPadInside = 0.012;

sim::JointVector joint_vector_deg(const double (&deg)[hand::kHandJointDofs]) {
  sim::JointVector q;
  for (int i = 0; i < q.size(); ++i) q[i] = deg[i] * kDeg;
  return q;
}

// How a grasp is held: the object's centre in the palm frame when held, the palm's orientation in the
// world, the way the palm moves in over the approach (world, unit), and the open and closed postures.
struct GraspPlan {
  Eigen::Vector3d object_in_hand;
  Eigen::Quaterniond q_WH = Eigen::Quaterniond::Identity();
  Eigen::Vector3d approach_W{0, 0, -1};
  sim::JointVector open = hand::rest_joint_angles().vector(), closed;
};

// The pinch, from the glove's pinch posture on the skeleton: the thumb's fingertip against the
// index's distal phalanx. The plate lies between their pads, its normal d from the thumb's pad to the
// index's; it extends away from the hand along e (the pads' direction from the palm, across d). The
// palm turns so that d is world +z (the thumb under the plate) and e world -x (toward the table).
GraspPlan pinch_plan() {
  const hand::HandJointAngles closed = sim::pinch_posture();
  const hand::SkeletonPose s = hand::skeleton_pose(closed);
  const auto& thumb = hand::finger_geometry()[0];
  const auto& index = hand::finger_geometry()[1];
  const Eigen::Vector3d tip = s.joints[0][3], a = s.joints[1][2], b = s.joints[1][3];
  const double along = std::clamp((tip - a).dot(b - a) / (b - a).squaredNorm(), 0.0, 1.0);
  const Eigen::Vector3d on_index = a + along * (b - a);
  const double r_index = index.radius[2] + along * (index.radius[3] - index.radius[2]);
  const Eigen::Vector3d d = (on_index - tip).normalized();
  const Eigen::Vector3d pinch = 0.5 * ((tip + thumb.radius[3] * d) + (on_index - r_index * d));
  const Eigen::Vector3d e = (pinch - pinch.dot(d) * d).normalized();
  Eigen::Matrix3d hand_axes, world_axes;
  hand_axes << d, e, d.cross(e);
  world_axes << Eigen::Vector3d::UnitZ(), -Eigen::Vector3d::UnitX(), -Eigen::Vector3d::UnitY();
  GraspPlan plan;
  plan.object_in_hand = pinch + (0.5 * kPlateLength - kPadInside) * e;
  plan.q_WH = Eigen::Quaterniond(Eigen::Matrix3d(world_axes * hand_axes.transpose()));
  plan.approach_W = -Eigen::Vector3d::UnitX();
  // Open: the index turned away from the thumb (its rest abduction reaches the plate's plane).
  hand::HandJointAngles open = hand::rest_joint_angles();
  open.finger[1][0] = 4 * kDeg;
  plan.open = open.vector();
  plan.closed = closed.vector();
  return plan;
}

GraspPlan grasp_plan(GraspKind kind) {
  GraspPlan plan;
  switch (kind) {
    case GraspKind::tripod_box:
      plan.object_in_hand = kBoxInHand;
      plan.closed = joint_vector_deg(kClosedDeg);
      for (int f = 0; f < kTripodFingers; ++f)
        for (int k = 1; k < 4; ++k) plan.closed[4 * f + k] *= kTripodSqueeze;
      return plan;
    case GraspKind::power_ball: {
      plan.object_in_hand = kBallInHand;
      plan.closed = joint_vector_deg(kBallTouchDeg);
      for (int f = 0; f < hand::kHandFingers; ++f)
        for (int k = 1; k < 4; ++k) plan.closed[4 * f + k] *= kBallSqueeze;
      return plan;
    }
    case GraspKind::pinch_plate:
      return pinch_plan();
  }
  throw std::invalid_argument("grasp_plan: no such grasp");
}

// A half-cosine from 0 at `from` to 1 at `to`.
double ease(double t, double from, double to) {
  const double s = std::clamp((t - from) / (to - from), 0.0, 1.0);
  return 0.5 * (1.0 - std::cos(std::numbers::pi * s));
}

}  // namespace

PressSchedule::PressSchedule(const Press& p) : press(p) {
  down_start = 0.3;
  down_end = down_start + p.depth_m / p.down_m_s;
  up_start = down_end + 0.5;
  up_end = up_start + (p.depth_m + kClearance) / p.up_m_s;
  end = up_end + 1.2;
}

double PressSchedule::z(double t) const {
  if (t < down_start) return 0;
  if (t < down_end) return -press.down_m_s * (t - down_start);
  if (t < up_start) return -press.depth_m;
  if (t < up_end) return -press.depth_m + press.up_m_s * (t - up_start);
  return kClearance;
}

world::SceneDesc press_scene(const std::string& object) {
  // The rigid hands of seeds 002 and 001 in the same places: their scene is the stylus scene with that
  // hand.
  for (const auto& [prefix, model] :
       {std::pair<std::string, world::HandModelKind>{"spring_", world::HandModelKind::spring},
        {"contact_point_", world::HandModelKind::contact_point}}) {
    if (object.rfind(prefix, 0) != 0) continue;
    const std::string place = object.substr(prefix.size());
    if (place == "deformable_bunny")
      throw std::invalid_argument("press_scene: the " + prefix.substr(0, prefix.size() - 1) +
                                  " hand does not touch deformable objects yet");
    world::SceneDesc s = press_scene(place);
    for (world::HandDesc& h : s.hands) h.model = model;
    return s;
  }
  if (object == "movable_bunny") return scene_file("stylus_bunny");
  if (object == "fixed_bunny") {
    world::SceneDesc s = scene_file("stylus_bunny");
    for (world::ObjectDesc& o : s.objects)
      if (o.name == "bunny") o.kind = world::BodyKind::static_body;
    return s;
  }
  if (object == "deformable_bunny") {
    world::SceneDesc s = scene_file("deformable_bunny");
    move_hand(s, Eigen::Vector3d(0.08, 0.1, 0.9));  // over the bunny, as in stylus_bunny
    return s;
  }
  if (object == "free_space") {
    world::SceneDesc s = scene_file("stylus_bunny");
    move_hand(s, Eigen::Vector3d(0.08, 0.1, 1.3));
    return s;
  }
  if (object == "table_edge") {
    // The table's +x edge (the top at z = 0.75 ends at x = 0.5): half the palm over it.
    world::SceneDesc s = scene_file("stylus_bunny");
    move_hand(s, Eigen::Vector3d(0.5, 0.0, 0.8));
    return s;
  }
  throw std::invalid_argument("press_scene: no object '" + object +
                              "' (movable_bunny, fixed_bunny, deformable_bunny, table_edge, free_space; spring_ or "
                              "contact_point_ before one of them but the deformable bunny for a rigid hand)");
}

TouchRun run_press_hold_lift(const world::SceneDesc& scene, const PressSchedule& schedule,
                             const OfflineOptions& options) {
  OfflineLoops loops(scene, options);
  Eigen::Vector3d start_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  SimulatedStylus stylus(
      start_D, [&schedule](double t) { return Eigen::Vector3d(0, 0, schedule.z(t)); }, options.haptic_period_s);
  TouchRun r;
  r.trace = run_offline(loops, stylus, std::lround(schedule.end / options.haptic_period_s),
                        penetration_probe(loops, r.penetration_max_m));
  r.energy_j = stylus.energy_j();
  return r;
}

OfflineOptions movable_bunny_press_options() {
  OfflineOptions options;
  options.visual_every_ticks = 17;
  options.settle_s = 0.5;
  options.passivity_control = false;
  return options;
}

AfterLift after_lift(const OfflineTrace& trace, const PressSchedule& schedule, const OfflineOptions& options) {
  AfterLift a;
  const double T = options.haptic_period_s;
  const long ticks = static_cast<long>(trace.replies.size());
  for (long k = 0; k < ticks; ++k) {
    a.largest = std::max(a.largest, trace.replies[k].wrench[0].f_D.norm());
    if (a.touch < 0 && trace.replies[k].in_contact[0]) a.touch = k;
  }
  if (a.touch >= 0) {
    const double touch_z = schedule.z(a.touch * T), grace = T + options.visual_every_ticks * T;
    long above = -1;
    for (long k = std::lround(schedule.up_start / T); k < ticks; ++k) {
      const double t = k * T;
      if (above < 0 && schedule.z(t) > touch_z) above = k;
      if (above < 0 || t < above * T + grace) continue;
      a.pull = std::max(a.pull, -trace.replies[k].wrench[0].f_D.z());
    }
  }
  for (long k = std::lround((schedule.up_end + 1.0) / T); k < ticks; ++k) {
    a.after = std::max(a.after, trace.replies[k].wrench[0].f_D.norm());
    a.flagged = a.flagged || trace.replies[k].in_contact[0];
  }
  return a;
}

namespace {
struct GraspNames {
  GraspKind kind;
  const char *name, *object;
};
constexpr GraspNames kGraspNames[] = {{GraspKind::tripod_box, "grasp_box", "box"},
                                      {GraspKind::power_ball, "grasp_ball", "ball"},
                                      {GraspKind::pinch_plate, "pinch_plate", "plate"}};
const GraspNames& names_of(GraspKind kind) {
  for (const GraspNames& n : kGraspNames)
    if (n.kind == kind) return n;
  throw std::invalid_argument("no such grasp");
}
}  // namespace

const char* grasp_name(GraspKind kind) { return names_of(kind).name; }
const char* grasp_object(GraspKind kind) { return names_of(kind).object; }

world::SceneDesc grasp_scene(world::SceneDesc s, GraspKind kind) {
  if (s.hands.empty() || s.devices.empty()) throw std::invalid_argument("grasp_scene: " + s.name + " has no hand");
  const auto named = [&s](const std::string& name) -> world::ObjectDesc* {
    for (world::ObjectDesc& o : s.objects)
      if (o.name == name) return &o;
    throw std::invalid_argument("grasp_scene: " + s.name + " has no object named " + name);
  };
  if (kind == GraspKind::pinch_plate) {
    const world::ObjectDesc* table = named("table");
    if (table->shape.type != world::ShapeType::box || !table->pose.q_W.matrix().isIdentity(1e-12))
      throw std::invalid_argument("grasp_scene: " + s.name + "'s table is not an unturned box");
    const Eigen::Vector3d top = table->pose.p_W + 0.5 * table->shape.size;  // its +x edge and top
    world::ObjectDesc plate;
    plate.name = "plate";
    plate.shape.type = world::ShapeType::box;
    plate.shape.size = Eigen::Vector3d(kPlateLength, kPlateWidth, kPlateThickness);
    // 20 cm toward -y from the table's middle: clear of the scenes' box, ball and bunny.
    plate.pose.p_W = Eigen::Vector3d(top.x() + kPlateOverhang - 0.5 * kPlateLength, table->pose.p_W.y() - 0.2,
                                     top.z() + 0.5 * kPlateThickness);
    plate.material = table->material;
    plate.material.density_kg_m3 = 1050;  // 34 g
    s.objects.push_back(plate);
  }
  world::ObjectDesc* o = named(grasp_object(kind));
  if (kind == GraspKind::tripod_box)
    o->pose.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(kBoxYaw, Eigen::Vector3d::UnitZ()));
  const GraspPlan plan = grasp_plan(kind);
  s.hands[0].pose.q_W = plan.q_WH;
  move_hand(s, o->pose.p_W - plan.q_WH * plan.object_in_hand - GraspSchedule::kAboveM * plan.approach_W);
  return s;
}

sim::GloveTrajectory grasp_release_trajectory(const Eigen::Vector3d& palm_D, const Eigen::Quaterniond& q_D,
                                              GraspKind kind) {
  using G = GraspSchedule;
  const GraspPlan plan = grasp_plan(kind);
  std::vector<sim::GloveTrajectory::Sample> samples;
  for (int k = 0; k * 0.01 <= G::kEnd + 1e-9; ++k) {  // every 10 ms, interpolated linearly between
    const double t = k * 0.01;
    const double close = ease(t, G::kCloseAt, G::kGrippedAt) - ease(t, G::kOpenAt, G::kOpenedAt);
    const Eigen::Vector3d p =
        G::kAboveM * (ease(t, G::kDownAt, G::kCloseAt) - ease(t, G::kOpenedAt, G::kWithdrawnAt)) * plan.approach_W +
        G::kLiftM * ease(t, G::kLiftAt, G::kHeldAt) * Eigen::Vector3d::UnitZ();
    samples.push_back({t, (1 - close) * plan.open + close * plan.closed, {p.x(), p.y(), p.z()}});
  }
  sim::GloveTrajectory motion =
      sim::GloveTrajectory::from_samples(grasp_name(kind), samples, {palm_D.x(), palm_D.y(), palm_D.z()});
  motion.set_palm_orientation(q_D);
  return motion;
}

FrameWork frame_work(const OfflineTrace& trace) {
  FrameWork w;
  for (std::size_t k = 0; k + 1 < trace.replies.size() && k + 1 < trace.poses.size(); ++k) {
    const DeviceFrames &from = trace.poses[k], &to = trace.poses[k + 1];
    const Eigen::Vector3d palm_move = to.p_D[0] - from.p_D[0];
    const Eigen::Vector3d palm_turn = hand::rotation_difference(to.q_D[0], from.q_D[0]);
    for (int j = 0; j < trace.replies[k].frames; ++j) {
      const haptic::ReplyWrench& f = trace.replies[k].wrench[j];
      const Eigen::Vector3d move = to.p_D[j] - from.p_D[j];
      const Eigen::Vector3d turn = hand::rotation_difference(to.q_D[j], from.q_D[j]);
      const double grounded = f.f_D.dot(move) + f.tau_D.dot(turn);
      w.grounded_j += grounded;
      w.on_palm_j += j == 0 ? grounded
                            : f.f_D.dot(move - palm_move - palm_turn.cross(from.p_D[j] - from.p_D[0])) +
                                  f.tau_D.dot(turn - palm_turn);
    }
  }
  return w;
}

GraspRun run_grasp_release(const world::SceneDesc& scene, const OfflineOptions& options, GraspKind kind) {
  using G = GraspSchedule;
  OfflineLoops loops(scene, options);
  const int held = loops.world().rigid() ? loops.world().rigid()->find(grasp_object(kind)) : -1;
  if (held < 0) throw std::invalid_argument("run_grasp_release: " + scene.name + " has no rigid " + grasp_object(kind));
  GraspRun run;
  run.object_z0 = run.object_top = loops.world().snapshot().bodies[held].p_WO.z();
  Eigen::Vector3d palm_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, palm_D, q_D);
  const bool left = scene.hands[0].side == world::HandSide::left;
  SimulatedGlove glove(grasp_release_trajectory(palm_D, q_D, kind), sim::kGloveFramesAll, left,
                       options.haptic_period_s);
  const double T = options.haptic_period_s;
  const long lift_tick = std::lround(G::kLiftAt / T), held_tick = std::lround(G::kHeldAt / T);
  const long open_tick = std::lround(G::kOpenAt / T);
  const long grip_tick = std::lround(G::kGrippedAt / T);
  auto probe = penetration_probe(loops, run.penetration_max_m);
  auto held_in_palm = [&] {
    const world::WorldSnapshot& s = loops.world().snapshot();
    const hand::HandleState& palm = s.handles[0][0];
    return Eigen::Vector3d(palm.q_WH.conjugate() * (s.bodies[held].p_WO - palm.p_WH));
  };
  Eigen::Vector3d held_at = Eigen::Vector3d::Zero();
  run.trace = run_offline(loops, glove, std::lround(G::kEnd / T), [&](long tick) {
    probe(tick);
    if (tick >= grip_tick && tick < lift_tick)
      for (const world::ContactRecord& c : loops.world().snapshot().contacts)
        if (c.hand == 0 && c.object == held) run.squeeze_world_n += c.f_W.norm();
    run.object_top = std::max(run.object_top, loops.world().snapshot().bodies[held].p_WO.z());
    if (tick == lift_tick) run.energy_at_lift_j = glove.simulation().passivity_energy_j();
    if (tick == held_tick) held_at = held_in_palm();
    if (tick == open_tick) {
      run.energy_at_open_j = glove.simulation().passivity_energy_j();
      run.hold_slip_m = (held_in_palm() - held_at).norm();
    }
  });
  const double released_from = G::kOpenedAt + T + options.visual_every_ticks * T;
  for (std::size_t k = 0; k < run.trace.replies.size(); ++k) {
    const double t = static_cast<double>(k) * T;
    const bool gripping = static_cast<long>(k) >= grip_tick && static_cast<long>(k) < lift_tick;
    for (int j = 0; j < run.trace.replies[k].frames; ++j) {
      const double f = run.trace.replies[k].wrench[j].f_D.norm();
      if (gripping) run.squeeze_felt_n += f;
      if (t > released_from) run.release_n = std::max(run.release_n, f);
      if (t > G::kOpenedAt + 1.0) run.after_n = std::max(run.after_n, f);
    }
  }
  run.squeeze_world_n /= static_cast<double>(lift_tick - grip_tick);
  run.squeeze_felt_n /= static_cast<double>(lift_tick - grip_tick);
  run.energy_j = glove.simulation().passivity_energy_j();
  for (int j = 0; j < loops.proxy().handles(); ++j) run.observed_j += loops.proxy().energy_in(j);
  run.object_end = loops.world().snapshot().bodies[held];
  return run;
}

}  // namespace hapticd::offline
