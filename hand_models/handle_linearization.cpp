#include "hand_models/handle_linearization.hpp"

#include <Eigen/Dense>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/contact_solve.hpp"

namespace hapticd::hand {

Eigen::VectorXd coupling_wrench(const HandModel& model, const Eigen::VectorXd& x_t, const Eigen::VectorXd& v_t,
                                const std::vector<HandleState>& handles) {
  const int m = model.num_handles();
  const CouplingParams& cp = model.config().coupling;
  Eigen::VectorXd W = Eigen::VectorXd::Zero(6 * m);
  for (int j = 0; j < m; ++j) {
    const RigidHandle& H = model.handles()[j];
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const int a = H.nodes[si];
      W.segment<6>(6 * j) +=
          coupling_spring(x_t.segment<3>(3 * a), v_t.segment<3>(3 * a), handles[j], H.r_B[si], cp.stiffness_n_m,
                          cp.damping_ns_m)
              .W_B;
    }
  }
  return W;
}

Eigen::VectorXd HandleLinearization::evaluate(const std::vector<HandleState>& handles) const {
  const int m = static_cast<int>(x0.size());
  Eigen::VectorXd dx(6 * m), dv(6 * m);
  for (int j = 0; j < m; ++j) {
    dx.segment<3>(6 * j) = handles[j].p_WH - x0[j].p_WH;
    dx.segment<3>(6 * j + 3) = rotation_difference(handles[j].q_WH, x0[j].q_WH);
    dv.segment<3>(6 * j) = handles[j].v_WH - x0[j].v_WH;
    dv.segment<3>(6 * j + 3) = handles[j].w_WH - x0[j].w_WH;
  }
  Eigen::VectorXd F = F0 + K * dx + D * dv;
  if (contacts.count() > 0) {
    ContactProblem p;
    p.W = contacts.W;
    p.u_free = contacts.u0 + contacts.U_K * dx + contacts.U_D * dv;
    p.bias = contacts.bias;
    p.mu = contacts.mu;
    PgsOptions options;
    options.max_iterations = 10000;
    options.tolerance = 1e-12;
    F += contacts.G * solve_contacts_pgs(p, options, &contacts.lambda0).lambda;
  }
  return F;
}

