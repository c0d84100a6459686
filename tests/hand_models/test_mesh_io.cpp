#include <gtest/gtest.h>

#include "file_test_util.hpp"
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <vector>

#include "hand_models/mesh_io.hpp"

namespace hapticd::hand {
namespace {

namespace fs = std::filesystem;

const std::string kMeshes = std::string(HAPTICD_TEST_DATA) + "/meshes/";

// Unit cube, Kuhn split into 6 tets; line n of kEle holds tet n - 2, line n of kNode point n - 2.
const std::string kNode =
    "8 3 0 0\n"
    "0 0 0 0\n"
    "1 1 0 0\n"
    "2 0 1 0\n"
    "3 1 1 0\n"
    "4 0 0 1\n"
    "5 1 0 1\n"
    "6 0 1 1\n"
    "7 1 1 1\n";
const std::string kEle =
    "6 4 0\n"
    "0 0 1 3 7\n"
    "1 0 1 5 7\n"
    "2 0 2 3 7\n"
    "3 0 2 6 7\n"
    "4 0 4 5 7\n"
    "5 0 4 6 7\n";

// One tet; line numbers are quoted by the Gmsh error tests.
const std::string kGmsh22 =
    "$MeshFormat\n"        // 1
    "2.2 0 8\n"            // 2
    "$EndMeshFormat\n"     // 3
    "$Nodes\n"             // 4
    "4\n"                  // 5
    "1 0 0 0\n"            // 6
    "2 1 0 0\n"            // 7
    "3 0 1 0\n"            // 8
    "4 0 0 1\n"            // 9
    "$EndNodes\n"          // 10
    "$Elements\n"          // 11
    "2\n"                  // 12
    "1 2 2 0 1 1 2 3\n"    // 13
    "2 4 2 0 1 1 2 3 4\n"  // 14
    "$EndElements\n";      // 15
const std::string kGmsh41 =
    "$MeshFormat\n"     // 1
    "4.1 0 8\n"         // 2
    "$EndMeshFormat\n"  // 3
    "$Nodes\n"          // 4
    "1 4 1 4\n"         // 5
    "3 1 0 4\n"         // 6
    "1\n2\n3\n4\n"      // 7-10
    "0 0 0\n"           // 11
    "1 0 0\n"           // 12
    "0 1 0\n"           // 13
    "0 0 1\n"           // 14
    "$EndNodes\n"       // 15
    "$Elements\n"       // 16
    "1 1 1 1\n"         // 17
    "3 1 4 1\n"         // 18
    "1 1 2 3 4\n"       // 19
    "$EndElements\n";   // 20

std::vector<std::string> split_lines(const std::string& text) {
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

std::string join_lines(const std::vector<std::string>& lines) {
  std::string out;
  for (const std::string& line : lines) out += line + "\n";
  return out;
}

// 1-based line n of text replaced by replacement.
std::string replace_line(const std::string& text, int n, const std::string& replacement) {
  std::vector<std::string> lines = split_lines(text);
  lines.at(static_cast<std::size_t>(n - 1)) = replacement;
  return join_lines(lines);
}

std::string erase_line(const std::string& text, int n) {
  std::vector<std::string> lines = split_lines(text);
  lines.erase(lines.begin() + (n - 1));
  return join_lines(lines);
}

std::string first_lines(const std::string& text, int n) {
  std::vector<std::string> lines = split_lines(text);
  lines.resize(static_cast<std::size_t>(n));
  return join_lines(lines);
}

using testing_util::throws_mesh_error;

void expect_unit_cube(const TetMesh& m, int tets) {
  EXPECT_EQ(m.num_nodes(), 8);
  EXPECT_EQ(m.num_tets(), tets);
  EXPECT_NEAR(total_volume(m), 1.0, 1e-12);
  EXPECT_EQ(m.surface.size(), 12u);
  for (const Tet& t : m.tets) EXPECT_GT(signed_volume(m.X[t[0]], m.X[t[1]], m.X[t[2]], m.X[t[3]]), 0.0);
}

void expect_same_mesh(const TetMesh& a, const TetMesh& b) {
  ASSERT_EQ(a.num_nodes(), b.num_nodes());
  for (int i = 0; i < a.num_nodes(); ++i) EXPECT_EQ(a.X[i], b.X[i]) << "node " << i;
  EXPECT_EQ(a.tets, b.tets);
  EXPECT_EQ(a.surface, b.surface);
}

class MeshIoTest : public testing_util::TempDirTest {
 protected:
  // Writes bad.node/bad.ele and loads them as a TetGen pair.
  std::function<void()> tetgen(const std::string& node, const std::string& ele) {
    node_ = write("bad.node", node);
    ele_ = write("bad.ele", ele);
    return [this] { load_tetgen(node_, ele_); };
  }

  std::function<void()> gmsh(const std::string& text) {
    msh_ = write("bad.msh", text);
    return [this] { load_gmsh(msh_); };
  }

  std::string node_, ele_, msh_;
};

// ---- good meshes ----

TEST_F(MeshIoTest, TetgenZeroBasedCubeWithCommentsLoads) {
  const TetMesh m = load_tetgen(kMeshes + "cube6_0based.node", kMeshes + "cube6_0based.ele");
  expect_unit_cube(m, 6);
  EXPECT_EQ(m.X[5], Eigen::Vector3d(1, 0, 1));
  for (const Tet& t : m.tets) EXPECT_NEAR(signed_volume(m.X[t[0]], m.X[t[1]], m.X[t[2]], m.X[t[3]]), 1.0 / 6, 1e-15);
}

TEST_F(MeshIoTest, TetgenOneBasedCubeWithAttributesMatchesZeroBased) {
  const TetMesh zero = load_tetgen(kMeshes + "cube6_0based.node", kMeshes + "cube6_0based.ele");
  const TetMesh one = load_tetgen(kMeshes + "cube6_1based.node", kMeshes + "cube6_1based.ele");
  expect_unit_cube(one, 6);
  expect_same_mesh(zero, one);
}

TEST_F(MeshIoTest, TetgenOrphanNodesAreDroppedAndOrderKept) {
  // 10 points listed out of order; points 4 and 9 belong to no tet.
  const TetMesh m = load_tetgen(kMeshes + "cube5_orphans.node", kMeshes + "cube5_orphans.ele");
  expect_unit_cube(m, 5);
  const Eigen::Vector3d corners[8] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {1, 1, 0},
                                      {0, 0, 1}, {1, 0, 1}, {0, 1, 1}, {1, 1, 1}};
  for (int i = 0; i < 8; ++i) EXPECT_EQ(m.X[i], corners[i]) << "node " << i;
  EXPECT_EQ(m.tets[4], (Tet{1, 2, 4, 7}));  // central tet, renumbered past orphan 4
}

TEST_F(MeshIoTest, GmshV22AndV41LoadIdenticallyToTetgen) {
  const TetMesh v22 = load_gmsh(kMeshes + "cube6_v22.msh");
  const TetMesh v41 = load_gmsh(kMeshes + "cube6_v41.msh");
  expect_unit_cube(v22, 6);  // node tag 99 only carries a point element, so it is dropped
  expect_same_mesh(v22, v41);
  expect_same_mesh(v22, load_tetgen(kMeshes + "cube6_0based.node", kMeshes + "cube6_0based.ele"));
}

TEST_F(MeshIoTest, LoadTetMeshDispatchesOnExtension) {
  EXPECT_EQ(load_tet_mesh(kMeshes + "cube6_v41.msh").num_tets(), 6);
  EXPECT_EQ(load_tet_mesh(kMeshes + "cube5_orphans.node").num_tets(), 5);
  EXPECT_EQ(load_tet_mesh(kMeshes + "cube5_orphans.ele").num_tets(), 5);
  EXPECT_EQ(load_tet_mesh(kMeshes + "cube6_1based").num_tets(), 6);
}

TEST_F(MeshIoTest, GeneratedBaseFilesLoad) {
  // Controls for the error tests below, which each change one line of these.
  tetgen(kNode, kEle);
  expect_unit_cube(load_tetgen(node_, ele_), 6);
  for (const std::string& text : {kGmsh22, kGmsh41}) {
    const TetMesh m = load_gmsh(write("good.msh", text));
    EXPECT_EQ(m.num_nodes(), 4);
    EXPECT_EQ(m.num_tets(), 1);
    EXPECT_NEAR(total_volume(m), 1.0 / 6, 1e-15);
    EXPECT_EQ(m.surface.size(), 4u);
  }
}

TEST_F(MeshIoTest, TetgenAcceptsCrlfTabsAndSignedNumbers) {
  std::string node = replace_line(kNode, 9, "7\t+1.0  1e0\t1.\t# corner");
  std::string crlf;
  for (char c : node) crlf += (c == '\n') ? std::string("\r\n") : std::string(1, c);
  tetgen(crlf, kEle);
  expect_unit_cube(load_tetgen(node_, ele_), 6);
}

// ---- TetGen errors ----

TEST_F(MeshIoTest, TetgenMissingFile) {
  const std::string node = (dir_ / "absent.node").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_tetgen(node, (dir_ / "absent.ele").string()); }, node, 0,
                                "cannot open file: No such file or directory"));
  const std::string ele = (dir_ / "absent.ele").string();
  const std::string good = write("good.node", kNode);
  EXPECT_TRUE(throws_mesh_error([&] { load_tetgen(good, ele); }, ele, 0, "cannot open file"));
}

