#pragma once
// A procedural adult hand: palm plus five three-phalanx fingers, defined as a
// signed distance field and embedded in a regular tetrahedral grid, with a
// smooth skin embedded in the tets.
//
// Conventions:
//  - SI units (metres).
//  - Hand frame: origin at the palm centre, fingers extend along +y, the palmar
//    side faces -z, the dorsal side +z.
//  - Right hand (default): thumb on the -x side (right hand lying palm-down on
//    a table, seen from above, thumb on the left). The left hand is the exact
//    mirror image (x -> -x); its tets stay positively oriented and its surfaces
//    outward.
//  - Pose: fingers spread a little and slightly flexed; the thumb leaves the
//    palm from its radial side near the wrist, about 45 degrees away from the
//    index and a little toward palmar. Its proximal segment is the
//    metacarpal-like part that forms the thenar eminence.
//  - Sizes: palm 9 x 8 x 2.5 cm (narrowing to 6.8 cm at the wrist), fingers
//    1.5-2.3 cm thick, hand length about 18.7 cm.
//
// Meshing: a grid cell is kept when it may touch the shape: SDF at its centre
// < (sqrt(3)/2) h, refined on 2 levels of sub-cubes with the same Lipschitz
// bound, so kept cells come within about h/4 of the shape instead of 0.87 h
// while still covering all of it. The mesh overhangs the hand by up to one
// cell. Cells are split into 6 Kuhn tets along the main diagonal (conforming
// without parity tricks). Every cell a bone axis passes through is kept and
// only the largest face-connected component survives, so no finger is lost.
// Gaps between adjacent long fingers grow from ~4 mm halfway along the proximal
// phalanges to ~8 mm at the 2nd joints and >1.5 cm at the distal phalanges. A
// cell wider than the gap bridges it, so the mesh fuses neighbouring fingers:
// at 20k tets (5 mm cells) up to about the 2nd joints, at 5k up to about the
// 3rd joints, at 1.7k and below the four fingers form a mitten (the thumb stays
// separate from 1.7k up). The skin keeps the fingers separate at every size.
// Covering makes the mesh volume exceed the hand's (about 1.6x at 20k tets, 5x
// at 350), so a density applied to the mesh overestimates the mass by as much.
//
// Skeleton-aware mesh (separate_fingers, for gloves whose fingers move on their
// own): the same cells and tets, but each kept cell belongs to the part (palm or
// finger) whose own SDF is smallest at its centre; the cells of the base joints
// are palm, a finger's bone axes claim the cells they cross (palm where two
// fingers' bones share one), and a finger's cells cut off from its bones join
// their neighbours' part. A grid node gets one copy per finger among its cells,
// except on a palm cell, where all its cells share one node: fingers meet only
// through palm flesh (the knuckles and webs) and each finger is one face-connected
// piece on the palm. Neighbouring long fingers then share no node farther than
// 2-6 mm beyond their base joints at 1.7k-20k tets (the webs stop at the
// knuckles, shorter than a real hand's; thumb and index share none), however
// wide the cells. The tet count, the tets' shapes and the skin are the
// default's (568 nodes instead of 501 at 1.7k). A cell wider than the gap holds skin of both fingers but is one
// finger's: a skin vertex of the other (by nearest part) goes to the nearest tet
// of its own finger or the palm, extrapolating (about 1.5 % of the vertices at
// 1.7k, smallest weight -0.27; -0.43 at 20k). Handle spheres cannot tell copies of
// one grid node apart: at 1.7k a 1.2-cell sphere around a phalanx also takes
// copies belonging to the neighbouring fingers.
//
// Skin: marching tetrahedra on the SDF sampled on the Kuhn tets of a uniform
// refinement of the grid (each cell split into n^3 cells, the smallest n that
// samples at 6 mm or finer; n = 1 for cells up to 6 mm, i.e. the mesh nodes
// themselves). The refined tets nest inside the mesh tets, so every skin
// vertex has exact barycentric coordinates in one mesh tet.
#include "hand_models/tet_mesh.hpp"

#include <Eigen/Core>
#include <array>
#include <string>
#include <vector>

