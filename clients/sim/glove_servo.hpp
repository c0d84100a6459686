#pragma once

// The simulated glove on the wire: its Hello, the servo loop's ServoDevice for it (poses of every
// frame out, per-frame wrenches in), and its per-tick trace.

#include <array>
#include <cstdint>
#include <string_view>
#include <vector>

#include "clients/sim/glove_simulation.hpp"
#include "clients/sim/servo_loop.hpp"
#include "protocol/messages.hpp"

namespace hapticd::sim {

// A glove's Hello: kind Glove, frames ids 0 .. frames-1 (16 or 6, glove_model.hpp), 6 DoF, named
// glove_frame_name() ("palm", "thumb_proximal", ...). Throws std::invalid_argument for another
// frame count or a client name the protocol refuses.
protocol::Hello glove_hello(int frames, std::string_view client_name, std::uint32_t rate_hz,
                            protocol::Hand hand = protocol::Hand::kUnspecified);

// One tick of a glove run, for --trace.
struct GloveTraceRow {
  double t_s = 0.0;
  JointVector q_C_rad = JointVector::Zero();  // commanded angles
  JointVector q_rad = JointVector::Zero();    // the joints
  Vec3d p_palm_C_m;                           // commanded palm position
  Vec3d p_palm_m;                             // palm position
  std::array<Vec3d, kMaxGloveFrames> f_N{};   // force held per frame id
  bool in_contact = false;                    // any frame
  bool sent = false;                          // false: a missed tick
};

class GloveServo final : public ServoDevice {
 public:
  // `sim` must step by servo_period_s() of the loop's rate; it and `trace` (appended to, one row a
  // tick, reserved in begin()) outlive the loop.
  explicit GloveServo(GloveSimulation& sim, std::vector<GloveTraceRow>* trace = nullptr) : sim_(sim), trace_(trace) {}

  void begin(std::uint64_t ticks) override;
  void advance(double scale) noexcept override {
    sim_.set_output_scale(scale);
    sim_.advance();
  }
  // Frames 0 .. frames-1 with their ids, positions and orientations (float32 on the wire).
  void write_pose(protocol::PoseSample& pose) noexcept override;
  // Each wrench for a frame of this glove is held with its own InContact flag; frames the reply
  // lacks keep their previous wrench.
  void apply(const protocol::ForceSample& sample) noexcept override;
  void end_tick(bool sent) noexcept override;
  void summarize(ServoResult& result) const override;

 private:
  GloveSimulation& sim_;
  std::vector<GloveTraceRow>* trace_;
};

}  // namespace hapticd::sim
