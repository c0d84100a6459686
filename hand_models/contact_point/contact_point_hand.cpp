#include "hand_models/contact_point/contact_point_hand.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/rigid_handle.hpp"
#include "hand_models/shape_probes.hpp"

namespace hapticd::hand::contact_point {
namespace {

bool thumb_or_palm(int s) { return s == 0 || (s - 1) / 3 == 0; }

// The pair's Coulomb coefficient: the geometric mean, as the world's other contacts take it.
double pair(double a, double b) { return std::sqrt(std::max(a, 0.0) * std::max(b, 0.0)); }

const Eigen::Vector3d kPalmHalf(kPalmHalfWidth_m, kPalmHalfLength_m, kPalmHalfThickness_m);

// A sample belongs to its contact's surface while their normals are within 60 degrees.
constexpr double kSameSurfaceCosine = 0.5;

}  // namespace

ContactPointHand::ContactPointHand(const ContactPointHandConfig& config, const Eigen::Vector3d& p_W,
                                   const Eigen::Quaterniond& q_W)
    : config_(config),
      handles_(static_cast<std::size_t>(std::max(config.handles, 1))),
      device_v_(handles_.size(), Vector6::Zero()) {
  if (config.handles != 1 && config.handles != 1 + kHandFingers && config.handles != 1 + kHandPhalanges)
    throw std::invalid_argument(
        "the contact-point hand is driven by its palm (1 handle, a stylus) or by a glove's palm and 5 distal "
        "phalanges (6) or 15 phalanges (16), not " +
        std::to_string(config.handles) + " handles");
  const ContactPointParams& p = config.params;
  if (!(p.gamma_n_m > 0) || !std::isfinite(p.gamma_n_m) || !(p.threshold_m >= 0) || !(p.threshold_m < 0.05) ||
      p.samples < 1 || p.samples > kMaxContactSamples || !(p.sample_radius_m >= 0) || !(p.wide_sample_radius_m >= 0) ||
      !(p.sample_radius_m < 0.05) || !(p.wide_sample_radius_m < 0.05) || !(p.lookahead_m >= p.threshold_m) ||
      !(p.lookahead_m < 0.1))
    throw std::invalid_argument(
        "contact-point hand: gamma must be positive and finite, the threshold in [0, 5 cm), 1 to " +
        std::to_string(kMaxContactSamples) +
        " samples, their radii in [0, 5 cm) and the lookahead in [threshold, 10 cm)");
  rest_pose_ = skeleton_pose(rest_joint_angles(), config.left);
  pose_ = rest_pose_;
  probes_S_[0] = box_probes(kPalmHalf);
  for (int f = 0; f < kHandFingers; ++f) {
    const FingerGeometry& g = finger_geometry()[f];
    for (int k = 0; k < 3; ++k) {
      const int i = 3 * f + k;
      radius_[i] = 0.5 * (g.radius[k] + g.radius[k + 1]);
      // Joint to joint about the segment's midpoint; the distal's round end at the fingertip.
      half_length_[i] = 0.5 * g.length[k];
      const double hi = k < 2 ? half_length_[i] : half_length_[i] - radius_[i];
      probes_S_[1 + i] = capsule_probes(-half_length_[i], hi, radius_[i]);
    }
  }
  tracked_frames::place(handles_, p_W, q_W.normalized(), rest_pose_);
  pose_ = rest_pose_;
}

HandleInfo ContactPointHand::handle_info(int, int) const { return tracked_frames::info(config_.handle_mass_kg); }

bool ContactPointHand::set_target(int j, const HandleTarget& target) {
  if (!target.v_device_W.allFinite() || !target.w_device_W.allFinite() || !tracked_frames::set(handles_, j, target))
    return false;
  device_v_[static_cast<std::size_t>(j)] << target.v_device_W, target.w_device_W;
  update_posture();
  return true;
}

void ContactPointHand::place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) {
  tracked_frames::place(handles_, p_W, q_W.normalized(), rest_pose_);
  for (Vector6& v : device_v_) v.setZero();
  pose_ = rest_pose_;
  angles_ = rest_joint_angles();
  clear_contacts();
}

void ContactPointHand::clear_contacts() {
  for (Contact& c : contacts_) c = Contact{};
  has_last_ = false;  // a placed hand did not sweep from where it was
}

