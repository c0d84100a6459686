// The glove hand: the procedural hand meshed with separate_fingers (each finger
// its own flesh, joined to the others only through palm flesh) and driven by a
// glove's tracked frames (palm + 15 phalanges, or palm + 5 fingertips) through
// the range of a real hand: fist, spread, thumb opposition, fast taps. No
// world, no contacts, gravity off; the visual loop's stiff drive and solver.
// First the skeleton-aware mesh itself: the split, the skin's embedding, the
// tet count and the mirror image.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <numbers>
#include <numeric>
#include <string>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/press_scenario.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kMm = 0.001;
constexpr std::array<int, 4> kTargets = {350, 1700, 5000, 20000};

const ProceduralHand& cached_hand(int target, bool separate, bool left = false) {
  static std::map<std::array<int, 3>, ProceduralHand> cache;
  const std::array<int, 3> key{target, separate, left};
  auto it = cache.find(key);
  if (it == cache.end()) {
    ProceduralHandOptions options;
    options.target_tets = target;
    options.left = left;
    options.separate_fingers = separate;
    it = cache.emplace(key, make_procedural_hand(options)).first;
  }
  return it->second;
}

const ProceduralHand& split_hand(int target, bool left = false) { return cached_hand(target, true, left); }

int find_root(std::vector<int>& parent, int i) {
  while (parent[i] != i) i = parent[i] = parent[parent[i]];
  return i;
}

std::array<int, 3> face_key(const Tet& t, int skip) {
  std::array<int, 3> f;
  for (int k = 0, m = 0; k < 4; ++k) {
    if (k != skip) f[m++] = t[k];
  }
  std::sort(f.begin(), f.end());
  return f;
}

// Components of the tets with use[e] set, joined through shared faces.
int face_connected_components(const TetMesh& mesh, const std::vector<char>& use) {
  std::vector<int> parent(mesh.num_tets());
  std::iota(parent.begin(), parent.end(), 0);
  std::map<std::array<int, 3>, int> first_with_face;
  for (int e = 0; e < mesh.num_tets(); ++e) {
    if (!use[e]) continue;
    for (int skip = 0; skip < 4; ++skip) {
      auto [it, inserted] = first_with_face.try_emplace(face_key(mesh.tets[e], skip), e);
      if (!inserted) parent[find_root(parent, e)] = find_root(parent, it->second);
    }
  }
  int roots = 0;
  for (int e = 0; e < mesh.num_tets(); ++e) roots += use[e] && find_root(parent, e) == e ? 1 : 0;
  return roots;
}

// ---------------------------------------------------------------------------------------------
// The skeleton-aware mesh.

// The split keeps the default mesh's cells and tets; only nodes are copied. So the tet count
// search, the tets' shapes and the skin are the default's.
TEST(SeparateFingers, SameCellsTetsAndSkinAsTheDefaultMeshWithNodesSplit) {
  for (int target : kTargets) {
    SCOPED_TRACE(target);
    const ProceduralHand& plain = cached_hand(target, false);
    const ProceduralHand& split = split_hand(target);
    EXPECT_EQ(split.spacing, plain.spacing);
    EXPECT_NEAR(split.mesh.num_tets(), target, 0.15 * target);
    ASSERT_EQ(split.mesh.num_tets(), plain.mesh.num_tets());
    EXPECT_GT(split.mesh.num_nodes(), plain.mesh.num_nodes());
    ASSERT_EQ(static_cast<int>(split.tet_part.size()), split.mesh.num_tets());
    ASSERT_EQ(static_cast<int>(split.node_part.size()), split.mesh.num_nodes());
    EXPECT_TRUE(plain.tet_part.empty() && plain.node_part.empty());
    const double kuhn = std::pow(split.spacing, 3) / 6.0;
    int moved = 0;
    for (int e = 0; e < split.mesh.num_tets(); ++e) {
      const Tet& a = split.mesh.tets[e];
      const Tet& b = plain.mesh.tets[e];
      for (int k = 0; k < 4; ++k) moved += split.mesh.X[a[k]] == plain.mesh.X[b[k]] ? 0 : 1;
      EXPECT_NEAR(signed_volume(split.mesh.X[a[0]], split.mesh.X[a[1]], split.mesh.X[a[2]], split.mesh.X[a[3]]), kuhn,
                  1e-9 * kuhn);
    }
    EXPECT_EQ(moved, 0);
    EXPECT_EQ(split.skin_vertices, plain.skin_vertices);
    EXPECT_EQ(split.skin_triangles, plain.skin_triangles);
  }
  // Only copies: every split node sits on a node of the default mesh, and no two split nodes share
  // both a place and a part (one copy per part that uses a grid node), while every default node is used.
  for (int target : kTargets) {
    SCOPED_TRACE(target);
    const ProceduralHand& plain = cached_hand(target, false);
    const ProceduralHand& split = split_hand(target);
    std::map<std::array<double, 3>, int> plain_at;
    for (int v = 0; v < plain.mesh.num_nodes(); ++v)
      plain_at[{plain.mesh.X[v].x(), plain.mesh.X[v].y(), plain.mesh.X[v].z()}] = v;
    ASSERT_EQ(static_cast<int>(plain_at.size()), plain.mesh.num_nodes());
    std::map<std::pair<int, int>, int> copies;  // (default node, part) -> split nodes there
    std::vector<char> used(plain.mesh.num_nodes(), 0);
    for (int v = 0; v < split.mesh.num_nodes(); ++v) {
      const auto it = plain_at.find({split.mesh.X[v].x(), split.mesh.X[v].y(), split.mesh.X[v].z()});
      ASSERT_NE(it, plain_at.end()) << "split node " << v << " is on no default node";
      used[it->second] = 1;
      ++copies[{it->second, split.node_part[v]}];
    }
    EXPECT_EQ(static_cast<int>(copies.size()), split.mesh.num_nodes()) << "a node copied twice for one part";
    EXPECT_EQ(std::count(used.begin(), used.end(), 1), plain.mesh.num_nodes());
  }
}

