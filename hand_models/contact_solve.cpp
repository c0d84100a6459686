#include "hand_models/contact_solve.hpp"

#include <algorithm>
#include <cmath>

#include "hand_models/contact_pgs.hpp"

namespace hapticd::hand {
namespace {

// An orthonormal contact frame (n, t1, t2).
Eigen::Matrix3d contact_frame(const Eigen::Vector3d& n) {
  const Eigen::Vector3d a = std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d t1 = n.cross(a).normalized();
  Eigen::Matrix3d F;
  F << n, t1, n.cross(t1);
  return F;
}

bool valid_support(const HandState& s, const BodySupport& b) {
  return b.body >= 0 && b.body < static_cast<int>(s.bodies.size()) && b.p_W.allFinite() && b.n_W.allFinite() &&
         std::abs(b.n_W.norm() - 1) < 1e-6 && std::isfinite(b.depth_m) && b.v_other_W.allFinite() &&
         std::isfinite(b.friction) && b.friction >= 0;
}

// Builds rows of J^T, 3 columns per row (row = DOF, column = contact direction), in contact frames
// of the relative velocity of the hand point (or body) against the other side.
class RowBuilder {
 public:
  RowBuilder(const HandModel& model, const HandState& s)
      : model_(model), s_(s), nh_(s.system.handle_dofs()), nt_(s.system.tool_dofs()), m_(model.num_handles()) {}
  // Appends row k's J^T entries (a hand point, or a body's support) and returns its frame (n, t1, t2).
  Eigen::Matrix3d add_point(const PointContact& pc, int k) {
    const Tet& t = model_.mesh().tets[pc.tet];
    const Eigen::Matrix3d F = contact_frame(pc.n_W);
    for (int a = 0; a < 4; ++a)
      if (pc.bary[a] != 0) add(nh_ + 3 * t[a], k, pc.bary[a] * F);
    if (pc.body >= 0) add_body(pc.body, embedded_value(t, pc.bary, s_.x), k, -1.0, F);
    return F;
  }
  Eigen::Matrix3d add_support(const BodySupport& b, int k) {
    const Eigen::Matrix3d F = contact_frame(b.n_W);
    add_body(b.body, b.p_W, k, 1.0, F);
    return F;
  }
  // The rows added since the last call, as J^T.
  Eigen::SparseMatrix<double> take(int count) {
    Eigen::SparseMatrix<double> Jt(nh_ + nt_, 3 * count);
    Jt.setFromTriplets(entries_.begin(), entries_.end());
    entries_.clear();
    return Jt;
  }