void ContactPointHand::recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) {
  ++resets_;
  bool whole = true;
  for (const HandleState& h : handles_) whole = whole && h.p_WH.allFinite() && h.q_WH.coeffs().allFinite();
  if (whole) {
    clear_contacts();
  } else if (fallback_p_W.allFinite() && fallback_q_W.coeffs().allFinite()) {
    place(fallback_p_W, fallback_q_W);
  } else {
    place(Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  }
}

int ContactPointHand::shape_handle(int s) const {
  if (num_handles() == 1 || s == 0) return 0;
  if (num_handles() == 1 + kHandPhalanges) return s;
  return (s - 1) % 3 == 2 ? 1 + (s - 1) / 3 : 0;  // 6 frames: a distal on its frame, the others on the palm
}

Eigen::Isometry3d ContactPointHand::shape_pose(int s) const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  const int j = shape_handle(s);
  if (j > 0 || s == 0) {  // on its own frame
    const HandleState& h = handles_[static_cast<std::size_t>(j)];
    T.linear() = h.q_WH.toRotationMatrix();
    T.translation() = h.p_WH;
    return T;
  }
  const HandleState& palm = handles_[0];  // placed on the palm in the posture the frames give
  T.linear() = palm.q_WH * pose_.R[s - 1];
  T.translation() = palm.p_WH + palm.q_WH * pose_.centre[s - 1];
  return T;
}

void ContactPointHand::update_posture() {
  if (num_handles() != 1 + kHandFingers) return;  // a stylus's fingers rest; a 16-frame glove's are tracked
  std::array<Eigen::Matrix3d, kHandFingers> R;
  const Eigen::Matrix3d palm_T = handles_[0].q_WH.toRotationMatrix().transpose();
  for (int f = 0; f < kHandFingers; ++f) R[f] = palm_T * handles_[1 + f].q_WH.toRotationMatrix();
  angles_ = joint_angles_from_distal(R, config_.left, &angles_);
  pose_ = skeleton_pose(angles_, config_.left);
}

Eigen::Vector3d ContactPointHand::project_to_surface(int s, const Eigen::Vector3d& p) const {
  if (s == 0) {
    Eigen::Vector3d q = p.cwiseMax(-kPalmHalf).cwiseMin(kPalmHalf);
    if ((q - p).squaredNorm() > 0) return q;  // outside: the clamp is on the surface
    // Inside: out through the nearest face.
    const Eigen::Vector3d gap = kPalmHalf - p.cwiseAbs();
    int axis = 0;
    gap.minCoeff(&axis);
    q[axis] = p[axis] >= 0 ? kPalmHalf[axis] : -kPalmHalf[axis];
    return q;
  }
  const int i = s - 1, k = i % 3;
  const double lo = -half_length_[i], hi = k < 2 ? half_length_[i] : half_length_[i] - radius_[i];
  const Eigen::Vector3d a(0, std::clamp(p.y(), lo, hi), 0);
  Eigen::Vector3d d = p - a;
  if (d.norm() < 1e-12) d = Eigen::Vector3d::UnitZ() * -1.0;  // on the axis: the palmar side
  return a + radius_[i] * d.normalized();
}

int ContactPointHand::probe(int s, const RigidObjects& objects, double margin_m, Eigen::Vector3d& p_S, double& depth_m,
                            Eigen::Vector3d& n_W) const {
  const Eigen::Isometry3d T = shape_pose(s);
  int best = -1;
  double best_depth = -margin_m;
  for (int o = 0; o < objects.object_count(); ++o)
    for (const Eigen::Vector3d& q : probes_S_[s]) {
      double d;
      Eigen::Vector3d n;
      if (!objects.surface_near(o, T * q, margin_m, d, n) || !(d > best_depth)) continue;
      best = o, best_depth = d, p_S = q, n_W = n;
    }
  depth_m = best_depth;
  if (best < 0) return best;
  // A shape lying along a face touches it with many probes at once (a capsule along a table, the
  // palm flat on it): the contact centres on those within kFlatTolerance_m of the deepest.
  constexpr double kFlatTolerance_m = 5e-4;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  int count = 0;
  for (const Eigen::Vector3d& q : probes_S_[s]) {
    double d;
    Eigen::Vector3d n;
    if (objects.surface_near(best, T * q, margin_m + kFlatTolerance_m, d, n) && d > best_depth - kFlatTolerance_m)
      sum += q, ++count;
  }
  const Eigen::Vector3d centre = project_to_surface(s, sum / count);
  double d;
  Eigen::Vector3d n;
  if (count > 1 && objects.surface_near(best, T * centre, margin_m + kFlatTolerance_m, d, n) &&
      d > best_depth - kFlatTolerance_m)
    p_S = centre, depth_m = d, n_W = n;
  return best;
}