TEST(SeparateFingers, FingersMeetOnlyThroughPalmFleshAndEachIsOnePieceOnThePalm) {
  for (int target : kTargets) {
    SCOPED_TRACE(target);
    const ProceduralHand& hand = split_hand(target);
    const TetMesh& mesh = hand.mesh;
    EXPECT_EQ(face_connected_components(mesh, std::vector<char>(mesh.num_tets(), 1)), 1);
    // A tet uses its own part's copies and shared nodes; palm tets only shared nodes.
    std::vector<unsigned> fingers_at(mesh.num_nodes(), 0);
    int foreign = 0;
    for (int e = 0; e < mesh.num_tets(); ++e) {
      const int p = hand.tet_part[e];
      ASSERT_GE(p, 0);
      ASSERT_LE(p, kHandPalmPart);
      for (int v : mesh.tets[e]) {
        foreign += hand.node_part[v] == p || hand.node_part[v] == kHandPalmPart ? 0 : 1;
        if (p != kHandPalmPart) fingers_at[v] |= 1u << p;
      }
    }
    EXPECT_EQ(foreign, 0);
    // Nodes used by two fingers are shared palm nodes, and they stay at the knuckles: no farther
    // than 6 mm beyond either finger's base joint along its proximal bone (the webs; the default
    // mesh at 1.7k fuses the long fingers up to the fingertips).
    for (int v = 0; v < mesh.num_nodes(); ++v) {
      if (std::popcount(fingers_at[v]) < 2) continue;
      EXPECT_EQ(hand.node_part[v], kHandPalmPart);
      if (target < 1700) continue;
      for (int f = 0; f < 5; ++f) {
        if (!(fingers_at[v] & (1u << f))) continue;
        const Eigen::Vector3d axis = (hand.joints[f][1] - hand.joints[f][0]).normalized();
        EXPECT_LT((mesh.X[v] - hand.joints[f][0]).dot(axis), 6 * kMm) << "finger " << f;
      }
    }
    // Each finger: one face-connected piece, sharing a face with palm flesh.
    std::map<std::array<int, 3>, int> palm_faces;
    for (int e = 0; e < mesh.num_tets(); ++e) {
      if (hand.tet_part[e] != kHandPalmPart) continue;
      for (int skip = 0; skip < 4; ++skip) palm_faces[face_key(mesh.tets[e], skip)] = e;
    }
    for (int f = 0; f < 5; ++f) {
      std::vector<char> use(mesh.num_tets());
      bool on_palm = false;
      int count = 0;
      for (int e = 0; e < mesh.num_tets(); ++e) {
        use[e] = hand.tet_part[e] == f;
        if (!use[e]) continue;
        ++count;
        for (int skip = 0; skip < 4; ++skip) on_palm = on_palm || palm_faces.count(face_key(mesh.tets[e], skip));
      }
      EXPECT_GT(count, 0) << "finger " << f;
      EXPECT_EQ(face_connected_components(mesh, use), 1) << "finger " << f;
      EXPECT_TRUE(on_palm) << "finger " << f;
    }
  }
}

