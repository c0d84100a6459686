#include "hand_models/fem_hand.hpp"

#include "hand_models/procedural_handles.hpp"

namespace hapticd::hand {

HandleInfo FemHand::handle_info(int j, int tracked_frames) const {
  const RigidHandle& h = model->handles()[static_cast<std::size_t>(j)];
  HandleInfo info;
  info.mass_kg = h.mass_kg;
  info.inertia_B = h.inertia_B;
  // A device tracking more than the palm drives each handle by its segment's frame (a glove).
  if (tracked_frames > 1) {
    const std::vector<HandFrame> frames = procedural_handle_frames(shape, model->num_handles());
    info.in_frame = frame_to_handle(frames[static_cast<std::size_t>(j)].p, frames[static_cast<std::size_t>(j)].R, h);
  }
  return info;
}

bool FemHand::set_target(int j, const HandleTarget& target) { return hand::set_target(state, j, target); }

void FemHand::place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) {
  place_hand(*model, state, p_W, q_W, 0);
}

void FemHand::step(HandleLinearization* model_out) { hand::step(*model, state, *solver, model_out); }

void FemHand::recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) {
  ++state.resets;
  // Placed rigidly at rest, a hand pressed into an object would overlap it by its compression and
  // the next step would push back with a jump: a hand whose positions are whole keeps its shape and
  // contacts, and only its motion (which a broken-off step may have left half-updated) stops.
  bool whole = state.x.allFinite();
  for (const HandleState& h : state.handles) whole = whole && h.p_WH.allFinite() && h.q_WH.coeffs().allFinite();
  if (whole) {
    state.v.setZero();
    for (HandleState& h : state.handles) h.v_WH.setZero(), h.w_WH.setZero();
    return;
  }
  state.contacts.clear();
  state.reserve_contacts.clear();
  state.bodies.clear();
  state.supports.clear();
  if (fallback_p_W.allFinite() && fallback_q_W.coeffs().allFinite()) {
    place_hand(*model, state, fallback_p_W, fallback_q_W.normalized(), 0);
  } else {
    const long resets = state.resets;
    state = make_rest_state(*model);
    state.resets = resets;
  }
}

bool FemHand::linearize_next_step(HandleLinearization& out, ContactLinearization contacts) {
  return hand::linearize_next_step(*model, state, *solver, out, contacts);
}

Eigen::VectorXd FemHand::coupling_wrench() const {
  return hand::coupling_wrench(*model, state.x, state.v, state.handles);
}

Eigen::Vector3d FemHand::skin_point(int i) const {
  const auto k = static_cast<std::size_t>(i);
  return embedded_value(model->mesh().tets[static_cast<std::size_t>(shape.skin_tet[k])], shape.skin_bary[k], state.x);
}

int FemHand::skin_handle(int i) const {
  return i >= 0 && i < static_cast<int>(skin_handles.size()) ? skin_handles[static_cast<std::size_t>(i)] : -1;
}

Flesh* FemHand::flesh() {
  flesh_.model = model.get();
  flesh_.state = &state;
  flesh_.point_tet = &shape.skin_tet;
  flesh_.point_bary = &shape.skin_bary;
  flesh_.rest_surface_vertices = &shape.skin_vertices;
  flesh_.surface_triangles = &shape.skin_triangles;
  flesh_.friction = friction;
  return &flesh_;
}

}  // namespace hapticd::hand
