// libFuzzer target: the scene loader (parse_scene_text), on any text.
//
// Relative asset paths resolve against a private scratch directory holding empty placeholders of
// the assets the shipped scenes name (the loader only checks that an asset is a readable regular
// file; it does not parse it), so inputs derived from scenes/ get past their file keys. An input
// may still name an absolute path: the loader then only stats it and opens it for reading.
// SceneError is the documented failure; anything else escaping is a finding.
#include <cstdint>
#include <string>

#include "server/world/scene_loader.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

const std::string& base_dir() {
  static const std::string dir = [] {
    auto& s = hapticd::fuzz::scratch();
    for (const char* asset : {"assets/bunny.obj", "assets/bunny_271.node", "assets/bunny_271.ele",
                              "assets/bunny_271.embed", "assets/letter_a.obj", "assets/letter_a_65.node",
                              "assets/letter_a_65.ele", "assets/letter_a_65.embed", "box.msh"})
      s.write(asset, "");
    return s.path().string();
  }();
  return dir;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(hapticd::fuzz::as_text(data, size));
  try {
    const hapticd::SceneDesc scene = hapticd::parse_scene_text(text, base_dir(), "fuzz.json");
    (void)scene;
  } catch (const hapticd::SceneError&) {
  }
  return 0;
}