namespace hapticd::hand {

struct ProceduralHandOptions {
  int target_tets = 1700;  // used when spacing <= 0: spacing chosen so the tet count is near this
  double spacing = 0.0;    // grid cell edge in m
  bool left = false;       // mirror image (left hand); tets stay positively oriented
  // Skeleton-aware mesh (see above): fingers share nodes only through palm flesh, so each moves on
  // its own however coarse the grid. Same cells and tet count; more nodes.
  bool separate_fingers = false;
};

// Part labels of ProceduralHand::tet_part and node_part: fingers are 0-4 (finger_index), the palm this.
inline constexpr int kHandPalmPart = 5;

// A rigid frame of the skeleton, usable as a handle seed.
struct HandFrame {
  std::string name;   // "palm", "thumb_proximal", ..., "little_distal"
  Eigen::Vector3d p;  // seed point (centre of the segment), m, hand frame
  Eigen::Matrix3d R;  // columns: segment axis frame (y along the bone toward the tip, z dorsal), det +1
  double radius;      // suggested handle sphere radius, m (covers the segment's core, stays inside the skin)
};

struct ProceduralHand {
  TetMesh mesh;     // the simulation mesh (finalize_mesh already applied)
  double spacing;   // grid cell edge used, m
  HandFrame palm;
  std::array<HandFrame, 15> phalanges;  // finger-major: thumb, index, middle, ring, little; proximal, middle, distal
  // Per finger: base joint, 2nd joint, 3rd joint, fingertip (the skin point farthest along the distal axis).
  std::array<std::array<Eigen::Vector3d, 4>, 5> joints;
  // Smooth skin embedded in the tets (for display and collision): each vertex is
  // given by barycentric coordinates in one tet.
  std::vector<Eigen::Vector3d> skin_vertices;  // rest positions
  std::vector<Triangle> skin_triangles;        // outward, counter-clockwise; a closed manifold
  std::vector<int> skin_tet;                   // containing tet per vertex
  std::vector<Eigen::Vector4d> skin_bary;      // weights of skin_tet's nodes, in its node order (sum 1, each >= 0,
                                               // except where separate_fingers extrapolates, see above)
  // separate_fingers only (empty otherwise): the part of each tet's grid cell, and the part whose copy
  // each node is (kHandPalmPart: a node shared by every part at it, on palm flesh).
  std::vector<int> tet_part;
  std::vector<int> node_part;
};

// Throws std::invalid_argument for a spacing that is non-finite or positive but
// outside [1 mm, 10 cm] (1 mm already gives about 2M tets), or, with spacing <= 0,
// a non-positive target. Takes ~0.1 s for 20k tets (-O2).
ProceduralHand make_procedural_hand(const ProceduralHandOptions& options = {});

// Grid spacing whose mesh has close to target_tets tets: within about 1 % for
// targets of 100 to 10^6 (the count is a step function of the spacing). Searches
// spacings between 1 mm and 10 cm, so below ~40 tets it returns 10 cm. Throws
// std::invalid_argument if target_tets <= 0.
double hand_spacing_for_tets(int target_tets);

// Signed distance from p (m, hand frame) to the hand's surface, negative inside;
// a 1-Lipschitz bound, exact away from the finger-palm blends.
double procedural_hand_sdf(const Eigen::Vector3d& p, bool left = false);

// The part of the hand nearest p (m, hand frame): the finger (0-4) or the palm (kHandPalmPart)
// whose own SDF, without the blend, is smallest there (the palm on ties). separate_fingers labels
// grid cells and skin vertices with it.
int procedural_hand_nearest_part(const Eigen::Vector3d& p, bool left = false);

// The mesh covers the hand with whole grid cells, so it holds more volume than
// the hand (1.6x at 20k tets, 5x at 350): the density that gives the mesh the
// hand's mass, density_kg_m3 times the skin's enclosed volume.
double embedding_density(const ProceduralHand& hand, double density_kg_m3);

// "thumb" = 0, "index" = 1, "middle" = 2, "ring" = 3, "little" = 4; -1 otherwise.
int finger_index(const std::string& finger);

}  // namespace hapticd::hand
