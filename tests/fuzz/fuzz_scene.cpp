// libFuzzer target: the scene loader (parse_scene_text), on any text; then, for what loads, the
// World it describes, three steps of it, and each device's link and the Welcome that would carry
// its limits (tests/fuzz/README.md).
//
// Relative asset paths resolve against a private scratch directory holding copies of the shipped
// assets (scenes/assets) and an empty box.msh, so inputs derived from scenes/ get past their file
// keys and build. An input may still name an absolute path: the loader then only stats it and
// opens it for reading, and the World may fail to read it.
//
// Oracles: SceneError is the loader's only failure. A scene the loader accepts whose shapes are all
// primitives (no file to misread) and whose hands are all fem (the one model built so far) must
// build: any exception from the World or make_device_link is then a finding, as is a non-finite
// handle or body pose after a step (World::step promises none) and a Welcome the encoder refuses
// (the user-found bug: a device limit beyond the wire's left every Hello unanswered). Scenes with
// files may fail to build with the World's documented std::exception (a placeholder or unreadable
// file, or a mass from a mesh's volume out of range).
//
// Cost: only scenes of primitives with palm-handled hands are built (cheap_to_build); hands above 4 x kMinHandTets are built at kMinHandTets (the loader's own lower bound; the
// count changes only the mesh's spacing), and the flesh distance grids are left out (hand-hand
// contact, hand contact in scenes with deformable objects), so an input builds and steps within the
// 10 s limit under the sanitizers.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "protocol/codec.hpp"
#include "protocol/limits.hpp"
#include "server/haptic/device_link.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

namespace fs = std::filesystem;

const std::string& base_dir() {
  static const std::string dir = [] {
    auto& s = hapticd::fuzz::scratch();
    for (const fs::directory_entry& e : fs::directory_iterator(fs::path(HAPTICD_SCENES_DIR) / "assets")) {
      if (!e.is_regular_file()) continue;
      std::ifstream in(e.path(), std::ios::binary);
      const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
      s.write("assets/" + e.path().filename().string(), bytes);
    }
    s.write("box.msh", "");
    return s.path().string();
  }();
  return dir;
}

[[noreturn]] void finding(const std::string& what, const std::string& detail) {
  std::fprintf(stderr, "fuzz_scene: %s: %s\n", what.c_str(), detail.c_str());
  std::abort();
}

// Only primitives and fem hands: nothing but the scene's numbers decides whether it builds.
bool must_build(const hapticd::world::SceneDesc& scene) {
  for (const hapticd::world::ObjectDesc& o : scene.objects)
    if (o.shape.type == hapticd::world::ShapeType::mesh || o.shape.type == hapticd::world::ShapeType::tet_mesh)
      return false;
  for (const hapticd::world::HandDesc& h : scene.hands)
    if (h.model != hapticd::world::HandModelKind::fem) return false;
  return true;
}

void check_finite(const hapticd::world::World& world) {
  const hapticd::world::WorldSnapshot& s = world.snapshot();
  for (const auto& hand : s.handles)
    for (const hapticd::hand::HandleState& h : hand)
      if (!h.p_WH.allFinite() || !h.q_WH.coeffs().allFinite())
        finding("non-finite handle pose", "step " + std::to_string(s.step));
  for (const hapticd::world::RigidBodyState& b : s.bodies)
    if (!b.p_WO.allFinite() || !b.q_WO.coeffs().allFinite() || !b.v_WO.allFinite() || !b.w_W.allFinite())
      finding("non-finite body state", "step " + std::to_string(s.step));
}

// The Welcome the haptic core sends for this link (fill_welcome, as its handshake), encoded.
void check_welcome(const hapticd::haptic::DeviceLink& link, hapticd::protocol::Encoder& encoder) {
  namespace protocol = hapticd::protocol;
  std::uint16_t ids[hapticd::haptic::kMaxHapticHandles];
  for (int j = 0; j < link.handles; ++j) ids[j] = static_cast<std::uint16_t>(j);
  protocol::Welcome w;
  hapticd::haptic::fill_welcome(link, 1, 1000, {ids, static_cast<std::size_t>(link.handles)}, w);
  const protocol::EncodeResult r = encoder.encode(w);
  if (!r.ok())
    finding("the Welcome of device " + link.name + " does not encode",
            std::string(protocol::to_string(r.reason)) + ", force " + std::to_string(link.limits.max_force_n) +
                ", torque " + std::to_string(link.limits.max_torque_nm) + ", rate " +
                std::to_string(link.limits.max_force_rate_n_s));
}

// Only scenes that build and step within the 10 s limit under the sanitizers on a loaded 2-core
// machine: no mesh object (its distance grid alone took over 60 s for the shipped bunny) and only
// palm-handled hands (a 16-handle glove's world took 56 s). The others are fuzzed through the loader.
bool cheap_to_build(const hapticd::world::SceneDesc& scene) {
  if (!must_build(scene)) return false;
  for (const hapticd::world::HandDesc& h : scene.hands)
    if (h.handles != hapticd::world::HandleSet::palm) return false;
  return true;
}

void build_and_step(hapticd::world::SceneDesc scene) {
  if (!cheap_to_build(scene)) return;
  for (hapticd::world::HandDesc& h : scene.hands)
    if (h.resolution_tets > 4 * hapticd::world::kMinHandTets) h.resolution_tets = hapticd::world::kMinHandTets;
  hapticd::world::WorldOptions options;
  options.contact.reset();  // the scene's contact model: both get fuzzed
  // The flesh distance grids (1-3 mm cells) take tens of seconds under the sanitizers: hands pass
  // through each other, and touch deformable objects only in a scene without two hands.
  options.hand_hand_contacts = false;
  if (scene.needs_deformable_objects()) options.hand_contacts = false;
  try {
    hapticd::world::World world(scene, options);
    check_finite(world);
    for (int k = 0; k < 3; ++k) {
      world.step();
      check_finite(world);
    }
    static hapticd::protocol::Encoder encoder;
    for (const hapticd::world::DeviceDesc& d : scene.devices) check_welcome(hapticd::haptic::make_device_link(world, d, 1000.0), encoder);
  } catch (const std::exception& e) {
    finding("a scene of primitives and fem hands did not build", e.what());
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(hapticd::fuzz::as_text(data, size));
  hapticd::world::SceneDesc scene;
  try {
    scene = hapticd::world::parse_scene_text(text, base_dir(), "fuzz.json");
  } catch (const hapticd::world::SceneError&) {
    return 0;
  }
  build_and_step(std::move(scene));
  return 0;
}
