#include "server/haptic/visual_step.hpp"

#include <algorithm>
#include <limits>

#include "hand_models/rigid_handle.hpp"

namespace hapticd::haptic {

world::WorldOptions served_world_options() {
  world::WorldOptions o;
  o.hand_gravity = false;
  o.palm_hand_mass_scale = kServedPalmHandMassScale;
  o.drive = kProxyDrive;
  o.linearize = false;
  return o;
}

const char* to_string(HandleModelKind kind) {
  switch (kind) {
    case HandleModelKind::linearized:
      return "linearized";
    case HandleModelKind::bilateral:
      return "bilateral";
    case HandleModelKind::zoh:
      return "zoh";
  }
  return "?";
}

void fill_contact_flags(const world::World& world, int h, HapticModel& out) {
  const world::WorldSnapshot& snap = world.snapshot();
  const hand::Hand& hand = world.hand(h);
  out.in_contact = false;
  std::fill(std::begin(out.handle_in_contact), std::end(out.handle_in_contact), false);
  for (const world::ContactRecord& c : snap.contacts) {
    // Touching: a contact inside now, or one that carried force over the last step (a speculative
    // row holds the skin on the surface, depth <= 0, while it pushes: the stylus pressed the bunny
    // with up to 1.8 N and was never flagged once the bunny ended each step where the hand's solve
    // took it). A glove's frames stay gated by depth alone (Not there yet in docs/architecture.md).
    if (c.hand != h || (c.depth_m <= 0 && c.f_W.squaredNorm() == 0)) continue;
    out.in_contact = true;
    if (c.depth_m <= 0) continue;
    // A contact without a skin point of this hand (another hand's skin inside its flesh) marks no handle.
    const int j = c.point >= 0 ? hand.skin_handle(c.point) : -1;
    if (j >= 0 && j < kMaxHapticHandles) out.handle_in_contact[j] = true;
  }
  const std::vector<std::vector<hand::ClearancePlane>>& clearance = world.clearance(h);
  for (int j = 0; j < kMaxHapticHandles; ++j) {
    const int n = j < static_cast<int>(clearance.size())
                      ? std::min(static_cast<int>(clearance[j].size()), hand::kClearancePlanes)
                      : 0;
    for (int k = 0; k < n; ++k) out.clearance[j][k] = clearance[j][k];
    out.clearance_count[j] = n;
  }
  skin_radii(hand, out.skin_radius_m);
  out.skin_known = true;
}

void skin_radii(const hand::Hand& hand, double* radius_m) {
  const std::vector<hand::HandleState>& handles = hand.handles();
  const int m = std::min(static_cast<int>(handles.size()), kMaxHapticHandles);
  std::fill(radius_m, radius_m + kMaxHapticHandles, 0.0);
  for (int i = 0; i < hand.num_skin_points(); ++i) {
    const int j = hand.skin_handle(i);
    if (j >= 0 && j < m) radius_m[j] = std::max(radius_m[j], (hand.skin_point(i) - handles[j].p_WH).norm());
  }
}

static_assert(kMaxTickContacts == hand::kMaxLinearizedContacts, "the tick holds every row a model carries");

bool set_tick_contacts(const hand::HandleContactModel& in, int handles, TickContacts& out) {
  out.count = 0;
  out.proxy_prepared = false;
  out.max_lookahead_s = std::numeric_limits<double>::infinity();
  const int c = in.count(), n = 6 * handles, r = 3 * c;
  if (c == 0) return true;
  if (c > kMaxTickContacts || n > kMaxHapticDofs || in.G.rows() != n || in.G.cols() != r || in.W.rows() != r ||
      in.W.cols() != r || in.u0.size() != r || in.U_K.rows() != r || in.U_K.cols() != n || in.U_D.rows() != r ||
      in.U_D.cols() != n || in.lambda0.size() != r || in.bias.size() != c)
    return false;
  out.G = in.G;
  out.W = in.W;
  out.u0 = in.u0;
  out.U_K = in.U_K;
  out.U_D = in.U_D;
  out.lambda0 = in.lambda0;
  for (int i = 0; i < c; ++i) out.bias[i] = in.bias[i], out.mu[i] = in.mu[i];
  out.count = c;
  return true;
}

void fill_haptic_model(world::World& world, int h, hand::HandleLinearization& lin, HapticModel& out,
                       hand::ContactLinearization contacts) {
  out.handles = 0;
  out.solver.prepared = false;
  out.contacts.count = 0;
  hand::Hand& hand = world.hand(h);
  fill_contact_flags(world, h, out);
  if (!hand.linearize_next_step(lin, contacts)) return;
  const int m = static_cast<int>(lin.x0.size());
  if (m > kMaxHapticHandles || lin.F0.size() != 6 * m) return;
  if (!set_tick_contacts(lin.contacts, m, out.contacts)) return;
  out.F0 = lin.F0;
  out.K = lin.K;
  out.D = lin.D;
  for (int j = 0; j < m; ++j) {
    out.x0[j] = {lin.x0[j].p_WH, lin.x0[j].q_WH};
    out.v0[j] = lin.x0[j].v_WH;
    out.w0[j] = lin.x0[j].w_WH;
  }
  out.handles = m;
}

namespace {

// The zero-order hold: the flesh's wrench on the handles as the step left them (seed 004 eq. 4-5), K = D = 0.
void fill_held_model(world::World& world, int h, HapticModel& out) {
  out.handles = 0;
  out.solver.prepared = false;
  out.contacts.count = 0;
  fill_contact_flags(world, h, out);
  const hand::Hand& hand = world.hand(h);
  const std::vector<hand::HandleState>& handles = hand.handles();
  const int m = std::min(hand.num_handles(), kMaxHapticHandles);
  const Eigen::VectorXd F = hand.coupling_wrench();
  if (F.size() < 6 * m || !F.allFinite()) return;
  out.F0 = F.head(6 * m);
  out.K.setZero(6 * m, 6 * m);
  out.D.setZero(6 * m, 6 * m);
  for (int j = 0; j < m; ++j) {
    out.x0[j] = {handles[j].p_WH, handles[j].q_WH};
    out.v0[j] = handles[j].v_WH;
    out.w0[j] = handles[j].w_WH;
  }
  out.handles = m;
}

}  // namespace

hand::HandleTarget proxy_target(const ProxyTargets& targets, int h, int j, std::uint64_t until_ns,
                                const hand::HandleState* from, const hand::ClearancePlane* planes, int planes_count,
                                double skin_radius_m) {
  const double ahead = std::clamp(1e-9 * (static_cast<double>(until_ns) - static_cast<double>(targets.t_ns)),
                                  -kMaxProxyExtrapolation_s, kMaxProxyExtrapolation_s);
  const HapticPose& p = targets.pose[h][j];
  double share = 1.0;
  if (from) {
    const Eigen::Vector3d dx = p.p_W - from->p_WH, dtheta = hand::rotation_difference(p.q_W, from->q_WH);
    const Eigen::Vector3d move = ahead * targets.v_W[h][j], turn = ahead * targets.w_W[h][j];
    if (planes && planes_count > 0) share = hand::clearance_share(planes, planes_count, dx, dtheta, move, turn);
    if (skin_radius_m >= 0) share = std::min(share, hand::free_travel_share(dx, dtheta, move, turn, skin_radius_m));
  }
  const Eigen::Vector3d v = share * targets.v_W[h][j], w = share * targets.w_W[h][j];
  return {p.p_W + ahead * v,        hand::rotate_by(p.q_W, ahead * w), v, w,
          targets.v_device_W[h][j], targets.w_device_W[h][j]};
}

VisualStep::VisualStep(world::World& world, TripleBuffer<HapticSnapshot>& snapshots,
                       TripleBuffer<ProxyTargets>& targets, const TickSolverPreparer* preparer, HandleModelKind kind)
    : world_(world), snapshots_(snapshots), targets_(targets), preparer_(preparer), kind_(kind) {}

void VisualStep::advance_world(std::uint64_t publish_ns, double dt_s) {
  targets_.update();
  const ProxyTargets& targets = targets_.front();
  for (int h = 0; h < std::min(world_.num_hands(), kMaxHands); ++h) {
    if (!targets.driven[h]) continue;
    hand::Hand& hand = world_.hand(h);
    if (targets.resyncs[h] != resyncs_seen_[h]) {
      resyncs_seen_[h] = targets.resyncs[h];
      place_resynced(h, targets.pose[h][0]);
    }
    const std::vector<std::vector<hand::ClearancePlane>>& clearance = world_.clearance(h);
    double radius_m[kMaxHapticHandles];
    skin_radii(hand, radius_m);
    for (int j = 0; j < std::min(hand.num_handles(), kMaxHapticHandles); ++j) {
      const bool planes = j < static_cast<int>(clearance.size()) && !clearance[j].empty();
      hand.set_target(
          j, proxy_target(targets, h, j, publish_ns, &hand.handles()[j], planes ? clearance[j].data() : nullptr,
                          planes ? std::min(static_cast<int>(clearance[j].size()), hand::kClearancePlanes) : 0,
                          radius_m[j]));
    }
  }
  if (inject_) inject_();
  world_.step(dt_s);
}

// A hand whose proxies were re-synced onto their device (a gap in its samples longer than the re-sync
// gap: a stalled server) is moved to them at once, or its first models would pull the proxies back to
// where the hand was. Not into an object: the surfaces it touches (as planes at their gaps, about the
// palm) and its handles' clearance planes bound the rigid move of the whole hand there. Placed all the
// way after hapticd stopped 100-200 ms while its stylus pressed the bunny (the re-sync dropped the
// force, and the stylus sank 8 mm in), the hand was inside the bunny and pulled the lifting stylus up
// to 7.1 N toward it, 4.2-4.7 N still a second later, InContact (SERVER_PAUSE in
// tests/e2e/press_hold_lift_busy.sh; ServerStalls in the lockstep runner: 5.14 N). Stopped at the
// surface, the hand presses the proxies back out.
void VisualStep::place_resynced(int h, const HapticPose& palm) {
  hand::Hand& hand = world_.hand(h);
  const std::vector<hand::HandleState>& handles = hand.handles();
  const hand::HandleState& from = handles[0];
  const Eigen::Vector3d move = palm.p_W - from.p_WH, turn = hand::rotation_difference(palm.q_W, from.q_WH);
  const Eigen::Vector3d none = Eigen::Vector3d::Zero();
  double share = 1.0;
  for (const world::ContactRecord& c : world_.snapshot().contacts) {
    if (c.hand != h) continue;
    const hand::ClearancePlane touched{c.n_W, c.p_W - from.p_WH, std::max(0.0, -c.depth_m)};
    share = std::min(share, hand::clearance_share(&touched, 1, none, none, move, turn));
  }
  const std::vector<std::vector<hand::ClearancePlane>>& clearance = world_.clearance(h);
  for (std::size_t j = 0; j < std::min(handles.size(), clearance.size()); ++j) {
    const Eigen::Vector3d move_j = move + turn.cross(handles[j].p_WH - from.p_WH);
    const int count = std::min(static_cast<int>(clearance[j].size()), hand::kClearancePlanes);
    share = std::min(share, hand::clearance_share(clearance[j].data(), count, none, none, move_j, turn));
  }
  if (share >= 1.0)
    hand.place(palm.p_W, palm.q_W);
  else
    hand.place(from.p_WH + share * move, hand::rotate_by(from.q_WH, share * turn));
}

void VisualStep::build_models(std::uint64_t publish_ns, double dt_s) {
  HapticSnapshot& out = snapshots_.back();
  out.hands = std::min(world_.num_hands(), kMaxHands);
  for (int h = 0; h < out.hands; ++h) {
    world_.hand(h).set_step_length(dt_s);
    if (kind_ != HandleModelKind::zoh) {
      fill_haptic_model(world_, h, scratch_, out.model[h],
                        kind_ == HandleModelKind::linearized ? hand::ContactLinearization::unilateral
                                                             : hand::ContactLinearization::held);
    } else {
      fill_held_model(world_, h, out.model[h]);
    }
    out.model[h].t_end_ns = publish_ns + static_cast<std::uint64_t>(1e9 * dt_s);
    out.model[h].step_s = dt_s;
    out.model[h].resyncs = resyncs_seen_[h];
  }
}

void VisualStep::prepare_tick_solvers() {
  if (!preparer_) return;
  HapticSnapshot& out = snapshots_.back();
  for (int h = 0; h < out.hands; ++h) preparer_->prepare(h, out.model[h]);
}

void VisualStep::recover() {
  const ProxyTargets& targets = targets_.front();
  for (int h = 0; h < world_.num_hands(); ++h) {
    hand::Hand& hand = world_.hand(h);
    // Where its proxy is if a device drives it, else where its first handle is.
    const bool driven = h < kMaxHands && targets.driven[h];
    const hand::HandleState& first = hand.handles()[0];
    hand.recover(driven ? targets.pose[h][0].p_W : first.p_WH, driven ? targets.pose[h][0].q_W : first.q_WH);
  }
}

}  // namespace hapticd::haptic
