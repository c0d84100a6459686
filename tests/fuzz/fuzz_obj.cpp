// libFuzzer target: the Wavefront OBJ loader (load_obj) and, on what it accepts, the enclosed
// volume. MeshError is the documented failure.
#include <cstdint>

#include "hand_models/embedded_surface.hpp"
#include "tests/fuzz/fuzz_util.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string path = hapticd::fuzz::scratch().write("surface.obj", hapticd::fuzz::as_text(data, size));
  try {
    const hapticd::hand::SurfaceMesh surface = hapticd::hand::load_obj(path);
    (void)hapticd::hand::enclosed_volume(surface);
  } catch (const hapticd::hand::MeshError&) {
  }
  return 0;
}