// Every skin vertex follows the flesh of the part nearest to it (its finger's copies or shared
// palm nodes, never a neighbouring finger's), with exact weights; where that part's cells stop
// short of the vertex (a cell nearer the neighbour took the gap) the weights extrapolate a little.
TEST(SeparateFingers, SkinVerticesFollowTheirOwnPart) {
  for (int target : kTargets) {
    SCOPED_TRACE(target);
    const ProceduralHand& hand = split_hand(target);
    double worst_position = 0, lowest = 1;
    int wrong_part = 0, extrapolated = 0;
    for (size_t i = 0; i < hand.skin_vertices.size(); ++i) {
      const Tet& t = hand.mesh.tets[hand.skin_tet[i]];
      const Eigen::Vector4d& w = hand.skin_bary[i];
      EXPECT_NEAR(w.sum(), 1.0, 1e-12);
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int k = 0; k < 4; ++k) p += w[k] * hand.mesh.X[t[k]];
      worst_position = std::max(worst_position, (p - hand.skin_vertices[i]).norm());
      const int part = procedural_hand_nearest_part(hand.skin_vertices[i]);
      for (int v : t) wrong_part += hand.node_part[v] == part || hand.node_part[v] == kHandPalmPart ? 0 : 1;
      lowest = std::min(lowest, w.minCoeff());
      extrapolated += w.minCoeff() < -1e-9 ? 1 : 0;
    }
    EXPECT_LT(worst_position, 1e-12);
    EXPECT_EQ(wrong_part, 0);
    // A little: the gap a neighbour's cell took is one cell, so a vertex lies less than a tet's height
    // beyond its tet's face (weight > -1), and few vertices are in such gaps.
    std::printf("[split skin] %d tets: %d of %zu skin vertices extrapolated, lowest weight %.3f\n", target,
                extrapolated, hand.skin_vertices.size(), lowest);
    EXPECT_GT(lowest, -1.0);
    EXPECT_LT(extrapolated, 0.02 * static_cast<double>(hand.skin_vertices.size()));
  }
}

TEST(SeparateFingers, LeftHandIsTheMirrorImage) {
  const ProceduralHand& right = split_hand(1700);
  const ProceduralHand& left = split_hand(1700, true);
  ASSERT_EQ(left.mesh.num_nodes(), right.mesh.num_nodes());
  ASSERT_EQ(left.mesh.num_tets(), right.mesh.num_tets());
  EXPECT_EQ(left.node_part, right.node_part);
  EXPECT_EQ(left.tet_part, right.tet_part);
  EXPECT_EQ(left.skin_tet, right.skin_tet);
  const Eigen::Vector3d m(-1.0, 1.0, 1.0);
  for (int i = 0; i < left.mesh.num_nodes(); ++i) EXPECT_EQ(left.mesh.X[i], right.mesh.X[i].cwiseProduct(m));
  for (const Tet& t : left.mesh.tets) {
    EXPECT_GT(signed_volume(left.mesh.X[t[0]], left.mesh.X[t[1]], left.mesh.X[t[2]], left.mesh.X[t[3]]), 0.0);
  }
  for (size_t i = 0; i < left.skin_vertices.size(); ++i) {
    Eigen::Vector3d p = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) p += left.skin_bary[i][k] * left.mesh.X[left.mesh.tets[left.skin_tet[i]][k]];
    EXPECT_LT((p - left.skin_vertices[i]).norm(), 1e-12);
    EXPECT_EQ(procedural_hand_nearest_part(left.skin_vertices[i], true),
              procedural_hand_nearest_part(right.skin_vertices[i]));
  }
}

// ---------------------------------------------------------------------------------------------
// The glove: handle targets from joint angles.

struct Glove {
  const ProceduralHand* hand = nullptr;
  int m = 0;
  std::unique_ptr<HandModel> model;
  HandState state;
  std::unique_ptr<CoupledSolver> solver;
  HandJointAngles angles;  // of the current targets
  // Over the run so far.
  long steps = 0, failed_steps = 0;
  double step_ms_sum = 0, step_ms_max = 0, min_det = 1e300, max_energy = 0, max_error = 0;
  int max_inverted = 0;  // at any step
  // Per tet: whether the run's postures may invert it (joint_flesh()); the most inverted tets
  // outside that set at any step, and every tet inverted at some step.
  std::vector<char> may_invert;
  int max_inverted_elsewhere = 0;
  std::vector<char> ever_inverted;
};

