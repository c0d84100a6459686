#include "hand_models/mesh_io.hpp"

#include <algorithm>
#include <charconv>
#include <climits>
#include <cmath>
#include <filesystem>
#include <string_view>
#include <system_error>
#include <unordered_map>
#include <utility>
#include <vector>

#include "hand_models/text_reader.hpp"

namespace hapticd::hand {
namespace {

// Declared counts are untrusted until their lines have actually been read.
constexpr long long kReserveCap = 1 << 16;

std::size_t capped(long long count) { return static_cast<std::size_t>(std::clamp(count, 0LL, kReserveCap)); }

std::string str(long long v) { return std::to_string(v); }

using detail::fail_at;
using detail::parse_int;
using detail::parse_real;
using detail::quote;
using detail::TextReader;

Eigen::Vector3d parse_point(const TextReader& r, std::size_t first) {
  return {parse_real(r, r[first], "coordinate", true), parse_real(r, r[first + 1], "coordinate", true),
          parse_real(r, r[first + 2], "coordinate", true)};
}

void check_no_repeat(const TextReader& r, const Tet& t, int k, std::string_view token) {
  for (int j = 0; j < k; ++j) {
    if (t[j] == t[k]) r.fail("tet repeats node " + quote(token));
  }
}

struct RawTets {
  std::vector<Tet> tets;
  std::vector<long long> lines;  // source line of each tet, for finalize_mesh errors
};

// Drops orphan nodes (keeping file order), then finalizes; finalize_mesh errors
// get the tet file's path and, when they name a tet, that tet's line.
TetMesh assemble(const std::vector<Eigen::Vector3d>& X, RawTets raw, const std::string& tet_path, long long end_line) {
  std::vector<int> remap(X.size(), -1);
  for (const Tet& t : raw.tets) {
    for (int v : t) remap[static_cast<std::size_t>(v)] = 0;
  }
  TetMesh mesh;
  for (std::size_t i = 0; i < X.size(); ++i) {
    if (remap[i] < 0) continue;
    remap[i] = mesh.num_nodes();
    mesh.X.push_back(X[i]);
  }
  for (Tet& t : raw.tets) {
    for (int& v : t) v = remap[static_cast<std::size_t>(v)];
  }
  mesh.tets = std::move(raw.tets);
  try {
    finalize_mesh(mesh);
  } catch (const MeshError& e) {
    const std::string_view msg = e.what();
    long long line = end_line;
    std::size_t tet = 0;
    if (msg.starts_with("tet ") && std::from_chars(msg.data() + 4, msg.data() + msg.size(), tet).ec == std::errc() &&
        tet < raw.lines.size()) {
      line = raw.lines[tet];
    }
    fail_at(tet_path, line, std::string(msg));
  }
  return mesh;
}

// Indices were range-checked while parsing, so only duplicates remain to catch.
void check_unique(const std::string& path, const std::vector<long long>& index, const std::vector<long long>& lines,
                  long long base, const std::string& what) {
  std::vector<long long> first_line(index.size(), 0);
  for (std::size_t i = 0; i < index.size(); ++i) {
    long long& first = first_line[static_cast<std::size_t>(index[i] - base)];
    if (first)
      fail_at(path, lines[i], "duplicate " + what + " index " + str(index[i]) + " (first on line " + str(first) + ")");
    first = lines[i];
  }
}

std::string attributes(long long n) { return str(n) + (n == 1 ? " attribute" : " attributes"); }

std::string fields_found(std::size_t n) { return ", found " + str(static_cast<long long>(n)); }

std::vector<Eigen::Vector3d> read_tetgen_nodes(const std::string& path, long long& base) {
  TextReader r(path, true);
  const std::string header = "header '<#points> 3 <#attributes> <0|1>'";
  if (!r.next()) r.fail("file is empty, expected " + header);
  if (r.size() != 4) r.fail("expected " + header + " (4 integers)" + fields_found(r.size()));
  const long long n = parse_int(r, r[0], "point count", 1, INT_MAX);
  if (parse_int(r, r[1], "dimension") != 3) r.fail("expected dimension 3, found " + quote(r[1]));
  const long long nattr = parse_int(r, r[2], "attribute count", 0, INT_MAX);
  const long long marker = parse_int(r, r[3], "boundary marker flag", 0, 1);
  const long long fields = 4 + nattr + marker;
  const std::string layout = (fields == 4) ? "4 numbers (index and x y z)"
                                           : str(fields) + " fields (index, x y z, " + attributes(nattr) +
                                                 (marker ? " and a boundary marker)" : ")");
  std::vector<Eigen::Vector3d> pts;
  std::vector<long long> index, lines;
  pts.reserve(capped(n));
  index.reserve(capped(n));
  lines.reserve(capped(n));
  for (long long i = 0; i < n; ++i) {
    r.expect_more("point " + str(i + 1) + " of " + str(n));
    if (static_cast<long long>(r.size()) != fields) r.fail("expected " + layout + fields_found(r.size()));
    if (i == 0) base = parse_int(r, r[0], "first point index", 0, 1);
    index.push_back(parse_int(r, r[0], "point index", base, base + n - 1));
    pts.push_back(parse_point(r, 1));
    for (long long k = 0; k < nattr; ++k) parse_real(r, r[static_cast<std::size_t>(4 + k)], "attribute", false);
    if (marker) parse_int(r, r[static_cast<std::size_t>(fields - 1)], "boundary marker");
    lines.push_back(r.line());
  }
  if (r.next()) r.fail("expected end of file after " + str(n) + " points, found " + r.found());
  check_unique(path, index, lines, base, "point");
  std::vector<Eigen::Vector3d> X(pts.size());
  for (std::size_t i = 0; i < pts.size(); ++i) X[static_cast<std::size_t>(index[i] - base)] = pts[i];
  return X;
}

RawTets read_tetgen_tets(const std::string& path, long long base, long long num_nodes, long long& end_line) {
  TextReader r(path, true);
  const std::string header = "header '<#tets> 4 <#attributes>'";
  if (!r.next()) r.fail("file is empty, expected " + header);
  if (r.size() != 3) r.fail("expected " + header + " (3 integers)" + fields_found(r.size()));
  const long long n = parse_int(r, r[0], "tet count", 1, INT_MAX);
  const long long per_tet = parse_int(r, r[1], "nodes per tet");
  if (per_tet == 10) r.fail("quadratic tets (10 nodes per tet) are not supported; expected 4 nodes per tet");
  if (per_tet != 4) r.fail("expected 4 nodes per tet, found " + quote(r[1]));
  const long long nattr = parse_int(r, r[2], "attribute count", 0, INT_MAX);
  const long long fields = 5 + nattr;
  const std::string layout = (nattr == 0) ? "5 integers (index and 4 node indices)"
                                          : str(fields) + " fields (index, 4 node indices, " + attributes(nattr) + ")";
  RawTets raw;
  std::vector<long long> index;
  raw.tets.reserve(capped(n));
  raw.lines.reserve(capped(n));
  index.reserve(capped(n));
  for (long long i = 0; i < n; ++i) {
    r.expect_more("tet " + str(i + 1) + " of " + str(n));
    if (static_cast<long long>(r.size()) != fields) r.fail("expected " + layout + fields_found(r.size()));
    index.push_back(parse_int(r, r[0], "tet index", base, base + n - 1));
    Tet t{};
    for (int k = 0; k < 4; ++k) {
      const std::string_view tok = r[static_cast<std::size_t>(1 + k)];
      t[k] = static_cast<int>(parse_int(r, tok, "node index", base, base + num_nodes - 1) - base);
      check_no_repeat(r, t, k, tok);
    }
    for (long long k = 0; k < nattr; ++k) parse_real(r, r[static_cast<std::size_t>(5 + k)], "attribute", false);
    raw.tets.push_back(t);
    raw.lines.push_back(r.line());
  }
  if (r.next()) r.fail("expected end of file after " + str(n) + " tets, found " + r.found());
  check_unique(path, index, raw.lines, base, "tet");
  end_line = r.line();
  return raw;
}

// Node count of Gmsh element types 1..19; other types are skipped unchecked.
constexpr int kGmshNodes[] = {0, 2, 3, 4, 4, 8, 6, 5, 3, 6, 9, 10, 27, 18, 14, 1, 8, 20, 15, 13};
constexpr long long kGmshTet4 = 4;
constexpr long long kGmshTet10 = 11;

class GmshReader {
 public:
  explicit GmshReader(const std::string& path) : r_(path, false) {}