TEST_F(MeshIoTest, TetgenEmptyFile) {
  EXPECT_TRUE(throws_mesh_error(tetgen("", kEle), node_, 0, "file is empty"));
  EXPECT_TRUE(throws_mesh_error(tetgen("# nothing\n\n   # still nothing\n", kEle), node_, 3, "file is empty"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, "\n"), ele_, 1, "file is empty"));
}

TEST_F(MeshIoTest, TetgenBadHeader) {
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "8 3 0"), kEle), node_, 1,
                                "expected header '<#points> 3 <#attributes> <0|1>' (4 integers), found 3"));
  EXPECT_TRUE(
      throws_mesh_error(tetgen(replace_line(kNode, 1, "8 2 0 0"), kEle), node_, 1, "expected dimension 3, found '2'"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "8 3 0 2"), kEle), node_, 1,
                                "boundary marker flag '2' is out of range [0, 1]"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "eight 3 0 0"), kEle), node_, 1,
                                "point count 'eight' is not an integer"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 1, "6 4")), ele_, 1,
                                "expected header '<#tets> 4 <#attributes>' (3 integers), found 2"));
}

TEST_F(MeshIoTest, TetgenTruncatedFiles) {
  EXPECT_TRUE(
      throws_mesh_error(tetgen(erase_line(kNode, 9), kEle), node_, 8, "expected point 8 of 8, found end of file"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, erase_line(kEle, 7)), ele_, 6, "expected tet 6 of 6, found end of file"));
}