// Joint flesh (procedural_joint_stiffness's classification, from the hand's geometry alone): a tet
// within the band of a joint or with nodes on two bones, the flesh the 16-handle glove softens.
// If `finger` >= 0, only that finger's joint flesh.
std::vector<char> joint_flesh(const ProceduralHand& hand, int finger = -1) {
  const std::vector<double> k = procedural_joint_stiffness(hand, 16, 0.5);
  std::vector<char> joint(k.size());
  for (size_t e = 0; e < k.size(); ++e) joint[e] = k[e] < 1 && (finger < 0 || hand.tet_part[e] == finger);
  return joint;
}

// m handles as the glove server makes them (procedural_handles), the visual loop's almost
// kinematic drive (kProxyDrive), default flesh at the hand's mass, gravity off.
std::unique_ptr<Glove> make_glove(const ProceduralHand& hand, int m, bool soft_joints = true) {
  single_threaded_cholmod();  // as the visual loop runs it
  auto g = std::make_unique<Glove>();
  g->hand = &hand;
  g->m = m;
  HandConfig config;
  config.gravity_m_s2.setZero();
  config.drive = DriveParams{1e6, 1e3, 1e3, 10.0};
  config.handles = procedural_handles(hand, m);
  if (soft_joints) config.element_stiffness = procedural_joint_stiffness(hand, m, kGloveJointStiffness);
  config.material.density_kg_m3 = embedding_density(hand, config.material.density_kg_m3);
  g->model = std::make_unique<HandModel>(hand.mesh, config);
  g->state = make_rest_state(*g->model);
  g->solver = make_solver(SolverKind::schur_cholmod);
  g->angles = rest_joint_angles();
  g->may_invert = joint_flesh(hand);
  g->ever_inverted.assign(hand.mesh.tets.size(), 0);
  return g;
}

// Handle targets for the tracked frames at `angles` (palm fixed at the hand frame), with the
// velocity of getting there from the current targets in dt.
void set_angles(Glove& g, const HandJointAngles& angles, double dt) {
  const std::vector<HandleTarget> targets = posture_targets(*g.hand, *g.model, angles, Eigen::Vector3d::Zero(),
                                                            Eigen::Quaterniond::Identity(), false);
  for (int j = 0; j < g.m; ++j) {
    HandleTarget t = targets[j];
    const HandleTarget& last = g.state.targets[j];
    t.v_W = (t.p_W - last.p_W) / dt;
    t.w_W = rotation_difference(t.q_W, last.q_W) / dt;
    ASSERT_TRUE(set_target(g.state, j, t));
  }
  g.angles = angles;
}

// Largest distance of a handle from its target, m.
double handle_error(const Glove& g) {
  double e = 0;
  for (int j = 0; j < g.m; ++j) e = std::max(e, (g.state.handles[j].p_WH - g.state.targets[j].p_W).norm());
  return e;
}

int inverted(const Glove& g) {
  int n = 0;
  for (int e = 0; e < g.model->fem().num_tets(); ++e)
    n += g.model->fem().deformation_gradient(e, g.state.x).determinant() > 0 ? 0 : 1;
  return n;
}

// det F of every tet.
std::vector<double> dets(const Glove& g) {
  std::vector<double> d(g.model->fem().num_tets());
  for (int e = 0; e < g.model->fem().num_tets(); ++e) d[e] = g.model->fem().deformation_gradient(e, g.state.x).determinant();
  return d;
}

// Tets inverted in one of a and b (det F of each tet) and not in the other, leaving out those within
// kCrease of flat in both: at a fold's crease they creep across det F = 0 for seconds of a hold
// (measured: 3 of ~75 in the held fist still change between 1 and 3 s).
constexpr double kCrease = 0.05;
std::vector<int> inverted_in_one_only(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<int> differ;
  for (size_t e = 0; e < a.size(); ++e)
    if ((a[e] <= 0) != (b[e] <= 0) && std::max(std::abs(a[e]), std::abs(b[e])) > kCrease) differ.push_back(static_cast<int>(e));
  return differ;
}