void ContactPointHand::make_contact(int s, int object, const Eigen::Vector3d& p_S, const Eigen::Vector3d& n_W,
                                    const RigidObjects& objects) {
  const ContactPointParams& prm = config_.params;
  const Eigen::Isometry3d T = shape_pose(s), T_O = objects.object_pose(object), T_OW = T_O.inverse();
  const double rho = thumb_or_palm(s) ? prm.wide_sample_radius_m : prm.sample_radius_m;
  const Eigen::Vector3d n_S = T.linear().transpose() * n_W;
  const Eigen::Vector3d t1 = n_S.unitOrthogonal(), t2 = n_S.cross(t1);
  Contact c;
  c.object = object;
  c.mu_static = pair(config_.friction_static, objects.object_friction_static(object));
  c.mu_dynamic = pair(config_.friction, objects.object_friction(object));
  // The samples on a ring around the probe point (a symmetric area: no moment about its centre from
  // an even load), each put on the shape's surface, each with the object's surface point nearest to it.
  for (int k = 0; k < prm.samples; ++k) {
    const double phi = 2 * M_PI * k / prm.samples;
    const Eigen::Vector3d q =
        prm.samples == 1 ? p_S : project_to_surface(s, p_S + rho * (std::cos(phi) * t1 + std::sin(phi) * t2));
    const Eigen::Vector3d q_W = T * q;
    double d;
    Eigen::Vector3d n, C;
    if (!objects.surface_near(object, q_W, prm.threshold_m + 2 * rho + 0.01, d, n)) continue;
    C = q_W + d * n;
    // A point already deep inside: where it entered the surface since the last step, when it did.
    Eigen::Vector3d hit, n_hit;
    if (d > prm.threshold_m && has_last_ && objects.ray_hit(object, last_T_[s] * q, q_W, hit, n_hit))
      C = hit, n = n_hit;
    // A sample whose nearest surface faces another way than the contact's (the far side of a thin
    // part, a bulge's underside beside the contact) is another part of the object (3.5's occlusion
    // test by the normals): a plane there would push the hand sideways or pull it in.
    if (n.dot(n_W) < kSameSurfaceCosine) continue;
    Sample& sample = c.samples[c.count++];
    sample.p_S = q;
    sample.C_O = T_OW * C;
    sample.n_O = T_OW.linear() * n;
  }
  if (c.count > 0) contacts_[s] = c;
}

void ContactPointHand::slide(Sample& sample, double mu_dynamic, const Eigen::Isometry3d& T_O,
                             const Eigen::Vector3d& p_W, int object, const RigidObjects& objects) const {
  const Eigen::Vector3d C = T_O * sample.C_O, n = T_O.linear() * sample.n_O;
  const Eigen::Vector3d target = slide_target(mu_dynamic, C, n, p_W);
  if (target == C) return;
  // Section 3.5: from just outside the surface, a ray finds it; cast along the old normal (the paper
  // casts toward the hand point, which on a flat face lands short of the target, between it and p).
  const double offset = std::max(config_.params.threshold_m, 1e-3);
  Eigen::Vector3d C_new, n_new;
  double d;
  if (!objects.ray_hit(object, target + offset * n, target - offset * n, C_new, n_new)) {
    // The ray missed (the target is past an edge): the nearest surface point.
    if (!objects.surface_near(object, target, 0.01, d, n_new)) return;
    C_new = target + d * n_new;
  }
  if (n_new.dot(n) <= 0) return;  // an occluding part of the object (3.5, rays R4 and R5 of Fig. 3)
  const Eigen::Isometry3d T_OW = T_O.inverse();
  sample.C_O = T_OW * C_new;
  sample.n_O = T_OW.linear() * n_new;
}