TEST_F(MeshIoTest, TetgenMoreDataThanDeclared) {
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode + "8 2 2 2\n", kEle), node_, 10,
                                "expected end of file after 8 points, found '8 2 2 2'"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, kEle + "\n# comment\n6 0 1 2 4\n"), ele_, 10,
                                "expected end of file after 6 tets, found '6 0 1 2 4'"));
}

TEST_F(MeshIoTest, TetgenWrongFieldCount) {
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 4, "2 0 2")), ele_, 4,
                                "expected 5 integers (index and 4 node indices), found 3"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 3, "1 1 0"), kEle), node_, 3,
                                "expected 4 numbers (index and x y z), found 3"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "8 3 1 1"), kEle), node_, 2,
                                "expected 6 fields (index, x y z, 1 attribute and a boundary marker), found 4"));
}

TEST_F(MeshIoTest, TetgenNonFiniteCoordinate) {
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 5, "3 1 nan 0"), kEle), node_, 5,
                                "coordinate 'nan' is not a finite number"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 6, "4 0 0 -inf"), kEle), node_, 6,
                                "coordinate '-inf' is not a finite number"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 7, "5 1e999 0 1"), kEle), node_, 7,
                                "coordinate '1e999' is out of the range of a double"));
}

TEST_F(MeshIoTest, TetgenNonNumericToken) {
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 6, "4 0 0 1.0abc"), kEle), node_, 6,
                                "coordinate '1.0abc' is not a number"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 3, "1 0 1 x 7")), ele_, 3,
                                "node index 'x' is not an integer"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 3, "1 0 1 5.0 7")), ele_, 3,
                                "node index '5.0' is not an integer"));
}