void advance(Glove& g) {
  if (step(*g.model, g.state, *g.solver) != StepStatus::ok) ++g.failed_steps;
  ++g.steps;
  g.step_ms_sum += g.state.timings.total_ms;
  g.step_ms_max = std::max(g.step_ms_max, g.state.timings.total_ms);
  int count = 0, elsewhere = 0;
  for (int e = 0; e < g.model->fem().num_tets(); ++e) {
    const double det = g.model->fem().deformation_gradient(e, g.state.x).determinant();
    g.min_det = std::min(g.min_det, det);
    if (det > 0) continue;
    ++count;
    elsewhere += g.may_invert[e] ? 0 : 1;
    g.ever_inverted[e] = 1;
  }
  g.max_inverted = std::max(g.max_inverted, count);
  g.max_inverted_elsewhere = std::max(g.max_inverted_elsewhere, elsewhere);
  g.max_energy = std::max(g.max_energy, total_energy(*g.model, g.state));
  g.max_error = std::max(g.max_error, handle_error(g));
}

double dt(const Glove& g) { return g.model->config().dt_s; }

HandJointAngles blend(const HandJointAngles& a, const HandJointAngles& b, double s) {
  return HandJointAngles::from_vector((1.0 - s) * a.vector() + s * b.vector());
}

// Targets from the current angles to `to` in `seconds`, eased (at rest at both ends), one step each.
void move_to(Glove& g, const HandJointAngles& to, double seconds) {
  const HandJointAngles from = g.angles;
  const int n = static_cast<int>(std::lround(seconds / dt(g)));
  for (int k = 1; k <= n; ++k) {
    set_angles(g, blend(from, to, 0.5 * (1.0 - std::cos(std::numbers::pi * k / n))), dt(g));
    advance(g);
  }
}

void hold(Glove& g, double seconds) {
  const int n = static_cast<int>(std::lround(seconds / dt(g)));
  for (int k = 0; k < n; ++k) {
    set_angles(g, g.angles, dt(g));
    advance(g);
  }
}

double energy(const Glove& g) { return total_energy(*g.model, g.state); }

// The reference of a held posture: a fresh glove of m handles brought to it 4x slower than the
// tests' 0.5 s moves and held kSettle. A held posture is an equilibrium of the flesh, which does not
// remember how fast it got there: the same elements must be inverted (inverted_in_one_only).
constexpr double kSettle = 3.0;  // s
std::vector<double> dets_when_reached_slowly(const ProceduralHand& hand, int m, const HandJointAngles& angles) {
  auto g = make_glove(hand, m);
  move_to(*g, angles, 2.0);
  hold(*g, kSettle);
  return dets(*g);
}

// Largest drive force on a handle, N: what holding the flesh in this posture costs the tracked frame.
double largest_drive_force(const Glove& g) {
  double f = 0;
  for (int j = 0; j < g.m; ++j)
    f = std::max(f, g.model->config().drive.stiffness_n_m * (g.state.targets[j].p_W - g.state.handles[j].p_WH).norm());
  return f;
}

void print_run(const char* what, const Glove& g) {
  std::printf("[glove] %s: %d tets, %d handles, %ld steps: %.2f ms/step mean, %.2f max; largest handle error "
              "%.3f mm; at worst %d inverted tets (smallest det F %.3f); largest energy %.3f J; %ld failed steps, "
              "%ld resets\n",
              what, g.model->fem().num_tets(), g.m, g.steps, g.step_ms_sum / static_cast<double>(g.steps),
              g.step_ms_max, g.max_error / kMm, g.max_inverted, g.min_det, g.max_energy, g.failed_steps,
              g.state.resets);
  std::map<int, int> by_part;
  int joint = 0, inverted_joint = 0, total = 0;
  for (size_t e = 0; e < g.ever_inverted.size(); ++e) {
    joint += g.may_invert[e];
    if (!g.ever_inverted[e]) continue;
    ++total, ++by_part[g.hand->tet_part[e]];
    inverted_joint += g.may_invert[e];
  }
  std::printf("[glove] tets inverted at some step: %d (%d of the %d that may), by part:", total, inverted_joint, joint);
  for (const auto& [part, n] : by_part) std::printf(" %d: %d", part, n);
  std::printf("; at worst %d at once outside them\n", g.max_inverted_elsewhere);
}

// ---------------------------------------------------------------------------------------------
// Postures (rad): abduction, then flexion of the three joints, per finger.

HandJointAngles fist() {
  HandJointAngles a;
  a.finger[0] = {-20 * kDeg, 35 * kDeg, 45 * kDeg, 50 * kDeg};  // thumb folded over the middle phalanges
  for (int f = 1; f < 5; ++f) a.finger[f] = {(-4.0 + 4.0 * (f - 1)) * kDeg, 85 * kDeg, 100 * kDeg, 65 * kDeg};
  return a;
}