bool linearize_handles(const HandModel& model, const HandState& s, CoupledSolver& solver, HandleLinearization& out,
                       const HeldContacts* held, const ContactRows* rows) {
  out.contacts = HandleContactModel{};
  if (held && rows) return false;  // one or the other
  const CoupledSystem& sys = s.system;
  const int m = model.num_handles(), nh = 6 * m, nt = sys.tool_dofs();
  const int nb = (sys.handle_dofs() - nh) / 6;  // rigid bodies solved with the hand
  const double h = step_length(model, s);
  const CouplingParams& cp = model.config().coupling;

  // The coupling Jacobians split into their K and D parts (eq. 11), which the
  // assembled system only holds combined as -h D - h^2 K.
  Eigen::MatrixXd K_hh = Eigen::MatrixXd::Zero(nh, nh), D_hh = K_hh;
  Eigen::MatrixXd K_th = Eigen::MatrixXd::Zero(nt, nh), D_th = K_th;
  std::vector<Eigen::Triplet<double>> kd_ht;  // h K_ht + D_ht: nonzero on the handles' own nodes only
  Eigen::VectorXd W_el = Eigen::VectorXd::Zero(nh);
  for (int j = 0; j < m; ++j) {
    const RigidHandle& H = model.handles()[j];
    const HandleState& hs = s.handles[j];
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const int a = H.nodes[si];
      const SpringTerms sp = coupling_spring(s.x.segment<3>(3 * a), s.v.segment<3>(3 * a), hs, H.r_B[si],
                                             cp.stiffness_n_m, cp.damping_ns_m);
      K_hh.block<6, 6>(6 * j, 6 * j) += sp.dWB_dxh;
      D_hh.block<6, 6>(6 * j, 6 * j) += sp.dWB_dvh;
      K_th.block<3, 6>(3 * a, 6 * j) += sp.dFA_dxh;
      D_th.block<3, 6>(3 * a, 6 * j) += sp.dFA_dvh;
      const Eigen::Matrix<double, 6, 3> block = h * sp.dWB_dxA + sp.dWB_dvA;
      for (int r = 0; r < 6; ++r)
        for (int c = 0; c < 3; ++c) kd_ht.emplace_back(6 * j + r, 3 * a + c, block(r, c));
      // Elastic part: the wrench with the damping of the current velocities removed (linear in v).
      Vector6d v_h;
      v_h << hs.v_WH, hs.w_WH;
      W_el.segment<6>(6 * j) += sp.W_B - sp.dWB_dvA * s.v.segment<3>(3 * a) - sp.dWB_dvh * v_h;
    }
  }
  // Solves with everything but the handles: the tool and the implicit bodies
  // (block elimination of the bodies through the tool's A_t^-1). Columns: the
  // constant part, the K and D parts, then the held (or the model's) contact rows' J^T.
  const int nc = held ? held->rows() : rows ? 3 * rows->count() : 0;
  const int nk = 1 + 2 * nh;
  Eigen::SparseMatrix<double> KD_ht(nh, nt);
  KD_ht.setFromTriplets(kd_ht.begin(), kd_ht.end());  // duplicates (a node in two springs) are summed
  Eigen::SparseMatrix<double> J_t(0, nt), J_b(0, 6 * nb);  // held rows on the tool and on the bodies
  if (nc > 0) {
    const Eigen::SparseMatrix<double> J = held ? held->J : Eigen::SparseMatrix<double>(rows->Jt.transpose());
    J_t = J.rightCols(nt);
    J_b = J.middleCols(nh, 6 * nb);
  }
  const Eigen::SparseMatrix<double> A_bt = sys.A_ht.bottomRows(6 * nb);
  // The tool solution Y (nt x (nk + nc + 6 nb)) is only ever looked at through three sparse
  // operators: the handles' springs KD_ht (what the model is made of), the held rows J_t and the
  // bodies' couplings A_bt. Everything after the solves works on their stacked product O Y
  // ((nh + nc + 6 nb) rows), never on the tool's nt rows.
  Eigen::SparseMatrix<double, Eigen::RowMajor> O(nh + nc + 6 * nb, nt);  // by rows: each row a dot product down a column of Y
  {
    std::vector<Eigen::Triplet<double>> o;
    o.reserve(KD_ht.nonZeros() + J_t.nonZeros() + A_bt.nonZeros());
    const auto append = [&o](const Eigen::SparseMatrix<double>& M, int row0) {
      for (int col = 0; col < M.outerSize(); ++col)
        for (Eigen::SparseMatrix<double>::InnerIterator it(M, col); it; ++it)
          o.emplace_back(row0 + static_cast<int>(it.row()), static_cast<int>(it.col()), it.value());
    };
    append(KD_ht, 0);
    append(J_t, nh);
    append(A_bt, nh + nc);
    O.setFromTriplets(o.begin(), o.end());
  }
  Eigen::MatrixXd OY(nh + nc + 6 * nb, nk + nc + 6 * nb);
  const Eigen::MatrixXd* solved = solver.tool_solution(sys);  // A_t^-1 [b_t, A_th] when the solver kept it
  const double k = cp.stiffness_n_m, d = cp.damping_ns_m;
  if (solved != nullptr && d > 0) {
    // From the Schur complement's own solves: eq. 11 gives K_th = (k / d) D_th + E,
    // E = -d [w]x [rho]x on the rotation columns only (the handle's spin), so
    // A_th = -h D_th - h^2 K_th = -(1 + h k / d) h D_th - h E, and only E, the
    // held rows and the contact impulses need new solves (3m + nc + 1 columns
    // instead of 12m + nc + 1).
    Eigen::MatrixXd rhs(nt, 3 * m + nc + 1);
    for (int j = 0; j < m; ++j)
      rhs.middleCols<3>(3 * j) = h * K_th.middleCols<3>(6 * j + 3) - (k / d) * h * D_th.middleCols<3>(6 * j + 3);
    rhs.middleCols(3 * m, nc) = Eigen::MatrixXd(J_t.transpose());
    rhs.col(3 * m + nc) = held ? Eigen::VectorXd(held->impulse.tail(nt)) : Eigen::VectorXd::Zero(nt);
    Eigen::MatrixXd Z;
    if (!solver.solve_tool(sys, rhs, Z)) return false;
    const Eigen::MatrixXd OZ = O * Z, OS = O * (*solved);
    Eigen::MatrixXd OY_E = Eigen::MatrixXd::Zero(O.rows(), nh);
    for (int j = 0; j < m; ++j) OY_E.middleCols<3>(6 * j + 3) = OZ.middleCols<3>(3 * j);
    const Eigen::MatrixXd OY_D = -(OS.middleCols(1, nh) + h * OY_E) / (1 + h * k / d);
    // The step's contact impulses act as known forces; the held rows' multipliers then only correct them.
    OY.col(0) = OS.col(0) + OZ.col(3 * m + nc);
    OY.middleCols(1, nh) = (k / d) * OY_D + OY_E;
    OY.middleCols(1 + nh, nh) = OY_D;
    OY.middleCols(nk, nc) = OZ.middleCols(3 * m, nc);
    OY.rightCols(6 * nb) = OS.rightCols(6 * nb);
  } else {
    Eigen::MatrixXd rhs(nt, nk + nc + 6 * nb), Y;
    rhs << sys.b_t, h * K_th, h * D_th, Eigen::MatrixXd(J_t.transpose()), Eigen::MatrixXd(sys.A_th.rightCols(6 * nb));
    if (held) rhs.col(0) += held->impulse.tail(nt);
    if (!solver.solve_tool(sys, rhs, Y)) return false;
    OY.noalias() = O * Y;
  }
  Eigen::MatrixXd X_b = Eigen::MatrixXd::Zero(6 * nb, nk + nc);  // the bodies' part of each solution
  if (nb > 0) {
    const Eigen::MatrixXd AY_b = OY.bottomRightCorner(6 * nb, 6 * nb);  // A_bt Y_b
    const Eigen::MatrixXd S_b = sys.A_h.bottomRightCorner(6 * nb, 6 * nb) - AY_b;
    Eigen::MatrixXd R_b = -OY.bottomLeftCorner(6 * nb, nk + nc);
    R_b.col(0) += sys.b_h.tail(6 * nb);  // the bodies' own RHS for b_t's column; zero for the handle columns
    if (held) R_b.col(0) += held->impulse.segment(nh, 6 * nb);
    if (nc > 0) R_b.rightCols(nc) += Eigen::MatrixXd(J_b.transpose());
    X_b = S_b.partialPivLu().solve(R_b);
    // Y -= Y_b X_b, seen through O.
    OY.leftCols(nk + nc) -= OY.rightCols(6 * nb) * X_b;
  }
  if (rows && nc > 0) {
    // The rows' relative velocities J V for every column (their tool part, seen through O, and their
    // bodies' part), and for the impulse columns W.
    HandleContactModel& c = out.contacts;
    const Eigen::MatrixXd JV = OY.block(nh, 0, nc, nk + nc) + J_b * X_b;
    c.W = JV.rightCols(nc);
    c.U_K = JV.middleCols(1, nh);
    c.U_D = JV.middleCols(1 + nh, nh);
    Eigen::VectorXd v0(nh);
    for (int j = 0; j < m; ++j) v0.segment<6>(6 * j) << s.handles[j].v_WH, s.handles[j].w_WH;
    c.u0 = rows->u_known + JV.col(0) + c.U_D * v0;
    c.G = OY.block(0, nk, nh, nc);
    c.bias = rows->bias;
    c.mu = rows->mu;
    ContactProblem p{c.W, c.u0, c.bias, c.mu};
    PgsOptions options;
    options.max_iterations = 500;
    options.tolerance = 1e-10;
    c.lambda0 = solve_contacts_pgs(p, options, &rows->warm).lambda;
    if (!c.W.allFinite() || !c.u0.allFinite() || !c.U_K.allFinite() || !c.U_D.allFinite() || !c.G.allFinite() ||
        !c.lambda0.allFinite())
      return false;
  } else if (nc > 0) {
    // Multipliers that keep J V = u for every column: W mu = u e0^T - J Y, with
    // W = J A^-1 J^T (handles held). Redundant rows (more contacts than a body
    // has DOFs) make W singular: a relative 1e-10 regularization picks the
    // least-norm multipliers without changing the held velocities measurably.
    const Eigen::MatrixXd Z_b = X_b.rightCols(nc);
    Eigen::MatrixXd W = OY.block(nh, nk, nc, nc) + J_b * Z_b;
    W.diagonal().array() += 1e-10 * W.diagonal().cwiseAbs().maxCoeff();
    Eigen::MatrixXd Q = -(OY.block(nh, 0, nc, nk) + J_b * X_b.leftCols(nk));
    Q.col(0) += held->u;
    const Eigen::MatrixXd mu = W.ldlt().solve(Q);
    // Y += Z mu (Z: the held rows' columns of Y), for the springs' rows, all the model needs below.
    OY.topLeftCorner(nh, nk) += OY.block(0, nk, nh, nc) * mu;
  }
  // KD_ht times y0, Y_K and Y_D.
  const Eigen::VectorXd P0 = OY.block(0, 0, nh, 1);
  const Eigen::MatrixXd P_D = OY.block(0, 1 + nh, nh, nh);
  out.K = K_hh + OY.block(0, 1, nh, nh);
  out.D = D_hh + P_D;
  out.x0 = s.handles;
  Eigen::VectorXd v0(nh);
  for (int j = 0; j < m; ++j) v0.segment<6>(6 * j) << s.handles[j].v_WH, s.handles[j].w_WH;
  // F0 = W_el + D_hh v0 + (h K_ht + D_ht) v_t(dx = 0, v = v0).
  out.F0 = W_el + D_hh * v0 + P0 + P_D * v0;
  return out.F0.allFinite() && out.K.allFinite() && out.D.allFinite();
}

bool linearize_next_step(const HandModel& model, HandState& s, CoupledSolver& solver, HandleLinearization& out,
                         ContactLinearization contacts) {
  assemble(model, s);
  Eigen::VectorXd v_h, v_t;
  SolveReport report;
  bool ok = solver.solve(s.system, v_h, v_t, report);
  if (ok && contacts == ContactLinearization::unilateral) {
    ContactRows rows;
    contact_rows(model, s, kMaxLinearizedContacts, rows);
    ok = linearize_handles(model, s, solver, out, nullptr, rows.count() > 0 ? &rows : nullptr);
  } else if (ok) {
    ok = linearize_handles(model, s, solver, out, s.held.rows() > 0 ? &s.held : nullptr);
  }
  if (!ok) out = HandleLinearization{};
  return ok;
}

}  // namespace hapticd::hand
