#pragma once
// A fine closed triangle surface (for collision and display) embedded in a coarse
// regular tet grid (for deformation): each surface vertex follows the tet that
// contains it through fixed barycentric weights, as for seed paper 004's bunny
// (4000 triangles in 271 tets) and letters (~175 triangles in ~65 tets).
//
// Meshing: the grid's planes sit uneven fractions of a cell (0.37, 0.21, 0.43) off
// the low faces of the surface's bounding box. A cell is kept when a surface
// triangle touches it (closed cell, separating-axis test) or when it lies inside
// the solid (generalized winding number of the surface at the cell centre, one
// evaluation per face-connected region of untouched cells). Kept cells are split
// into 6 Kuhn tets (conforming between neighbours) and only the largest
// face-connected component survives. Every part of the surface and of the solid is
// then covered; the mesh overhangs the surface by up to one cell, so its volume
// exceeds the solid's (4.6x for the bunny at 270 tets).
#include <Eigen/Core>
#include <string>
#include <vector>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

struct SurfaceMesh {
  std::vector<Eigen::Vector3d> vertices;  // m
  std::vector<Triangle> triangles;        // closed, counter-clockwise seen from outside
};

struct EmbeddedBody {
  TetMesh mesh;                               // coarse simulation mesh (finalize_mesh applied), covers the surface
  SurfaceMesh surface;                        // the fine surface, rest positions
  std::vector<int> surface_tet;               // containing tet per surface vertex
  std::vector<Eigen::Vector4d> surface_bary;  // weights of surface_tet's nodes in its node order; sum 1, each >= -1e-9
  double spacing = 0.0;                       // grid cell edge, m
};

// Spacing searched so the tet count is close to target_tets: within ~1 % where the
// count's steps allow (it is a step function of the spacing; counts are multiples
// of 6), never coarser than one cell over the whole surface. Throws
// std::invalid_argument for target_tets <= 0 and MeshError for a surface that is
// empty, has an index out of range, a repeated index in a triangle or a
// non-finite vertex, or whose vertices are not all covered by the kept component
// (parts more than a cell apart, or vertices used by no triangle far from the rest).
EmbeddedBody embed_surface(const SurfaceMesh& surface, int target_tets);

// Same with a given grid spacing (m). Throws std::invalid_argument for a spacing
// that is not finite and positive or that needs more than 2^21 grid cells (cells
// over the bounding box, kept or not).
EmbeddedBody embed_surface_with_spacing(const SurfaceMesh& surface, double spacing);

// Volume enclosed by a closed surface (divergence theorem), m^3; positive when
// the triangles face outward.
double enclosed_volume(const SurfaceMesh& surface);

// Wavefront OBJ: 'v x y z' (extra values such as w or vertex colours are checked
// as numbers and ignored) and 'f' with 1-based, or negative (relative), vertex
// indices in the forms 'a', 'a/b', 'a//c', 'a/b/c'; polygons are fan-triangulated.
// Other statements (vt, vn, g, o, s, usemtl, l, ...) are ignored. Every failure is
// a MeshError "<path>:<line>: ..." (line 0: the file as a whole).
SurfaceMesh load_obj(const std::string& path);

// Shortest round-trip decimal coordinates, 1-based triangles. Throws MeshError if
// the file cannot be written.
void save_obj(const std::string& path, const SurfaceMesh& surface);

// .embed text format: '#' starts a comment; line 1 "hapticd-embedding 1"; then
// "<surface vertices> <tets> <spacing m>"; then one line per surface vertex, in
// order: "<tet> <w0> <w1> <w2> <w3>" (tet: 0-based position in the mesh's element
// list; weights in that tet's node order). Numbers are written shortest
// round-trip, so saving and loading is exact.
void save_embedding(const std::string& path, const EmbeddedBody& body);

// Reads an .embed file for the given mesh and surface and returns the complete
// body. Strict: MeshError "<path>:<line>: ..." for a bad header, counts that do
// not match the mesh or surface, a tet out of range, a non-finite or negative
// (< -1e-9) weight, weights not summing to 1 (1e-9), weights that put a vertex
// more than 1e-6 of the mesh's size away from the surface's vertex, missing or
// extra lines.
EmbeddedBody load_embedding(const std::string& path, TetMesh mesh, SurfaceMesh surface);

// load_obj + load_tet_mesh (mesh_io.hpp) + load_embedding, e.g.
// ("bunny.obj", "bunny_271", "bunny_271.embed").
EmbeddedBody load_embedded_body(const std::string& obj_path, const std::string& mesh_path,
                                const std::string& embed_path);

}  // namespace hapticd::hand
