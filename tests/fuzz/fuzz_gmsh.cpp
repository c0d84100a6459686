// libFuzzer target: the Gmsh ASCII loader (load_gmsh, .msh 2.2 and 4.1). MeshError is the
// documented failure.
#include <cstdint>

#include "hand_models/mesh_io.hpp"
#include "tests/fuzz/fuzz_util.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string path = hapticd::fuzz::scratch().write("mesh.msh", hapticd::fuzz::as_text(data, size));
  try {
    const hapticd::hand::TetMesh mesh = hapticd::hand::load_gmsh(path);
    (void)mesh;
  } catch (const hapticd::hand::MeshError&) {
  }
  return 0;
}
