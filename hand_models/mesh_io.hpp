#pragma once
// Tetrahedral mesh loaders: TetGen (.node + .ele) and Gmsh ASCII (.msh 2.2 and 4.1).
#include <string>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

// Every loader returns a finalized mesh (see finalize_mesh) without orphan nodes;
// nodes keep their file order. Every failure is a MeshError whose message starts
// with "<path>:<line>: " and says what was expected and what was found. Line 0
// means the file as a whole (missing, unreadable, unknown kind); problems found
// at end of file point at its last line.

// The index base (0 or 1) comes from the first point of the .node file and
// applies to every index in both files.
TetMesh load_tetgen(const std::string& node_path, const std::string& ele_path);

// Keeps 4-node tets (type 4); skips points, lines, triangles and other
// lower-dimensional elements; rejects 10-node tets and binary files.
TetMesh load_gmsh(const std::string& path);

// "<base>.msh" -> Gmsh; "<base>.node", "<base>.ele" or "<base>" -> TetGen pair
// "<base>.node" + "<base>.ele".
TetMesh load_tet_mesh(const std::string& path);

}  // namespace hapticd::hand
