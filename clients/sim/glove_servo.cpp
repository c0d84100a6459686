#include "clients/sim/glove_servo.hpp"

#include <stdexcept>
#include <string>

#include "protocol/codec.hpp"

namespace hapticd::sim {

protocol::Hello glove_hello(int frames, std::string_view client_name, std::uint32_t rate_hz, protocol::Hand hand) {
  if (!valid_glove_frame_count(frames))
    throw std::invalid_argument("a glove tracks 16 or 6 frames, not " + std::to_string(frames));
  protocol::Hello hello;
  hello.device_kind = protocol::DeviceKind::kGlove;
  hello.requested_rate_hz = rate_hz;
  hello.hand = hand;
  if (!hello.client_name.assign(client_name)) throw std::invalid_argument("client name longer than 64 bytes");
  for (int id = 0; id < frames; ++id) {
    protocol::TrackedFrame frame;
    frame.id = static_cast<std::uint16_t>(id);
    frame.dof = 6;
    frame.name.assign(glove_frame_name(frames, id));  // <= 14 bytes ("little_proximal")
    hello.frames.push_back(frame);
  }
  if (const protocol::RejectReason r = protocol::validate(hello); r != protocol::RejectReason::kNone)
    throw std::invalid_argument("the Hello would be refused: " + std::string(protocol::to_string(r)));
  return hello;
}

void GloveServo::begin(std::uint64_t ticks) {
  if (trace_ != nullptr) trace_->reserve(trace_->size() + ticks);
}

void GloveServo::write_pose(protocol::PoseSample& pose) noexcept {
  const auto poses = sim_.frame_poses();
  pose.poses.resize(static_cast<std::size_t>(sim_.frames()));
  for (int id = 0; id < sim_.frames(); ++id) {
    protocol::FramePose& out = pose.poses[static_cast<std::size_t>(id)];
    const RigidPose& in = poses[static_cast<std::size_t>(id)];
    out.frame = static_cast<std::uint16_t>(id);
    out.position_m = {static_cast<float>(in.p_m.x()), static_cast<float>(in.p_m.y()), static_cast<float>(in.p_m.z())};
    out.orientation = {static_cast<float>(in.q.w()), static_cast<float>(in.q.x()), static_cast<float>(in.q.y()),
                       static_cast<float>(in.q.z())};
  }
}

void GloveServo::apply(const protocol::ForceSample& sample) noexcept {
  for (const protocol::FrameWrench& w : sample.wrenches) {
    const protocol::Vec3& f = w.wrench.force_n;
    const protocol::Vec3& t = w.wrench.torque_nm;
    sim_.set_wrench(w.frame, {f.x, f.y, f.z}, {t.x, t.y, t.z}, w.flags & protocol::ForceFlags::kInContact);
  }
}

void GloveServo::end_tick(bool sent) noexcept {
  sim_.record_tick();
  if (trace_ == nullptr) return;
  GloveTraceRow& row = trace_->emplace_back();
  row.t_s = sim_.time_s();
  row.q_C_rad = sim_.commanded_angles();
  row.q_rad = sim_.joints().q_rad;
  row.p_palm_C_m = sim_.trajectory().palm_position(sim_.time_s());
  row.p_palm_m = sim_.palm().p_DT_m;
  for (int id = 0; id < sim_.frames(); ++id) row.f_N[static_cast<std::size_t>(id)] = sim_.force(id);
  row.in_contact = sim_.in_contact();
  row.sent = sent;
}

void GloveServo::summarize(ServoResult& r) const {
  r.contact_ticks = sim_.contact_ticks();
  r.force_max_n = sim_.force_max_n();
  r.force_rms_n = sim_.force_rms_n();
  r.passivity_energy_j = sim_.passivity_energy_j();
  r.penetration_max_m = sim_.penetration_max_m();
}

}  // namespace hapticd::sim