  TetMesh load() {
    read_format();
    bool have_nodes = false, have_elements = false;
    while (r_.next()) {
      const std::string name(r_[0]);
      if (r_.size() != 1 || !name.starts_with('$') || name.starts_with("$End"))
        r_.fail("expected a section such as '$Nodes', found " + r_.found());
      if (name == "$Nodes") {
        if (have_nodes) r_.fail("second $Nodes section; expected one");
        have_nodes = true;
        v4_ ? read_nodes_41() : read_nodes_22();
      } else if (name == "$Elements") {
        if (!have_nodes) r_.fail("expected $Nodes before $Elements");
        if (have_elements) r_.fail("second $Elements section; expected one");
        have_elements = true;
        v4_ ? read_elements_41() : read_elements_22();
        if (tets_.tets.empty()) r_.fail("expected 4-node tetrahedra (element type 4) in $Elements, found none");
      } else {
        skip_section(name);
      }
    }
    if (!have_elements)
      r_.fail(std::string("expected ") + (have_nodes ? "an $Elements" : "a $Nodes") + " section, found end of file");
    return assemble(X_, std::move(tets_), r_.path(), r_.line());
  }

 private:
  void read_format() {
    if (!r_.next()) r_.fail("file is empty, expected '$MeshFormat'");
    if (r_.size() != 1 || r_[0] != "$MeshFormat")
      r_.fail("expected '$MeshFormat' on the first line, found " + r_.found());
    const std::string format = "format line '<version> <file-type> <data-size>'";
    r_.expect_more(format);
    if (r_.size() != 3) r_.fail("expected " + format + " (3 fields)" + fields_found(r_.size()));
    const double version = parse_real(r_, r_[0], "version", true);
    const long long file_type = parse_int(r_, r_[1], "file-type");
    parse_int(r_, r_[2], "data-size");
    if (file_type == 1) r_.fail("binary MSH files are not supported; expected file-type 0 (ASCII)");
    if (file_type != 0) r_.fail("expected file-type 0 (ASCII), found " + quote(r_[1]));
    v4_ = std::abs(version - 4.1) < 1e-9;
    if (!v4_ && !(version >= 2.0 && version < 3.0))
      r_.fail("MSH version " + quote(r_[0]) + " is not supported; expected 2.x or 4.1");
    expect_end("$EndMeshFormat", "after the format line");
  }

