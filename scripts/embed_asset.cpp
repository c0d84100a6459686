// embed_asset <surface.obj> <target_tets> <out_base>: embeds a closed surface in a
// coarse Kuhn tet grid (embed_surface) and writes <out_base>.node/.ele (TetGen,
// 0-based) and <out_base>.embed, then reloads them to check they match.
// Built and run by scripts/make-assets.
#include <charconv>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <string>

#include "hand_models/embedded_surface.hpp"
#include "hand_models/mesh_io.hpp"

namespace {

std::string num(double v) {
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

void save_tetgen(const std::string& base, const hapticd::hand::TetMesh& mesh, const std::string& origin) {
  std::ofstream node(base + ".node"), ele(base + ".ele");
  node << "# " << origin << "\n" << mesh.num_nodes() << " 3 0 0\n";
  for (int i = 0; i < mesh.num_nodes(); ++i) {
    node << i << ' ' << num(mesh.X[i].x()) << ' ' << num(mesh.X[i].y()) << ' ' << num(mesh.X[i].z()) << '\n';
  }
  ele << "# " << origin << "\n" << mesh.num_tets() << " 4 0\n";
  for (int e = 0; e < mesh.num_tets(); ++e) {
    const hapticd::hand::Tet& t = mesh.tets[e];
    ele << e << ' ' << t[0] << ' ' << t[1] << ' ' << t[2] << ' ' << t[3] << '\n';
  }
  node.flush();
  ele.flush();
  if (!node || !ele) throw hapticd::hand::MeshError(base + ".node/.ele: cannot write");
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: embed_asset <surface.obj> <target_tets> <out_base>\n";
    return 2;
  }
  try {
    const std::string obj = argv[1];
    const std::string base = argv[3];
    const int target = std::stoi(argv[2]);
    const hapticd::hand::SurfaceMesh surface = hapticd::hand::load_obj(obj);
    const hapticd::hand::EmbeddedBody body = hapticd::hand::embed_surface(surface, target);
    const std::string name = obj.substr(obj.find_last_of('/') + 1);
    const std::string origin = "embed_surface(" + name + ", " + std::to_string(target) + "), spacing " +
                               num(body.spacing) + " m; see scenes/assets/README";
    save_tetgen(base, body.mesh, origin);
    hapticd::hand::save_embedding(base + ".embed", body);
    const hapticd::hand::EmbeddedBody back = hapticd::hand::load_embedded_body(obj, base, base + ".embed");
    if (back.mesh.num_tets() != body.mesh.num_tets() || back.surface_tet != body.surface_tet) {
      std::cerr << "embed_asset: " << base << " does not reload identically\n";
      return 1;
    }
    std::printf("%s: %zu vertices, %zu triangles, volume %.4g m^3 -> %s: %d nodes, %d tets, spacing %.4g m\n",
                name.c_str(), surface.vertices.size(), surface.triangles.size(),
                hapticd::hand::enclosed_volume(surface), base.c_str(), body.mesh.num_nodes(), body.mesh.num_tets(),
                body.spacing);
  } catch (const std::exception& e) {
    std::cerr << "embed_asset: " << e.what() << '\n';
    return 1;
  }
  return 0;
}