ContactForce ContactPointHand::slid_force(const Contact& c, Sample& sample, const Eigen::Isometry3d& T_O,
                                          const Eigen::Vector3d& p_W) const {
  const double gamma = config_.params.gamma_n_m / c.count;
  ContactForce f = contact_force(gamma, c.mu_static, c.mu_dynamic, T_O * sample.C_O, T_O.linear() * sample.n_O, p_W);
  if (f.state != ContactState::sliding) return f;
  // The point slides first (section 3.5), to where its spring is the kinetic force (eq. 5); the
  // object then takes that spring as a stuck one's, implicitly. A kinetic force applied as a
  // constant overshot: a 100 g box held by sliding fingers swung 3 mm up and down every step.
  slide(sample, c.mu_dynamic, T_O, p_W, c.object, *objects_);
  f = contact_force(gamma, c.mu_static, c.mu_dynamic, T_O * sample.C_O, T_O.linear() * sample.n_O, p_W);
  f.state = ContactState::sliding;
  return f;
}

void ContactPointHand::before_ode_step(double h, RigidObjects& objects) {
  objects_ = &objects;
  if (!config_.touches) return;
  const ContactPointParams& prm = config_.params;
  const int n_objects = objects.object_count();
  wrench_.assign(static_cast<std::size_t>(n_objects), Vector6::Zero());
  stiffness_.assign(static_cast<std::size_t>(n_objects), Matrix6::Zero());
  applied_.assign(static_cast<std::size_t>(n_objects), Vector6::Zero());
  std::vector<char> pushed(static_cast<std::size_t>(n_objects), 0);
  for (int s = 0; s < kContactPointShapes; ++s) {
    Contact& c = contacts_[s];
    const Eigen::Isometry3d T = shape_pose(s);
    if (c.object < 0) {
      Eigen::Vector3d p_S, n_W;
      double depth;
      int o = probe(s, objects, prm.threshold_m, p_S, depth, n_W);
      if (o >= 0 && depth > prm.threshold_m && has_last_) {
        // The shape went past the threshold within one step (a fast move, a teleport): the object its
        // point entered first along the way (3.5: continuous collision detection for fast hands).
        double first = INFINITY;
        const Eigen::Vector3d from = last_T_[s] * p_S, to = T * p_S;
        for (int k = 0; k < objects.object_count(); ++k) {
          Eigen::Vector3d hit, n;
          if (objects.ray_hit(k, from, to, hit, n) && (hit - from).norm() < first)
            first = (hit - from).norm(), o = k, n_W = n;
        }
      }
      if (o >= 0) make_contact(s, o, p_S, n_W, objects);
      continue;  // its force starts with the next ODE step
    }
    const Eigen::Isometry3d T_O = objects.object_pose(c.object);
    const bool dynamic = objects.object_dynamic(c.object);
    const Eigen::Vector3d com = dynamic ? objects.object_body(c.object).p_com_W : Eigen::Vector3d::Zero();
    const double gamma = prm.gamma_n_m / c.count;
    // The contact ends once every hand point is this far outside: the threshold it was made within,
    // and as much again plus its samples' spread (its ring of samples, made around a point just
    // within the threshold, lies partly beyond it: without the margin a finger's contacts ended the
    // step they were made, over and over, and never pushed).
    const double release = 2 * prm.threshold_m + (thumb_or_palm(s) ? prm.wide_sample_radius_m : prm.sample_radius_m);
    bool left = true;
    int active = 0;
    c.f_W.setZero();
    Eigen::Vector3d p_sum = Eigen::Vector3d::Zero(), n_sum = Eigen::Vector3d::Zero();
    c.depth_m = 0;
    for (int k = 0; k < c.count; ++k) {
      Sample& sample = c.samples[k];
      const Eigen::Vector3d p = T * sample.p_S, C = T_O * sample.C_O, n = T_O.linear() * sample.n_O;
      const double depth = n.dot(C - p);
      // The contact point's tangent plane stands for the object only near it: a hand point farther
      // than the threshold outside the object's surface (past an edge, beside a curved part) exerts
      // nothing. (Not its sign: a mesh's distance grid and the plane differ by up to a millimetre.)
      double d_geometry;
      Eigen::Vector3d n_geometry;
      const bool near = objects.surface_near(c.object, p, prm.threshold_m, d_geometry, n_geometry);
      if (near || objects.surface_near(c.object, p, release, d_geometry, n_geometry)) left = false;
      const ContactForce f = near ? slid_force(c, sample, T_O, p) : ContactForce{};
      sample.state = f.state;
      if (f.state == ContactState::separated) continue;
      const Eigen::Vector3d C_at = T_O * sample.C_O;
      ++active;
      c.f_W += f.total();
      p_sum += C_at;
      n_sum += n;
      c.depth_m = std::max(c.depth_m, depth);
      if (dynamic) {
        // The object takes -f at C; C moves with it, so the spring stiffens its motion (implicit below).
        const Eigen::Vector3d r = C_at - com;
        Eigen::Matrix<double, 3, 6> J;
        J << Eigen::Matrix3d::Identity(), -skew(r);
        wrench_[c.object] += J.transpose() * -f.total();
        stiffness_[c.object] += gamma * J.transpose() * J;
        pushed[c.object] = 1;
      }
    }
    if (left) {
      c = Contact{};  // every hand point has left the object: the contact ends (3.2)
      continue;
    }
    if (active > 0) c.p_W = p_sum / active, c.n_W = n_sum.normalized();
  }
  for (int s = 0; s < kContactPointShapes; ++s) last_T_[s] = shape_pose(s);
  has_last_ = true;
  // Each pushed body: the springs integrated implicitly over h with its mass (a 6x6 solve), applied
  // as the force that gives ODE's explicit step the same velocity change.
  for (int o = 0; o < n_objects; ++o) {
    if (!pushed[o]) continue;
    const ContactBody b = objects.object_body(o);
    Matrix6 M = Matrix6::Zero();
    M.topLeftCorner<3, 3>() = b.mass_kg * Eigen::Matrix3d::Identity();
    M.bottomRightCorner<3, 3>() = b.inertia_W;
    Vector6 xi, weight = Vector6::Zero();
    xi << b.v_W, b.w_W;
    weight.head<3>() = b.mass_kg * b.gravity_W;
    // With its weight in the solve (ODE adds the weight itself, so it comes off again): without it
    // the springs' share shrank to M / (M + h^2 K) of their force, and a 100 g box held by four
    // stuck fingers pulling it up with 5.5 N stayed on the table.
    const Eigen::LDLT<Matrix6> A(M + h * h * stiffness_[o]);
    const Vector6 dxi = A.solve(h * (wrench_[o] + weight) - h * h * stiffness_[o] * xi);
    const Vector6 w = M * dxi / h - weight;
    if (A.info() != Eigen::Success || !w.allFinite()) {
      ++resets_;  // nothing non-finite reaches a body
      clear_contacts();
      return;
    }
    objects.add_object_wrench(o, w.head<3>(), w.tail<3>());
    applied_[o] = w;
  }
}