  void expect_end(const std::string& tag, const std::string& after) {
    r_.expect_more("'" + tag + "' " + after);
    if (r_.size() != 1 || r_[0] != tag) r_.fail("expected '" + tag + "' " + after + ", found " + r_.found());
  }

  // A '$' line inside a section's data means the section ended early.
  void data_line(const std::string& what) {
    r_.expect_more(what);
    if (r_[0].starts_with('$')) r_.fail("expected " + what + ", found " + r_.found());
  }

  void skip_section(const std::string& name) {
    const std::string end = "$End" + name.substr(1);
    const long long start = r_.line();
    while (r_.next()) {
      if (r_[0] == end) return;
    }
    r_.fail("expected '" + end + "' to close " + name + " from line " + str(start) + ", found end of file");
  }

  long long count_header(const std::string& what) {
    r_.expect_more(what + " count");
    if (r_.size() != 1) r_.fail("expected 1 integer (" + what + " count)" + fields_found(r_.size()));
    return parse_int(r_, r_[0], what + " count", 1, INT_MAX);
  }

  // Returns (#blocks, #items) from "<#blocks> <#items> <min tag> <max tag>".
  std::pair<long long, long long> block_header(const std::string& what) {
    const std::string header = "header '<#blocks> <#" + what + "s> <min tag> <max tag>'";
    r_.expect_more(header);
    if (r_.size() != 4) r_.fail("expected " + header + " (4 integers)" + fields_found(r_.size()));
    const long long blocks = parse_int(r_, r_[0], "block count", 0, INT_MAX);
    const long long n = parse_int(r_, r_[1], what + " count", 1, INT_MAX);
    parse_int(r_, r_[2], "min tag");
    parse_int(r_, r_[3], "max tag");
    return {blocks, n};
  }

