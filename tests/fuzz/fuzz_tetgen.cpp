// libFuzzer target: the TetGen loader (load_tetgen). The input is the .node file, then a NUL
// byte, then the .ele file (no NUL: an empty .ele). MeshError is the documented failure.
#include <cstdint>
#include <cstring>
#include <string_view>

#include "hand_models/mesh_io.hpp"
#include "tests/fuzz/fuzz_util.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view input = hapticd::fuzz::as_text(data, size);
  const std::size_t nul = input.find('\0');
  const std::string_view node = input.substr(0, nul);
  const std::string_view ele = nul == std::string_view::npos ? std::string_view{} : input.substr(nul + 1);
  const auto& dir = hapticd::fuzz::scratch();
  const std::string node_path = dir.write("mesh.node", node);
  const std::string ele_path = dir.write("mesh.ele", ele);
  try {
    const hapticd::hand::TetMesh mesh = hapticd::hand::load_tetgen(node_path, ele_path);
    (void)mesh;
  } catch (const hapticd::hand::MeshError&) {
  }
  return 0;
}