TEST_F(MeshIoTest, TetgenDuplicateOrBadPointIndex) {
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 6, "3 0 0 1"), kEle), node_, 6,
                                "duplicate point index 3 (first on line 5)"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 2, "2 0 0 0"), kEle), node_, 2,
                                "first point index '2' is out of range [0, 1]"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 9, "8 1 1 1"), kEle), node_, 9,
                                "point index '8' is out of range [0, 7]"));
}

TEST_F(MeshIoTest, TetgenNodeIndexOutOfRange) {
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 4, "2 0 2 3 8")), ele_, 4,
                                "node index '8' is out of range [0, 7]"));
  // 1-based files: index 0 is out of range.
  const std::string node1 = kMeshes + "cube6_1based.node";
  const std::string ele1 = write("one.ele", "1 4 0\n1 8 1 3 0\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_tetgen(node1, ele1); }, ele1, 2, "node index '0' is out of range [1, 8]"));
}

TEST_F(MeshIoTest, TetgenRepeatedNodeInTet) {
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 4, "2 0 2 2 7")), ele_, 4, "tet repeats node '2'"));
}

TEST_F(MeshIoTest, TetgenRejectsQuadraticAndOtherNodesPerTet) {
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 1, "6 10 0")), ele_, 1,
                                "quadratic tets (10 nodes per tet) are not supported"));
  EXPECT_TRUE(
      throws_mesh_error(tetgen(kNode, replace_line(kEle, 1, "6 3 0")), ele_, 1, "expected 4 nodes per tet, found '3'"));
}

TEST_F(MeshIoTest, TetgenDegenerateTetNamesItsLine) {
  // Nodes 0 1 2 3 all lie on z = 0.
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 1, "7 4 0") + "6 0 1 2 3\n"), ele_, 8,
                                "tet 6 is degenerate: volume 0"));
}

TEST_F(MeshIoTest, TetgenHugeDeclaredCounts) {
  // Would need 48 GB if reserved up front; must fail cheaply as a truncation.
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "2000000000 3 0 0"), kEle), node_, 9,
                                "expected point 9 of 2000000000, found end of file"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "1000000000000 3 0 0"), kEle), node_, 1,
                                "point count '1000000000000' is out of range [1, 2147483647]"));
  EXPECT_TRUE(throws_mesh_error(tetgen(replace_line(kNode, 1, "1e12 3 0 0"), kEle), node_, 1,
                                "point count '1e12' is not an integer"));
  EXPECT_TRUE(throws_mesh_error(tetgen(kNode, replace_line(kEle, 1, "2000000000 4 2000000000")), ele_, 2,
                                "expected 2000000005 fields (index, 4 node indices, 2000000000 attributes), found 5"));
}

// ---- Gmsh errors ----

TEST_F(MeshIoTest, GmshRejectsBinary) {
  const std::string binary_int_one("\x01\x00\x00\x00", 4);
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 2, "2.2 1 8\n" + binary_int_one)), msh_, 2,
                                "binary MSH files are not supported"));
  EXPECT_TRUE(
      throws_mesh_error(gmsh(replace_line(kGmsh41, 2, "4.1 1 8")), msh_, 2, "binary MSH files are not supported"));
}

TEST_F(MeshIoTest, GmshRejectsQuadraticTets) {
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 14, "2 11 2 0 1 1 2 3 4 1 2 3 4 1 2")), msh_, 14,
                                "quadratic tets (element type 11, 10 nodes) are not supported"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh41, 18, "3 1 11 1")), msh_, 18,
                                "quadratic tets (element type 11, 10 nodes) are not supported"));
}

TEST_F(MeshIoTest, GmshUnsupportedVersionOrMissingHeader) {
  EXPECT_TRUE(
      throws_mesh_error(gmsh(replace_line(kGmsh22, 2, "4.0 0 8")), msh_, 2, "MSH version '4.0' is not supported"));
  EXPECT_TRUE(
      throws_mesh_error(gmsh("solid cube\n"), msh_, 1, "expected '$MeshFormat' on the first line, found 'solid cube'"));
  EXPECT_TRUE(throws_mesh_error(gmsh(""), msh_, 0, "file is empty"));
  EXPECT_TRUE(
      throws_mesh_error(gmsh("$MeshFormat\n" + std::string(100000, '\0')), msh_, 2, "more than 65536 characters"));
}

