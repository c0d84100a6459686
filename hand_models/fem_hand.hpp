#pragma once
// The deformable hand of seed 004 behind the Hand interface: the procedural hand's tet mesh with
// linear co-rotational FEM flesh, coupled to its rigid handles by stiff damped springs (eq. 4-5),
// stepped implicitly with the coupled system solved by the Schur complement (eq. 7, 12-13).
#include <memory>
#include <string>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/procedural_hand.hpp"

namespace hapticd::hand {

class FemHand : public Hand {
 public:
  std::string_view model_name() const override { return "fem"; }
  bool left() const override { return left_side; }
  int num_handles() const override { return model->num_handles(); }
  HandleInfo handle_info(int j, int tracked_frames) const override;
  const std::vector<HandleState>& handles() const override { return state.handles; }
  bool set_target(int j, const HandleTarget& target) override;
  void place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) override;
  void set_step_length(double dt_s) override { state.dt_s = dt_s; }
  void step(HandleLinearization* model_out) override;
  void recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) override;
  long resets() const override { return state.resets; }
  bool linearize_next_step(HandleLinearization& out, ContactLinearization contacts) override;
  Eigen::VectorXd coupling_wrench() const override;
  int num_skin_points() const override { return static_cast<int>(shape.skin_tet.size()); }
  Eigen::Vector3d skin_point(int i) const override;
  int skin_handle(int i) const override;
  Flesh* flesh() override;

  // The FEM body itself (Hand::flesh: the world's collision embeds its contacts in these tets).
  bool left_side = false;  // the scene's side: a left hand (the mirror image)
  ProceduralHand shape;    // mesh, skeleton and the skin used for contact
  std::unique_ptr<HandModel> model;
  std::vector<int> skin_handles;  // per skin vertex, the handle of its part (procedural_skin_handles)
  HandState state;
  std::unique_ptr<CoupledSolver> solver;
  double friction = 0.5;

 private:
  Flesh flesh_;
};

// The FEM hand behind a Hand, for tests and benches that read its flesh; std::bad_cast for another model.
inline FemHand& as_fem(Hand& hand) { return dynamic_cast<FemHand&>(hand); }
inline const FemHand& as_fem(const Hand& hand) { return dynamic_cast<const FemHand&>(hand); }

}  // namespace hapticd::hand