  void claim_tag(long long tag, int index) {
    const auto [it, inserted] = tags_.try_emplace(tag, index, r_.line());
    if (!inserted) r_.fail("duplicate node tag " + str(tag) + " (first on line " + str(it->second.second) + ")");
  }

  void read_nodes_22() {
    const long long n = count_header("node");
    X_.reserve(capped(n));
    for (long long i = 0; i < n; ++i) {
      data_line("node " + str(i + 1) + " of " + str(n));
      if (r_.size() != 4) r_.fail("expected 4 numbers (tag x y z)" + fields_found(r_.size()));
      claim_tag(parse_int(r_, r_[0], "node tag", 1), static_cast<int>(X_.size()));
      X_.push_back(parse_point(r_, 1));
    }
    expect_end("$EndNodes", "after " + str(n) + " nodes");
  }

  void read_nodes_41() {
    const auto [blocks, n] = block_header("node");
    const long long header_line = r_.line();
    X_.reserve(capped(n));
    long long total = 0;
    for (long long b = 0; b < blocks; ++b) {
      const std::string in_block = " in node block " + str(b + 1);
      data_line("header of node block " + str(b + 1) + " of " + str(blocks));
      if (r_.size() != 4)
        r_.fail("expected 4 integers (entity-dim entity-tag parametric #nodes)" + fields_found(r_.size()));
      const long long dim = parse_int(r_, r_[0], "entity dimension", 0, 3);
      parse_int(r_, r_[1], "entity tag");
      const long long parametric = parse_int(r_, r_[2], "parametric flag", 0, 1);
      const long long m = parse_int(r_, r_[3], "block node count", 0, n - total);
      const std::size_t first = X_.size();
      for (long long j = 0; j < m; ++j) {
        data_line("node tag " + str(j + 1) + " of " + str(m) + in_block);
        if (r_.size() != 1) r_.fail("expected 1 integer (node tag)" + fields_found(r_.size()));
        claim_tag(parse_int(r_, r_[0], "node tag", 1), static_cast<int>(first + static_cast<std::size_t>(j)));
      }
      const std::size_t coords = 3 + static_cast<std::size_t>(parametric * dim);
      for (long long j = 0; j < m; ++j) {
        data_line("coordinates of node " + str(j + 1) + " of " + str(m) + in_block);
        if (r_.size() != coords)
          r_.fail("expected " + str(static_cast<long long>(coords)) + " numbers (x y z and parametric coordinates)" +
                  fields_found(r_.size()));
        X_.push_back(parse_point(r_, 0));
        for (std::size_t k = 3; k < coords; ++k) parse_real(r_, r_[k], "parametric coordinate", true);
      }
      total += m;
    }
    if (total != n)
      fail_at(r_.path(), header_line, "$Nodes declares " + str(n) + " nodes but its blocks hold " + str(total));
    expect_end("$EndNodes", "after " + str(blocks) + " node blocks");
  }

  void reject_unsupported(long long type) const {
    if (type == kGmshTet10)
      r_.fail("quadratic tets (element type 11, 10 nodes) are not supported; expected 4-node tets (type 4)");
  }

  // Node tags start at token `first`; `head` names the tokens before them.
  void element(long long type, std::size_t first, const std::string& head) {
    reject_unsupported(type);
    const long long want = (type < std::ssize(kGmshNodes)) ? kGmshNodes[type] : 0;
    const long long have = static_cast<long long>(r_.size()) - static_cast<long long>(first);
    if (want > 0 && have != want)
      r_.fail("expected " + str(static_cast<long long>(first) + want) + " integers (" + head + " and " + str(want) +
              " node tags)" + fields_found(r_.size()));
    if (have < 1)
      r_.fail("expected at least " + str(static_cast<long long>(first) + 1) + " integers (" + head + " and node tags)" +
              fields_found(r_.size()));
    for (std::size_t k = first; k < r_.size(); ++k) parse_int(r_, r_[k], "node tag");
    if (type != kGmshTet4) return;
    Tet t{};
    for (int k = 0; k < 4; ++k) {
      const std::string_view tok = r_[first + static_cast<std::size_t>(k)];
      const auto it = tags_.find(parse_int(r_, tok, "node tag"));
      if (it == tags_.end()) r_.fail("node tag " + quote(tok) + " is not defined in $Nodes");
      t[k] = it->second.first;
      check_no_repeat(r_, t, k, tok);
    }
    tets_.tets.push_back(t);
    tets_.lines.push_back(r_.line());
  }