 private:
  void add(int dof, int k, const Eigen::Matrix3d& block) {
    for (int r = 0; r < 3; ++r)
      for (int d = 0; d < 3; ++d) entries_.emplace_back(dof + r, 3 * k + d, block(r, d));
  }
  void add_body(int body, const Eigen::Vector3d& p_W, int k, double sign, const Eigen::Matrix3d& F) {
    const Eigen::Vector3d rho = p_W - s_.bodies[body].p_com_W;
    add(6 * (m_ + body), k, sign * F);
    add(6 * (m_ + body) + 3, k, sign * skew(rho) * F);  // (w x rho) . f = w . (rho x f)
  }
  const HandModel& model_;
  const HandState& s_;
  const int nh_, nt_, m_;
  std::vector<Eigen::Triplet<double>> entries_;
};

// A row's least normal velocity: penetrating, push out a fraction of the depth; a gap (speculative
// contact) may close fully.
double contact_bias(double depth_m, double h) {
  return depth_m > 0 ? kContactDepthRecovery * depth_m / h : depth_m / h;
}

// A row's known relative velocity (a kinematic other side's, in the frame), bias and friction.
void row_terms(const PointContact& pc, const Eigen::Matrix3d& F, double h, Eigen::Ref<Eigen::Vector3d> u_known,
               double& bias, double& mu) {
  u_known = -F.transpose() * (pc.body >= 0 ? Eigen::Vector3d::Zero() : pc.v_other_W);
  bias = contact_bias(pc.depth_m, h);
  mu = pc.friction;
}
void row_terms(const BodySupport& b, const Eigen::Matrix3d& F, double h, Eigen::Ref<Eigen::Vector3d> u_known,
               double& bias, double& mu) {
  u_known = -F.transpose() * b.v_other_W;
  bias = contact_bias(b.depth_m, h);
  mu = b.friction;
}

}  // namespace

void contact_rows(const HandModel& model, const HandState& s, int max_contacts, ContactRows& out) {
  struct Candidate {
    const PointContact* contact = nullptr;
    const BodySupport* support = nullptr;
    int rank = 0;  // 0: the hand's contacts, 1: its bodies' supports, 2: reserves
    double depth = 0;
  };
  std::vector<Candidate> candidates;
  for (const PointContact& pc : s.active_contacts)
    if (pc.constraint) candidates.push_back({&pc, nullptr, 0, pc.depth_m});
  for (const BodySupport& b : s.supports)
    if (valid_support(s, b)) candidates.push_back({nullptr, &b, 1, b.depth_m});
  // The step promotes a reserve that it would carry deeper (solve_constraint_contacts): the model
  // holds them as rows of their own, or skin between the rows would sink in the tick.
  for (const PointContact& pc : s.reserve_contacts)
    if (pc.constraint && valid_contact(model, s, pc)) candidates.push_back({&pc, nullptr, 2, pc.depth_m});
  if (static_cast<int>(candidates.size()) > max_contacts) {
    // By rank, then the deepest first (a gap is a negative depth). The bodies' supports keep up to a
    // third of the rows and the reserves two, however many the hand's own contacts are; the hand's
    // contacts take the rest. Without the supports the haptic tick lets a body the hand presses move
    // as if nothing held it (a hand pressing the bunny hard found 44 contacts of its own, and the
    // proxy sank at 1 m/s through a model with the table left out). Without the deepest reserves it
    // misses what the step promotes under a hard press: on the stylus bunny's 120 N press, 1-3 of 60
    // reserves carry up to a third of the impulse, and the model's force error p99 was 18 N. More reserves
    // cost the hand's contacts their coverage (one per cluster cell): on the blocks' flat faces the
    // median error grows 0.9 -> 1.3 N with two reserves, 5 N with eight (`scripts/bench-world`).
    std::stable_sort(candidates.begin(), candidates.end(), [](const Candidate& a, const Candidate& b) {
      return a.rank != b.rank ? a.rank < b.rank : a.depth > b.depth;
    });
    int count[3] = {0, 0, 0};
    for (const Candidate& cand : candidates) ++count[cand.rank];
    const int budget = std::max(0, max_contacts);
    int take[3], left = budget;
    left -= take[1] = std::min(count[1], budget / 3);
    left -= take[2] = std::min(count[2], budget / 12);
    left -= take[0] = std::min(count[0], left);
    for (int rank = 0; rank < 3; ++rank) {  // what a rank leaves goes to the others, in rank order
      const int more = std::min(count[rank] - take[rank], left);
      take[rank] += more;
      left -= more;
    }
    std::vector<Candidate> kept;
    kept.reserve(budget);
    int first = 0;
    for (int rank = 0; rank < 3; first += count[rank], ++rank)
      kept.insert(kept.end(), candidates.begin() + first, candidates.begin() + first + take[rank]);
    candidates.swap(kept);
  }
  const int c = static_cast<int>(candidates.size());
  const double h = step_length(model, s);
  out.frames.resize(c);
  out.u_known.resize(3 * c);
  out.bias.resize(c);
  out.mu.resize(c);
  out.warm.resize(3 * c);
  RowBuilder rows(model, s);
  for (int k = 0; k < c; ++k) {
    const Candidate& cand = candidates[k];
    Eigen::Vector3d warm_W = Eigen::Vector3d::Zero();
    if (cand.contact) {
      out.frames[k] = rows.add_point(*cand.contact, k);
      row_terms(*cand.contact, out.frames[k], h, out.u_known.segment<3>(3 * k), out.bias[k], out.mu[k]);
      warm_W = cand.contact->warm_impulse_W;
    } else {
      out.frames[k] = rows.add_support(*cand.support, k);
      row_terms(*cand.support, out.frames[k], h, out.u_known.segment<3>(3 * k), out.bias[k], out.mu[k]);
    }
    out.warm.segment<3>(3 * k) = out.frames[k].transpose() * warm_W;
  }
  out.Jt = rows.take(c);
}

bool solve_constraint_contacts(const HandModel& model, HandState& s, CoupledSolver& solver,
                               std::vector<Eigen::Vector3d>& impulses) {
  constexpr int kReserveRounds = 3;
  struct Row {
    int contact = -1, support = -1;  // index into s.active_contacts or s.supports
  };
  std::vector<Row> rows;
  for (size_t i = 0; i < s.active_contacts.size(); ++i)
    if (s.active_contacts[i].constraint) rows.push_back({static_cast<int>(i), -1});
  for (size_t i = 0; i < s.supports.size(); ++i)
    if (valid_support(s, s.supports[i])) rows.push_back({-1, static_cast<int>(i)});
  if (static_cast<int>(rows.size()) > kMaxStepContacts) {
    // A body buried in another (an absurd scene) finds thousands: the deepest are kept, the rest
    // left out of this step (StepTimings::contacts_dropped).
    const auto depth = [&](const Row& r) {
      return r.contact >= 0 ? s.active_contacts[r.contact].depth_m : s.supports[r.support].depth_m;
    };
    std::stable_sort(rows.begin(), rows.end(), [&](const Row& a, const Row& b) { return depth(a) > depth(b); });
    s.timings.contacts_dropped += static_cast<int>(rows.size()) - kMaxStepContacts;
    rows.resize(kMaxStepContacts);
  }
  std::vector<const PointContact*> reserves;
  for (const PointContact& r : s.reserve_contacts)
    if (r.constraint && valid_contact(model, s, r)) reserves.push_back(&r);
  s.held = HeldContacts{};
  const CoupledSystem& sys = s.system;
  const int nh = sys.handle_dofs(), nt = sys.tool_dofs();
  const double h = step_length(model, s);
  const Eigen::VectorXd V_free = (Eigen::VectorXd(nh + nt) << s.v_h_next, s.v_t_next).finished();
  RowBuilder builder(model, s);

  // Rows [first, rows.size()) join the problem: their part of J^T, of A^-1 J^T and of the LCP.
  ContactProblem problem;
  Eigen::VectorXd lambda;  // the last solution, the next round's first guess
  Eigen::SparseMatrix<double> Jt(nh + nt, 0);
  // A^-1 J^T = [X_h; X_t - Y X_h] (CoupledSolver::solve_block_parts; Y the handle columns of *Y_tool).
  Eigen::MatrixXd X_h(nh, 0), X_t(nt, 0);
  const Eigen::MatrixXd* Y_tool = nullptr;
  // V_free + A^-1 J^T l.
  const auto velocities = [&](const Eigen::VectorXd& l) {
    Eigen::VectorXd V = V_free;
    const Eigen::VectorXd dv_h = X_h * l;
    V.head(nh) += dv_h;
    V.tail(nt) += X_t * l;
    if (Y_tool) V.tail(nt).noalias() -= Y_tool->middleCols(1, nh) * dv_h;
    return V;
  };
  auto append_rows = [&](int first) -> bool {
    const int c = static_cast<int>(rows.size()), added = c - first;
    problem.u_free.conservativeResize(3 * c);
    problem.bias.conservativeResize(c);
    problem.mu.resize(c);
    lambda.conservativeResize(3 * c);
    for (int k = 0; k < added; ++k) {
      const Row& row = rows[first + k];
      const int i = first + k;
      Eigen::Vector3d warm = Eigen::Vector3d::Zero();
      Eigen::Matrix3d F;
      if (row.contact >= 0) {
        const PointContact& pc = s.active_contacts[row.contact];
        F = builder.add_point(pc, k);
        row_terms(pc, F, h, problem.u_free.segment<3>(3 * i), problem.bias[i], problem.mu[i]);
        warm = pc.warm_impulse_W;
      } else {
        const BodySupport& b = s.supports[row.support];
        F = builder.add_support(b, k);
        row_terms(b, F, h, problem.u_free.segment<3>(3 * i), problem.bias[i], problem.mu[i]);
      }
      lambda.segment<3>(3 * i) = F.transpose() * warm;
    }
    const Eigen::SparseMatrix<double> Jt_new = builder.take(added);
    problem.u_free.tail(3 * added) += Jt_new.transpose() * V_free;
    Eigen::MatrixXd X_h_new, X_t_new;
    const Eigen::MatrixXd* Y_round = nullptr;
    if (!solver.solve_block_parts(sys, Eigen::MatrixXd(Jt_new), X_h_new, X_t_new, Y_round)) return false;
    if (first > 0 && Y_round != Y_tool) return false;  // every column of X must be in the same form
    Y_tool = Y_round;
    Eigen::SparseMatrix<double> joined(nh + nt, 3 * c);
    joined.leftCols(3 * first) = Jt;
    joined.rightCols(3 * added) = Jt_new;
    Jt = std::move(joined);
    X_h.conservativeResize(nh, 3 * c);
    X_h.rightCols(3 * added) = X_h_new;
    X_t.conservativeResize(nt, 3 * c);
    X_t.rightCols(3 * added) = X_t_new;
    // W = J A^-1 J^T = J_h X_h + J_t (X_t - Y X_h); J by rows, so its products run down X's columns.
    const Eigen::SparseMatrix<double, Eigen::RowMajor> J_h = Jt.topRows(nh).transpose(),
                                                       J_t = Jt.bottomRows(nt).transpose();
    problem.W = J_h * X_h + J_t * X_t;
    if (Y_tool) problem.W.noalias() -= (J_t * Y_tool->middleCols(1, nh)) * X_h;
    return true;
  };

  Eigen::VectorXd V = V_free;
  impulses.assign(s.active_contacts.size(), Eigen::Vector3d::Zero());
  for (int round = 0, first = 0;; ++round) {
    if (static_cast<int>(rows.size()) > first) {
      if (!append_rows(first)) return false;
      PgsOptions options;
      options.max_iterations = kStepContactSweeps;
      options.tolerance = 1e-8;
      const PgsResult r = solve_contacts_pgs(problem, options, &lambda);
      if (!r.lambda.allFinite()) return false;
      lambda = r.lambda;
      s.timings.contact_iterations = r.iterations;
      s.timings.contact_converged = r.converged;
      V = velocities(lambda);
    }
    first = static_cast<int>(rows.size());
    if (round == kReserveRounds || reserves.empty()) break;

    // Reserves the solution carries deeper, and deeper than kReserveDepth_m, join the rows.
    for (size_t k = 0; k < reserves.size(); ++k) builder.add_point(*reserves[k], static_cast<int>(k));
    const Eigen::VectorXd u = builder.take(static_cast<int>(reserves.size())).transpose() * V;
    std::vector<const PointContact*> waiting;
    for (size_t k = 0; k < reserves.size(); ++k) {
      const PointContact& pc = *reserves[k];
      const double u_n = u[3 * k] - (pc.body >= 0 ? 0.0 : pc.n_W.dot(pc.v_other_W));
      const double end_depth = pc.depth_m - h * u_n;
      if (end_depth <= std::max(kReserveDepth_m, pc.depth_m) ||
          static_cast<int>(rows.size()) >= kMaxStepContacts) {  // shallow enough, coming out, or no room
        waiting.push_back(&pc);
        continue;
      }
      rows.push_back({static_cast<int>(s.active_contacts.size()), -1});
      s.active_contacts.push_back(pc);
      s.active_source.push_back(kReserveSource - static_cast<int>(&pc - s.reserve_contacts.data()));
      impulses.emplace_back(Eigen::Vector3d::Zero());
    }
    if (static_cast<int>(rows.size()) == first) break;
    reserves.swap(waiting);
    ++s.timings.reserve_rounds;
  }
  s.v_h_next = V.head(nh);
  s.v_t_next = V.tail(nt);
  const int c = static_cast<int>(rows.size());
  for (int k = 0; k < c; ++k)
    if (rows[k].contact >= 0)
      impulses[rows[k].contact] = contact_frame(s.active_contacts[rows[k].contact].n_W) * lambda.segment<3>(3 * k);

  // Held for the linearization: pushing rows' normals, and the tangents of those inside the cone.
  std::vector<int> held_cols;
  for (int k = 0; k < c; ++k) {
    const Eigen::Vector3d l = lambda.segment<3>(3 * k);
    if (l[0] <= 0) continue;
    held_cols.push_back(3 * k);
    const bool sticks = problem.mu[k] > 0 && l.tail<2>().norm() < (1 - 1e-6) * problem.mu[k] * l[0];
    if (sticks) held_cols.push_back(3 * k + 1), held_cols.push_back(3 * k + 2);
  }
  s.held.J.resize(static_cast<int>(held_cols.size()), nh + nt);
  std::vector<Eigen::Triplet<double>> held_entries;
  for (size_t r_i = 0; r_i < held_cols.size(); ++r_i)
    for (Eigen::SparseMatrix<double>::InnerIterator it(Jt, held_cols[r_i]); it; ++it)
      held_entries.emplace_back(static_cast<int>(r_i), static_cast<int>(it.row()), it.value());
  s.held.J.setFromTriplets(held_entries.begin(), held_entries.end());
  s.held.u = s.held.J * V;
  s.held.impulse = Jt * lambda;
  return true;
}

}  // namespace hapticd::hand