HandJointAngles spread() {
  HandJointAngles a;
  a.finger[0] = {-80 * kDeg, -10 * kDeg, 0.0, 0.0};
  const std::array<double, 4> yaw = {-25, 0, 18, 35};
  for (int f = 1; f < 5; ++f) a.finger[f] = {yaw[f - 1] * kDeg, -10 * kDeg, 0.0, 0.0};  // splayed, slightly hyperextended
  return a;
}

// The thumb's angles that put its tip at `target` (m, hand frame), the others at rest: coordinate
// descent from the rest angles, staying within the thumb's range.
HandJointAngles thumb_tip_at(const Eigen::Vector3d& target) {
  HandJointAngles a = rest_joint_angles();
  const std::array<double, 4> lo = {-70 * kDeg, -10 * kDeg, 0.0, 0.0}, hi = {40 * kDeg, 80 * kDeg, 70 * kDeg, 80 * kDeg};
  auto cost = [&](const HandJointAngles& x) { return (skeleton_pose(x).joints[0][3] - target).squaredNorm(); };
  for (double step_size = 10 * kDeg; step_size > 0.01 * kDeg; step_size *= 0.5) {
    for (bool improved = true; improved;) {
      improved = false;
      for (int k = 0; k < 4; ++k) {
        for (double s : {-step_size, step_size}) {
          HandJointAngles b = a;
          b.finger[0][k] = std::clamp(b.finger[0][k] + s, lo[k], hi[k]);
          if (cost(b) < cost(a) - 1e-14) a = b, improved = true;
        }
      }
    }
  }
  return a;
}

// ---------------------------------------------------------------------------------------------
// Runs.

// Each handle holds only its own part's nodes (the palm's, or its finger's: a
// sphere alone would take the neighbouring fingers' copies of a grid node), and
// no node is in two handles.
void expect_handles_on_their_own_parts(const Glove& g) {
  std::vector<int> taken(g.hand->mesh.num_nodes(), 0);
  for (int j = 0; j < g.m; ++j) {
    const int own = j == 0 ? kHandPalmPart : (g.m == 6 ? j - 1 : (j - 1) / 3);
    EXPECT_FALSE(g.model->handles()[j].nodes.empty()) << j;
    for (int v : g.model->handles()[j].nodes) {
      EXPECT_EQ(g.hand->node_part[v], own) << g.model->handles()[j].name << " node " << v;
      ++taken[v];
    }
  }
  EXPECT_LE(*std::max_element(taken.begin(), taken.end()), 1);
}