void ContactPointHand::own_contacts(std::vector<OwnContact>& out) const {
  for (int s = 0; s < kContactPointShapes; ++s) {
    const Contact& c = contacts_[s];
    if (c.object < 0 || c.f_W.isZero()) continue;
    OwnContact o;
    o.handle = shape_handle(s);
    o.object = c.object;
    o.p_W = c.p_W;
    o.n_W = c.n_W;
    o.f_W = c.f_W;
    o.depth_m = c.depth_m;
    o.mu = c.mu_dynamic;
    out.push_back(o);
  }
}

bool ContactPointHand::linearize_next_step(HandleLinearization& out, ContactLinearization) {
  const int m = num_handles();
  out.F0 = Eigen::VectorXd::Zero(6 * m);
  out.K = Eigen::MatrixXd::Zero(6 * m, 6 * m);
  out.D = Eigen::MatrixXd::Zero(6 * m, 6 * m);
  out.contacts = HandleContactModel{};
  // The model is the law where the tick will ask it: the tick carries each proxy to the model's step
  // end (seed 004 section 3), one step after the poses the world was stepped to, so the rows are taken
  // at the tracked frames carried along by their devices' motion for that step. Anchored at the step's
  // start instead, the rows stood 2-4 cm behind a stylus lifting off the fixed bunny at 15 Hz, and
  // the tangent planes of samples beside its curved flank pulled it down 1.5 N (0.32 N anchored here).
  // Not by the proxies' motion: a glove's finger held on a box moves as the rows push its proxy
  // toward the surface they put, and carried by that the anchor went 3-5 mm into the box each step,
  // where the model's force was 3-4 times the law's at the frames.
  struct Restore {
    std::vector<HandleState>& handles;
    std::vector<HandleState> saved;
    ~Restore() { handles = std::move(saved); }
  } restore{handles_, handles_};
  for (std::size_t j = 0; j < handles_.size(); ++j) {
    handles_[j].p_WH += dt_s_ * device_v_[j].head<3>();
    handles_[j].q_WH = rotate_by(handles_[j].q_WH, dt_s_ * device_v_[j].tail<3>());
  }
  out.x0 = handles_;
  if (!objects_ || !config_.touches) return true;
  const ContactPointParams& prm = config_.params;
  struct Row {
    int handle;
    Eigen::Vector3d p, C, n;
    double gamma, mu, depth;
  };
  std::vector<Row> rows;
  for (int s = 0; s < kContactPointShapes; ++s) {
    const Contact& c = contacts_[s];
    const Eigen::Isometry3d T = shape_pose(s);
    if (c.object >= 0) {
      const Eigen::Isometry3d T_O = objects_->object_pose(c.object);
      for (int k = 0; k < c.count; ++k) {
        Sample sample = c.samples[k];
        const Eigen::Vector3d p = T * sample.p_S;
        double d;
        Eigen::Vector3d n_geometry;
        if (!objects_->surface_near(c.object, p, prm.lookahead_m, d, n_geometry)) continue;
        if (d < -prm.threshold_m) {
          // Past the threshold the sample exerts nothing in the world (before_ode_step), whatever its
          // tangent plane says; its row is the surface there instead, speculative as a near shape's.
          // Its plane kept, a sample 12 mm above the bunny whose plane said 2 mm inside held a lifting
          // stylus back, 0.6 N down.
          rows.push_back({shape_handle(s), p, p + d * n_geometry, n_geometry, prm.gamma_n_m / c.count, c.mu_static, d});
          continue;
        }
        // The tick's cone is the sample's state's (eq. 5): a sample the last ODE step slid is taken
        // kinetic. A static cone on a finger sliding up the bunny's flank as the stylus lifted
        // dragged it down 0.5 N where the world's kinetic samples dragged 0.05-0.11 N.
        // Outside the cone at the anchor, it is slid as the world's next ODE step slides it before
        // it pushes (slid_force), and the row starts from the slid point and its normal, kinetic. The
        // anchor is a step ahead of the world's hand: a finger lifted along the bunny's flank by a late
        // model kept contact points from 9 mm lower, whose planes, facing down, pulled the stylus 1.1 N.
        const bool slid = sample.state == ContactState::sliding;
        const bool slides = slid_force(c, sample, T_O, p).state == ContactState::sliding;
        const double mu = slid || slides ? c.mu_dynamic : c.mu_static;
        const Eigen::Vector3d C = T_O * sample.C_O, n = T_O.linear() * sample.n_O;
        const double depth = n.dot(C - p);
        if (depth > -prm.lookahead_m) rows.push_back({shape_handle(s), p, C, n, prm.gamma_n_m / c.count, mu, depth});
      }
      continue;
    }
    // A speculative row: the shape's nearest point, the whole contact's gamma.
    Eigen::Vector3d p_S, n_W;
    double depth;
    const int o = probe(s, *objects_, prm.lookahead_m, p_S, depth, n_W);
    if (o < 0) continue;
    const Eigen::Vector3d p = T * p_S;
    rows.push_back({shape_handle(s), p, p + depth * n_W, n_W, prm.gamma_n_m,
                    pair(config_.friction_static, objects_->object_friction_static(o)), depth});
  }
  if (rows.empty()) return true;
  if (static_cast<int>(rows.size()) > kMaxLinearizedContacts) {
    std::partial_sort(rows.begin(), rows.begin() + kMaxLinearizedContacts, rows.end(),
                      [](const Row& a, const Row& b) { return a.depth > b.depth; });
    rows.resize(kMaxLinearizedContacts);
  }
  // Eqs. 1-5 as rows (see the header): with impulse lambda over the step h along direction e of the
  // contact frame, the hand takes e lambda / h at p; the row's velocity u = -e . (C - p(x)) / h +
  // lambda / (gamma h^2) vanishes at lambda = gamma h e . (C - p), the spring, and the complementarity
  // keeps lambda_n >= 0 (a hand point outside exerts nothing) and the tangential impulses in the cone.
  const double h = dt_s_;
  const int c = static_cast<int>(rows.size());
  HandleContactModel& model = out.contacts;
  model.G = Eigen::MatrixXd::Zero(6 * m, 3 * c);
  model.W = Eigen::MatrixXd::Zero(3 * c, 3 * c);
  model.u0 = Eigen::VectorXd::Zero(3 * c);
  model.U_K = Eigen::MatrixXd::Zero(3 * c, 6 * m);
  model.U_D = Eigen::MatrixXd::Zero(3 * c, 6 * m);
  model.bias = Eigen::VectorXd::Zero(c);
  model.mu.resize(c);
  model.lambda0 = Eigen::VectorXd::Zero(3 * c);
  for (int i = 0; i < c; ++i) {
    const Row& r = rows[i];
    const Eigen::Vector3d t1 = r.n.unitOrthogonal(), t2 = r.n.cross(t1);
    const Eigen::Vector3d dirs[3] = {r.n, t1, t2};
    const Eigen::Vector3d arm = r.p - handles_[r.handle].p_WH;
    const ContactForce f = contact_force(r.gamma, r.mu, r.mu, r.C, r.n, r.p);
    for (int a = 0; a < 3; ++a) {
      const int row = 3 * i + a;
      const Eigen::Vector3d& e = dirs[a];
      model.G.block<3, 1>(6 * r.handle, row) = e / h;
      model.G.block<3, 1>(6 * r.handle + 3, row) = arm.cross(e) / h;
      model.U_K.row(row) = model.G.col(row).transpose();
      model.W(row, row) = 1.0 / (r.gamma * h * h);
      model.u0[row] = -e.dot(r.C - r.p) / h;
      model.lambda0[row] = h * e.dot(f.total());
    }
    model.mu[i] = r.mu;
  }
  return true;
}