TEST_F(MeshIoTest, GmshTruncated) {
  EXPECT_TRUE(throws_mesh_error(gmsh(erase_line(kGmsh22, 9)), msh_, 9, "expected node 4 of 4, found '$EndNodes'"));
  EXPECT_TRUE(
      throws_mesh_error(gmsh(first_lines(kGmsh22, 13)), msh_, 13, "expected element 2 of 2, found end of file"));
  EXPECT_TRUE(throws_mesh_error(gmsh(first_lines(kGmsh41, 12)), msh_, 12,
                                "expected coordinates of node 3 of 4 in node block 1, found end of file"));
  EXPECT_TRUE(throws_mesh_error(gmsh(first_lines(kGmsh22, 14)), msh_, 14,
                                "expected '$EndElements' after 2 elements, found end of file"));
}

TEST_F(MeshIoTest, GmshWrongCounts) {
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 9, "4 0 0 1\n5 1 1 1")), msh_, 10,
                                "expected '$EndNodes' after 4 nodes, found '5 1 1 1'"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 12, "3")), msh_, 15,
                                "expected element 3 of 3, found '$EndElements'"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh41, 5, "1 5 1 5")), msh_, 5,
                                "$Nodes declares 5 nodes but its blocks hold 4"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh41, 6, "3 1 0 5")), msh_, 6,
                                "block node count '5' is out of range [0, 4]"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 5, "2000000000")), msh_, 10,
                                "expected node 5 of 2000000000, found '$EndNodes'"));
}

TEST_F(MeshIoTest, GmshBadNumbersAndTags) {
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 7, "2 1 nan 0")), msh_, 7,
                                "coordinate 'nan' is not a finite number"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh41, 13, "0 1 inf")), msh_, 13,
                                "coordinate 'inf' is not a finite number"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 14, "2 4 2 0 1 1 2 3 four")), msh_, 14,
                                "node tag 'four' is not an integer"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 14, "2 4 2 0 1 1 2 3 5")), msh_, 14,
                                "node tag '5' is not defined in $Nodes"));
  EXPECT_TRUE(
      throws_mesh_error(gmsh(replace_line(kGmsh22, 8, "2 0 1 0")), msh_, 8, "duplicate node tag 2 (first on line 7)"));
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 14, "2 4 2 0 1 1 2 3")), msh_, 14,
                                "expected 9 integers (tag, type, #tags, 2 tags and 4 node tags), found 8"));
}

TEST_F(MeshIoTest, GmshNoTetsOrUnclosedSection) {
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(erase_line(kGmsh22, 14), 12, "1")), msh_, 14,
                                "expected 4-node tetrahedra (element type 4) in $Elements, found none"));
  EXPECT_TRUE(throws_mesh_error(gmsh(first_lines(kGmsh22, 3) + "$Comments\nhello\n"), msh_, 5,
                                "expected '$EndComments' to close $Comments from line 4, found end of file"));
}

TEST_F(MeshIoTest, GmshDegenerateTetNamesItsLine) {
  EXPECT_TRUE(throws_mesh_error(gmsh(replace_line(kGmsh22, 9, "4 1 1 0")), msh_, 14, "tet 0 is degenerate"));
}

// ---- dispatch ----

TEST_F(MeshIoTest, LoadTetMeshRejectsUnknownExtensionAndMissingFiles) {
  const std::string obj = (dir_ / "cube.obj").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_tet_mesh(obj); }, obj, 0,
                                "unrecognised mesh file extension '.obj'; expected <name>.msh"));
  const std::string msh = (dir_ / "absent.msh").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_tet_mesh(msh); }, msh, 0, "cannot open file: No such file or directory"));
  const std::string base = (dir_ / "absent").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_tet_mesh(base); }, base + ".node", 0, "cannot open file"));
  EXPECT_TRUE(
      throws_mesh_error([&] { load_gmsh(dir_.string()); }, dir_.string(), 0, "cannot open file: it is a directory"));
}

}  // namespace
}  // namespace hapticd::hand