// Each cycle: open -> fist -> open -> spread -> open, 0.5 s per move, 0.15 s holds.
TEST(GloveHand, SixteenHandlesTwentyFistAndSpreadCyclesLeaveNoInvertedElement) {
  const ProceduralHand& hand = split_hand(1700);
  auto g = make_glove(hand, 16);
  expect_handles_on_their_own_parts(*g);
  std::vector<double> fist_energy, spread_energy;
  double hold_error = 0;
  int fist_inverted = 0;
  const std::vector<double> slow_fist = dets_when_reached_slowly(hand, 16, fist());
  for (int cycle = 0; cycle < 20; ++cycle) {
    SCOPED_TRACE(cycle);
    move_to(*g, fist(), 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    fist_energy.push_back(energy(*g));
    fist_inverted = std::max(fist_inverted, inverted(*g));
    move_to(*g, rest_joint_angles(), 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    EXPECT_EQ(inverted(*g), 0);
    move_to(*g, spread(), 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    spread_energy.push_back(energy(*g));
    EXPECT_EQ(inverted(*g), 0);
    move_to(*g, rest_joint_angles(), 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    // After each cycle: every element the fist inverted has come back and the flesh is at rest.
    EXPECT_EQ(inverted(*g), 0);
    EXPECT_LT(energy(*g), 1e-6);
  }
  // Then a fist held as long as the reference: cycling left no memory, the elements it inverts are
  // those of a fresh hand reaching the fist slowly.
  move_to(*g, fist(), 0.5);
  hold(*g, kSettle);
  EXPECT_EQ(inverted_in_one_only(dets(*g), slow_fist), std::vector<int>{});
  move_to(*g, rest_joint_angles(), 0.5);
  hold(*g, 0.15);
  EXPECT_EQ(inverted(*g), 0);
  print_run("20 fist + spread cycles", *g);
  std::printf("[glove] largest handle error at the end of a hold %.3g mm; held fist: %d inverted tets, "
              "%.4f J (cycle 1), %.4f J (cycle 20); held spread: %.4f J, %.4f J\n",
              hold_error / kMm, fist_inverted, fist_energy.front(), fist_energy.back(), spread_energy.front(),
              spread_energy.back());
  EXPECT_LT(hold_error, 2 * kMm);
  EXPECT_EQ(g->failed_steps, 0);
  EXPECT_EQ(g->state.resets, 0);
  // Bounded energy: the same postures hold the same energy every cycle, the motion little more.
  for (size_t k = 1; k < fist_energy.size(); ++k) {
    EXPECT_NEAR(fist_energy[k], fist_energy.front(), 1e-3 * fist_energy.front());
    EXPECT_NEAR(spread_energy[k], spread_energy.front(), 1e-3 * spread_energy.front());
  }
  EXPECT_LT(g->max_energy, 1.05 * fist_energy.front());
  // Each phalanx's flesh is carried by its own handle, so only joint flesh (bridging two bones) can
  // fold far enough to invert: at no step is an element elsewhere inverted.
  EXPECT_EQ(g->max_inverted_elsewhere, 0);
}

// The skeleton's thumb flexes in one plane turned by its abduction, so the tip reaches the little
// finger's base only by abducting the whole thumb (its metacarpal, the thenar flesh) 93 degrees
// across the palm and back.
TEST(GloveHand, SixteenHandlesThumbOppositionToTheLittleFingerBaseAndBack) {
  const ProceduralHand& hand = split_hand(1700);
  // The thumb tip 1 cm under the palm's skin at the little finger's base joint.
  const Eigen::Vector3d target = hand.joints[4][0] + Eigen::Vector3d(0, -0.003, -0.0225);
  const HandJointAngles opposed = thumb_tip_at(target);
  ASSERT_LT((skeleton_pose(opposed).joints[0][3] - target).norm(), 2 * kMm);
  auto g = make_glove(hand, 16);
  g->may_invert = joint_flesh(hand, 0);  // the thumb's: the only finger that moves
  double hold_error = 0;
  int held_inverted = 0;
  const std::vector<double> slow_opposed = dets_when_reached_slowly(hand, 16, opposed);
  for (int k = 0; k < 5; ++k) {
    SCOPED_TRACE(k);
    move_to(*g, opposed, 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    held_inverted = std::max(held_inverted, inverted(*g));
    move_to(*g, rest_joint_angles(), 0.5);
    hold(*g, 0.15);
    hold_error = std::max(hold_error, handle_error(*g));
    EXPECT_EQ(inverted(*g), 0);
    EXPECT_LT(energy(*g), 1e-6);
  }
  move_to(*g, opposed, 0.5);
  hold(*g, kSettle);
  EXPECT_EQ(inverted_in_one_only(dets(*g), slow_opposed), std::vector<int>{}) << "as when reached slowly";
  move_to(*g, rest_joint_angles(), 0.5);
  hold(*g, 0.15);
  EXPECT_EQ(inverted(*g), 0);
  print_run("5 thumb oppositions", *g);
  std::printf("[glove] thumb angles %.0f %.0f %.0f %.0f deg; largest handle error at the end of a hold %.3g mm; "
              "%d inverted tets in the held opposition\n",
              opposed.finger[0][0] / kDeg, opposed.finger[0][1] / kDeg, opposed.finger[0][2] / kDeg,
              opposed.finger[0][3] / kDeg, hold_error / kMm, held_inverted);
  EXPECT_LT(hold_error, 2 * kMm);
  EXPECT_EQ(g->failed_steps, 0);
  EXPECT_EQ(g->state.resets, 0);
  // Only the thumb moves, and its phalanges' flesh rides with their handles: at no step is an element
  // inverted outside the thumb's joint flesh.
  EXPECT_EQ(g->max_inverted_elsewhere, 0);
}

// Index taps (flexing 45, 40 and 20 degrees at its three joints) at 4 Hz for 2 s, then 6 Hz for 2 s.
TEST(GloveHand, SixteenHandlesFastIndexTapsAtFourAndSixHertz) {
  const ProceduralHand& hand = split_hand(1700);
  auto g = make_glove(hand, 16);
  g->may_invert = joint_flesh(hand, finger_index("index"));  // the only finger that moves
  const HandJointAngles rest = rest_joint_angles();
  HandJointAngles tap = rest;
  tap.finger[1] = {rest.finger[1][0], 45 * kDeg, 40 * kDeg, 20 * kDeg};
  double hold_error = 0;
  for (double hz : {4.0, 6.0}) {
    SCOPED_TRACE(hz);
    const int n = static_cast<int>(std::lround(2.0 / dt(*g)));
    for (int k = 1; k <= n; ++k) {
      set_angles(*g, blend(rest, tap, 0.5 * (1.0 - std::cos(2 * std::numbers::pi * hz * k * dt(*g)))), dt(*g));
      advance(*g);
    }
    hold(*g, 0.25);
    hold_error = std::max(hold_error, handle_error(*g));
    EXPECT_EQ(inverted(*g), 0);
    EXPECT_LT(energy(*g), 1e-6);
  }
  print_run("index taps, 2 s at 4 Hz and 2 s at 6 Hz", *g);
  std::printf("[glove] largest handle error at the end of a hold %.3g mm\n", hold_error / kMm);
  EXPECT_LT(hold_error, 2 * kMm);
  EXPECT_EQ(g->failed_steps, 0);
  EXPECT_EQ(g->state.resets, 0);
  // Only the index moves, its phalanges' flesh riding with their handles: at no step is an element
  // inverted outside the index's joint flesh (none is left: above).
  EXPECT_EQ(g->max_inverted_elsewhere, 0);
}

// Per-bone flesh joined by soft joints (procedural_joint_stiffness): a held fist stores a tenth of
// the elastic work of flesh as stiff at the joints as elsewhere, and the tracked frames' drives
// hold it with a fraction of the force, so a glove frame feels the flesh little beyond contact.
TEST(GloveHand, SoftJointsCutTheWorkAndTheForceOfAFist) {
  const ProceduralHand& hand = split_hand(1700);
  double fist_energy[2], fist_force[2];
  for (bool soft : {false, true}) {
    auto g = make_glove(hand, 16, soft);
    move_to(*g, fist(), 0.5);
    hold(*g, 0.3);
    fist_energy[soft] = energy(*g);
    fist_force[soft] = largest_drive_force(*g);
  }
  std::printf("[glove] held fist, joints as stiff as the flesh / soft (x%.2f): %.3f / %.3f J, largest frame force "
              "%.2f / %.2f N\n",
              kGloveJointStiffness, fist_energy[0], fist_energy[1], fist_force[0], fist_force[1]);
  EXPECT_LT(fist_energy[1], 0.15 * fist_energy[0]);
  EXPECT_LT(fist_force[1], 0.3 * fist_force[0]);
}

// Palm + 5 fingertips: the proximal and middle phalanges are free flesh, bent by the fingertips alone.
TEST(GloveHand, SixHandlesReachAFistWithTheFingertips) {
  const ProceduralHand& hand = split_hand(1700);
  auto g = make_glove(hand, 6);
  expect_handles_on_their_own_parts(*g);
  int fist_inverted = 0;
  double fist_error = 0;
  const std::vector<double> slow_fist = dets_when_reached_slowly(hand, 6, fist());
  for (int k = 0; k < 3; ++k) {
    SCOPED_TRACE(k);
    move_to(*g, fist(), 0.5);
    hold(*g, 0.5);  // the free phalanges settle within it (after 0.25 s, 2 of the 17 had not yet inverted)
    fist_error = std::max(fist_error, handle_error(*g));
    fist_inverted = std::max(fist_inverted, inverted(*g));
    EXPECT_EQ(inverted_in_one_only(dets(*g), slow_fist), std::vector<int>{}) << "as when reached slowly";
    move_to(*g, rest_joint_angles(), 0.5);
    hold(*g, 0.25);
    EXPECT_EQ(inverted(*g), 0);
    EXPECT_LT(energy(*g), 1e-6);
  }
  print_run("6 handles, 3 fists", *g);
  std::printf("[glove] largest fingertip handle error in the held fist %.3g mm; %d inverted tets there (%ld reached "
              "in 2 s)\n",
              fist_error / kMm, fist_inverted, std::count_if(slow_fist.begin(), slow_fist.end(), [](double d) { return d <= 0; }));
  EXPECT_LT(fist_error, 2 * kMm);
  EXPECT_EQ(g->failed_steps, 0);
  EXPECT_EQ(g->state.resets, 0);
}

}  // namespace
}  // namespace hapticd::hand