  void read_elements_22() {
    const long long n = count_header("element");
    for (long long i = 0; i < n; ++i) {
      data_line("element " + str(i + 1) + " of " + str(n));
      if (r_.size() < 3) r_.fail("expected at least 3 integers (tag type #tags)" + fields_found(r_.size()));
      parse_int(r_, r_[0], "element tag");
      const long long type = parse_int(r_, r_[1], "element type", 1);
      const long long ntags = parse_int(r_, r_[2], "tag count", 0, INT_MAX);
      const std::size_t first = 3 + static_cast<std::size_t>(ntags);
      for (std::size_t k = 3; k < std::min(first, r_.size()); ++k) parse_int(r_, r_[k], "element tag value");
      element(type, first, "tag, type, #tags, " + str(ntags) + " tags");
    }
    expect_end("$EndElements", "after " + str(n) + " elements");
  }

  void read_elements_41() {
    const auto [blocks, n] = block_header("element");
    const long long header_line = r_.line();
    long long total = 0;
    for (long long b = 0; b < blocks; ++b) {
      data_line("header of element block " + str(b + 1) + " of " + str(blocks));
      if (r_.size() != 4)
        r_.fail("expected 4 integers (entity-dim entity-tag type #elements)" + fields_found(r_.size()));
      parse_int(r_, r_[0], "entity dimension", 0, 3);
      parse_int(r_, r_[1], "entity tag");
      const long long type = parse_int(r_, r_[2], "element type", 1);
      reject_unsupported(type);
      const long long m = parse_int(r_, r_[3], "block element count", 0, n - total);
      for (long long j = 0; j < m; ++j) {
        data_line("element " + str(j + 1) + " of " + str(m) + " in element block " + str(b + 1));
        parse_int(r_, r_[0], "element tag");
        element(type, 1, "element tag");
      }
      total += m;
    }
    if (total != n)
      fail_at(r_.path(), header_line, "$Elements declares " + str(n) + " elements but its blocks hold " + str(total));
    expect_end("$EndElements", "after " + str(blocks) + " element blocks");
  }

  TextReader r_;
  bool v4_ = false;
  std::vector<Eigen::Vector3d> X_;
  std::unordered_map<long long, std::pair<int, long long>> tags_;  // tag -> (index, line)
  RawTets tets_;
};

}  // namespace

TetMesh load_tetgen(const std::string& node_path, const std::string& ele_path) {
  long long base = 0;
  const std::vector<Eigen::Vector3d> X = read_tetgen_nodes(node_path, base);
  long long end_line = 0;
  RawTets raw = read_tetgen_tets(ele_path, base, static_cast<long long>(X.size()), end_line);
  return assemble(X, std::move(raw), ele_path, end_line);
}

TetMesh load_gmsh(const std::string& path) { return GmshReader(path).load(); }

TetMesh load_tet_mesh(const std::string& path) {
  const std::string ext = std::filesystem::path(path).extension().string();
  if (ext == ".msh") return load_gmsh(path);
  if (ext.empty() || ext == ".node" || ext == ".ele") {
    const std::string base = path.substr(0, path.size() - ext.size());
    return load_tetgen(base + ".node", base + ".ele");
  }
  fail_at(path, 0,
          "unrecognised mesh file extension " + quote(ext) +
              "; expected <name>.msh (Gmsh ASCII), <name>.node or <name>.ele (TetGen pair), or <name> without "
              "extension (TetGen <name>.node + <name>.ele)");
}

}  // namespace hapticd::hand
