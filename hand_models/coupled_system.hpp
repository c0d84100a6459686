#pragma once
// The linear system of one implicit Euler step of a hand with m rigid handles
// (seed 004 eq. 7):  [A_h  A_ht] [v_h]   [b_h]
//                    [A_th A_t ] [v_t] = [b_t]
// A_t (3n x 3n) is symmetric positive definite with a pattern fixed per mesh;
// A_h (6m x 6m) is dense; A_th / A_ht are nonzero only on coupled nodes.
#include <Eigen/Core>
#include <Eigen/SparseCore>

namespace hapticd::hand {

struct CoupledSystem {
  Eigen::SparseMatrix<double> A_t;                    // both triangles stored
  Eigen::SparseMatrix<double> A_th;                   // 3n x 6m
  Eigen::SparseMatrix<double, Eigen::RowMajor> A_ht;  // 6m x 3n
  Eigen::MatrixXd A_h;                                // 6m x 6m
  Eigen::VectorXd b_t, b_h;

  int tool_dofs() const { return static_cast<int>(b_t.size()); }
  int handle_dofs() const { return static_cast<int>(b_h.size()); }
};

// Residual of eq. 7, ||A v - b|| / ||b||.
double relative_residual(const CoupledSystem& s, const Eigen::VectorXd& v_h, const Eigen::VectorXd& v_t);

}  // namespace hapticd::hand