Eigen::VectorXd ContactPointHand::coupling_wrench() const {
  Eigen::VectorXd out = Eigen::VectorXd::Zero(6 * num_handles());
  if (!objects_) return out;
  for (int s = 0; s < kContactPointShapes; ++s) {
    const Contact& c = contacts_[s];
    if (c.object < 0) continue;
    const Eigen::Isometry3d T = shape_pose(s), T_O = objects_->object_pose(c.object);
    const int j = shape_handle(s);
    for (int k = 0; k < c.count; ++k) {
      const Sample& sample = c.samples[k];
      const Eigen::Vector3d p = T * sample.p_S;
      double d;
      Eigen::Vector3d n;
      if (!objects_->surface_near(c.object, p, config_.params.threshold_m, d, n)) continue;  // as before_ode_step
      const Eigen::Vector3d f = contact_force(config_.params.gamma_n_m / c.count, c.mu_static, c.mu_dynamic,
                                              T_O * sample.C_O, T_O.linear() * sample.n_O, p)
                                    .total();
      out.segment<3>(6 * j) += f;
      out.segment<3>(6 * j + 3) += (p - handles_[j].p_WH).cross(f);
    }
  }
  return out;
}

Eigen::Vector3d ContactPointHand::skin_point(int i) const {
  if (i < kContactPointShapes) return shape_pose(std::max(i, 0)).translation();
  const int distal = 3 * (i - kContactPointShapes) + 2;
  return shape_pose(1 + distal) * Eigen::Vector3d(0, half_length_[distal], 0);
}

int ContactPointHand::skin_handle(int i) const {
  if (i < 0 || i >= num_skin_points()) return -1;
  if (i < kContactPointShapes) return shape_handle(i);
  return shape_handle(1 + 3 * (i - kContactPointShapes) + 2);  // a fingertip: its distal phalanx's
}

}  // namespace hapticd::hand::contact_point
