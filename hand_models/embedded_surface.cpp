#include "hand_models/embedded_surface.hpp"

#include <Eigen/Geometry>
#include <Eigen/LU>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <climits>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string_view>
#include <system_error>
#include <utility>

#include "hand_models/box_mesh.hpp"
#include "hand_models/mesh_io.hpp"

namespace hapticd {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3i;

constexpr double kPi = 3.14159265358979323846;
// Cells are tested slightly enlarged so a surface lying on a grid plane touches the cells on both sides.
constexpr double kCellSlack = 1e-9;
constexpr long long kMaxCells = 1LL << 21;  // grid cells (kept or not): up to 12M tets, several GB to finalize
constexpr double kWeightTolerance = 1e-9;

std::string str(long long v) { return std::to_string(v); }
std::string str(int v) { return std::to_string(v); }
std::string str(std::size_t v) { return std::to_string(v); }

std::string str(double v) {
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

std::string str(const Vector3d& p) { return "(" + str(p.x()) + ", " + str(p.y()) + ", " + str(p.z()) + ")"; }

[[noreturn]] void fail_at(const std::string& path, long long line, const std::string& msg) {
  throw MeshError(path + ":" + str(line) + ": " + msg);
}

// Keeps messages short and printable when the offending text is long or binary.
std::string quote(std::string_view s) {
  constexpr std::size_t kMax = 40;
  std::string out = "'";
  for (std::size_t i = 0; i < s.size() && i < kMax; ++i) {
    const auto c = static_cast<unsigned char>(s[i]);
    out += (c >= 0x20 && c < 0x7f) ? static_cast<char>(c) : '?';
  }
  if (s.size() > kMax) out += "...";
  return out + "'";
}

// Token lines of a text file with '#' comments; line() stays at the last line at end of file.
class LineReader {
 public:
  explicit LineReader(std::string path) : path_(std::move(path)) {
    std::error_code ec;
    if (std::filesystem::is_directory(path_, ec)) fail_at(path_, 0, "cannot open file: it is a directory");
    errno = 0;
    in_.open(path_, std::ios::binary);
    if (!in_) {
      const std::string why = errno ? std::error_code(errno, std::generic_category()).message() : "unknown error";
      fail_at(path_, 0, "cannot open file: " + why);
    }
  }

  bool next() {
    static constexpr const char* kSpace = " \t\r\v\f";
    while (read_line()) {
      ++line_;
      text_.erase(std::min(text_.find('#'), text_.size()));
      tokens_.clear();
      for (std::size_t i = text_.find_first_not_of(kSpace); i != std::string::npos;
           i = text_.find_first_not_of(kSpace, i)) {
        const std::size_t j = std::min(text_.find_first_of(kSpace, i), text_.size());
        tokens_.emplace_back(text_.data() + i, j - i);
        i = j;
      }
      if (!tokens_.empty()) return true;
    }
    tokens_.clear();
    return false;
  }

  const std::string& path() const { return path_; }
  long long line() const { return line_; }
  std::size_t size() const { return tokens_.size(); }
  std::string_view operator[](std::size_t i) const { return tokens_[i]; }
  std::string found() const {
    if (tokens_.empty()) return "end of file";
    const char* b = tokens_.front().data();
    return quote(std::string_view(b, static_cast<std::size_t>(tokens_.back().data() + tokens_.back().size() - b)));
  }
  [[noreturn]] void fail(const std::string& msg) const { fail_at(path_, line_, msg); }

 private:
  // Like std::getline, but a file without newlines (binary data, /dev/zero) cannot exhaust memory.
  bool read_line() {
    constexpr std::size_t kMaxLine = 1 << 16;
    using Traits = std::ifstream::traits_type;
    text_.clear();
    std::streambuf* buf = in_.rdbuf();
    for (auto c = buf->sbumpc(); !Traits::eq_int_type(c, Traits::eof()); c = buf->sbumpc()) {
      if (Traits::to_char_type(c) == '\n') return true;
      if (text_.size() == kMaxLine) fail_at(path_, line_ + 1, "expected a line, found more than 65536 characters");
      text_.push_back(Traits::to_char_type(c));
    }
    return !text_.empty();
  }

  std::string path_;
  std::ifstream in_;
  std::string text_;
  std::vector<std::string_view> tokens_;
  long long line_ = 0;
};

long long parse_int(const LineReader& r, std::string_view s, const std::string& what, long long lo, long long hi) {
  long long v = 0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (ec == std::errc::invalid_argument || end != s.data() + s.size())
    r.fail(what + " " + quote(s) + " is not an integer");
  if (ec == std::errc::result_out_of_range || v < lo || v > hi)
    r.fail(what + " " + quote(s) + " is out of range [" + str(lo) + ", " + str(hi) + "]");
  return v;
}

double parse_real(const LineReader& r, std::string_view s, const std::string& what) {
  std::string_view t = s;
  // from_chars rejects the leading '+' that printf-style writers may emit.
  if (t.size() > 1 && t[0] == '+' && t[1] != '+' && t[1] != '-') t.remove_prefix(1);
  double v = 0;
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  if (ec == std::errc::invalid_argument || end != t.data() + t.size())
    r.fail(what + " " + quote(s) + " is not a number");
  if (ec == std::errc::result_out_of_range) r.fail(what + " " + quote(s) + " is out of the range of a double");
  if (!std::isfinite(v)) r.fail(what + " " + quote(s) + " is not a finite number");
  return v;
}

std::ofstream open_for_writing(const std::string& path) {
  errno = 0;
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) {
    const std::string why = errno ? std::error_code(errno, std::generic_category()).message() : "unknown error";
    fail_at(path, 0, "cannot write file: " + why);
  }
  return out;
}

void finish_writing(std::ofstream& out, const std::string& path) {
  out.flush();
  if (!out) fail_at(path, 0, "cannot write file: output error");
}

void check_surface(const SurfaceMesh& s) {
  if (s.triangles.empty()) throw MeshError("surface has no triangles");
  const int n = static_cast<int>(s.vertices.size());
  for (int i = 0; i < n; ++i) {
    if (!s.vertices[i].allFinite()) throw MeshError("surface vertex " + str(i) + " has a non-finite coordinate");
  }
  for (std::size_t t = 0; t < s.triangles.size(); ++t) {
    const Triangle& tri = s.triangles[t];
    for (int k = 0; k < 3; ++k) {
      if (tri[k] < 0 || tri[k] >= n) {
        throw MeshError("surface triangle " + str(t) + " references vertex " + str(tri[k]) +
                        ", outside [0, " + str(n - 1) + "]");
      }
    }
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2])
      throw MeshError("surface triangle " + str(t) + " repeats a vertex");
  }
}

// Cell (i, j, k) spans origin + h * [i, i+1] x [j, j+1] x [k, k+1].
struct Grid {
  double h = 0.0;
  Vector3d origin;
  Vector3i n;  // cells per axis

  int num_cells() const { return n.x() * n.y() * n.z(); }
  int cell_id(const Vector3i& c) const { return (c.z() * n.y() + c.y()) * n.x() + c.x(); }
  Vector3i cell_coords(int id) const { return Vector3i(id % n.x(), (id / n.x()) % n.y(), id / (n.x() * n.y())); }
  Vector3d corner(const Vector3i& c) const { return origin + h * c.cast<double>(); }
  Vector3d centre(const Vector3i& c) const { return corner(c) + Vector3d::Constant(0.5 * h); }
  // Cells whose slightly enlarged closed box may contain p, per axis [first, last].
  std::pair<Vector3i, Vector3i> cell_range(const Vector3d& lo, const Vector3d& hi) const {
    Vector3i first, last;
    for (int a = 0; a < 3; ++a) {
      first[a] = std::clamp(static_cast<int>(std::floor((lo[a] - origin[a]) / h - kCellSlack)), 0, n[a] - 1);
      last[a] = std::clamp(static_cast<int>(std::floor((hi[a] - origin[a]) / h + kCellSlack)), 0, n[a] - 1);
    }
    return {first, last};
  }
};

std::pair<Vector3d, Vector3d> bounding_box(const SurfaceMesh& s) {
  Vector3d lo = Vector3d::Constant(std::numeric_limits<double>::infinity());
  Vector3d hi = -lo;
  for (const Triangle& t : s.triangles) {
    for (int v : t) {
      lo = lo.cwiseMin(s.vertices[v]);
      hi = hi.cwiseMax(s.vertices[v]);
    }
  }
  return {lo, hi};
}

// The box's low corner sits a fixed, uneven fraction of a cell inside the grid: a symmetric
// placement would add cells in symmetric groups, so the tet count would jump in large steps.
Grid make_grid(const std::pair<Vector3d, Vector3d>& box, double h) {
  const Vector3d offset = h * Vector3d(0.37, 0.21, 0.43);
  const Vector3d extent = box.second - box.first + offset;
  Grid g;
  g.h = h;
  long long cells = 1;
  for (int a = 0; a < 3; ++a) {
    const double n = std::floor(extent[a] / h) + 1.0;
    if (!(n <= static_cast<double>(kMaxCells))) cells = kMaxCells + 1;
    else cells *= static_cast<long long>(n);
    if (cells > kMaxCells) {
      throw std::invalid_argument("embedded surface: spacing " + str(h) + " m needs more than " + str(kMaxCells) +
                                  " grid cells");
    }
    g.n[a] = static_cast<int>(n);
  }
  g.origin = box.first - offset;
  return g;
}

// Separating-axis test of a triangle (vertices relative to the box centre) against the closed cube [-r, r]^3.
bool triangle_touches_cube(const Vector3d& v0, const Vector3d& v1, const Vector3d& v2, double r) {
  auto separated = [&](const Vector3d& axis) {
    const double p0 = axis.dot(v0), p1 = axis.dot(v1), p2 = axis.dot(v2);
    const double reach = r * axis.cwiseAbs().sum();
    return std::min({p0, p1, p2}) > reach || std::max({p0, p1, p2}) < -reach;
  };
  for (int a = 0; a < 3; ++a) {
    if (std::min({v0[a], v1[a], v2[a]}) > r || std::max({v0[a], v1[a], v2[a]}) < -r) return false;
  }
  const std::array<Vector3d, 3> edges = {v1 - v0, v2 - v1, v0 - v2};
  if (separated(edges[0].cross(edges[1]))) return false;
  for (const Vector3d& e : edges) {
    for (int a = 0; a < 3; ++a) {
      if (separated(e.cross(Vector3d::Unit(a)))) return false;
    }
  }
  return true;
}

// Generalized winding number (sum of signed solid angles / 4 pi): +-1 inside a closed surface, 0 outside.
double winding_number(const SurfaceMesh& s, const Vector3d& p) {
  double sum = 0.0;
  for (const Triangle& t : s.triangles) {
    const Vector3d a = s.vertices[t[0]] - p, b = s.vertices[t[1]] - p, c = s.vertices[t[2]] - p;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    const double num = a.dot(b.cross(c));
    const double den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    sum += 2.0 * std::atan2(num, den);
  }
  return sum / (4.0 * kPi);
}

// Face-connected components of the cells where mask is set; label -1 elsewhere. Returns the
// component count; sizes[l] is the number of cells of component l.
int label_components(const Grid& g, const std::vector<char>& mask, std::vector<int>& label, std::vector<int>& sizes) {
  label.assign(mask.size(), -1);
  sizes.clear();
  std::vector<int> queue;
  for (int start = 0; start < g.num_cells(); ++start) {
    if (!mask[start] || label[start] >= 0) continue;
    const int l = static_cast<int>(sizes.size());
    queue.assign(1, start);
    label[start] = l;
    for (std::size_t q = 0; q < queue.size(); ++q) {
      const Vector3i c = g.cell_coords(queue[q]);
      for (int a = 0; a < 3; ++a) {
        for (int dir = -1; dir <= 1; dir += 2) {
          Vector3i nb = c;
          nb[a] += dir;
          if (nb[a] < 0 || nb[a] >= g.n[a]) continue;
          const int id = g.cell_id(nb);
          if (mask[id] && label[id] < 0) {
            label[id] = l;
            queue.push_back(id);
          }
        }
      }
    }
    sizes.push_back(static_cast<int>(queue.size()));
  }
  return static_cast<int>(sizes.size());
}

// Kept cells: those a triangle touches plus untouched regions inside the solid, reduced to the
// largest face-connected component.
std::vector<char> cover_cells(const SurfaceMesh& s, const Grid& g) {
  std::vector<char> keep(g.num_cells(), 0);
  const double r = 0.5 * g.h * (1.0 + 2.0 * kCellSlack);
  for (const Triangle& t : s.triangles) {
    const Vector3d& a = s.vertices[t[0]];
    const Vector3d& b = s.vertices[t[1]];
    const Vector3d& c = s.vertices[t[2]];
    const auto [first, last] = g.cell_range(a.cwiseMin(b).cwiseMin(c), a.cwiseMax(b).cwiseMax(c));
    for (int k = first.z(); k <= last.z(); ++k) {
      for (int j = first.y(); j <= last.y(); ++j) {
        for (int i = first.x(); i <= last.x(); ++i) {
          const Vector3i cell(i, j, k);
          const int id = g.cell_id(cell);
          if (keep[id]) continue;
          const Vector3d m = g.centre(cell);
          if (triangle_touches_cube(a - m, b - m, c - m, r)) keep[id] = 1;
        }
      }
    }
  }
  // An untouched region lies wholly inside or wholly outside, so one sample decides it; its cells'
  // centres are at least h/2 from the surface, where the winding number is well conditioned.
  std::vector<char> untouched(keep.size());
  for (std::size_t i = 0; i < keep.size(); ++i) untouched[i] = !keep[i];
  std::vector<int> label, sizes;
  const int regions = label_components(g, untouched, label, sizes);
  std::vector<char> inside(regions, 0);
  std::vector<char> decided(regions, 0);
  for (int id = 0; id < g.num_cells(); ++id) {
    const int l = label[id];
    if (l < 0) continue;
    if (!decided[l]) {
      decided[l] = 1;
      inside[l] = std::abs(winding_number(s, g.centre(g.cell_coords(id)))) > 0.5 ? 1 : 0;
    }
    if (inside[l]) keep[id] = 1;
  }
  label_components(g, keep, label, sizes);
  const int best = static_cast<int>(std::max_element(sizes.begin(), sizes.end()) - sizes.begin());
  for (int id = 0; id < g.num_cells(); ++id) keep[id] = label[id] == best ? 1 : 0;
  return keep;
}

Eigen::Vector4d barycentric(const TetMesh& mesh, const Tet& t, const Vector3d& p) {
  const Vector3d& x0 = mesh.X[t[0]];
  Eigen::Matrix3d A;
  A << mesh.X[t[1]] - x0, mesh.X[t[2]] - x0, mesh.X[t[3]] - x0;
  const Vector3d l = A.partialPivLu().solve(p - x0);
  return {1.0 - l.sum(), l[0], l[1], l[2]};
}

EmbeddedBody build_body(const SurfaceMesh& surface, const std::pair<Vector3d, Vector3d>& box, double h) {
  const Grid g = make_grid(box, h);
  const std::vector<char> keep = cover_cells(surface, g);

  EmbeddedBody body;
  body.surface = surface;
  body.spacing = h;
  std::vector<int> kept_index(keep.size(), -1);
  const Vector3i nn = g.n + Vector3i::Ones();
  std::vector<int> node_of(static_cast<std::size_t>(nn.x()) * nn.y() * nn.z(), -1);
  for (int id = 0; id < g.num_cells(); ++id) {
    if (!keep[id]) continue;
    kept_index[id] = body.mesh.num_tets() / 6;
    const Vector3i cell = g.cell_coords(id);
    std::array<int, 8> corner_node;
    for (int c = 0; c < 8; ++c) {
      const Vector3i v = cell + Vector3i(c & 1, (c >> 1) & 1, (c >> 2) & 1);
      int& node = node_of[(static_cast<std::size_t>(v.z()) * nn.y() + v.y()) * nn.x() + v.x()];
      if (node < 0) {
        node = body.mesh.num_nodes();
        body.mesh.X.push_back(g.corner(v));
      }
      corner_node[c] = node;
    }
    for (const Tet& t : kuhn_cube_tets()) {
      body.mesh.tets.push_back({corner_node[t[0]], corner_node[t[1]], corner_node[t[2]], corner_node[t[3]]});
    }
  }
  finalize_mesh(body.mesh);

  // A vertex on a cell face may sit in either neighbour: take the tet that contains it most deeply.
  const int nv = static_cast<int>(surface.vertices.size());
  body.surface_tet.resize(nv);
  body.surface_bary.resize(nv);
  for (int v = 0; v < nv; ++v) {
    const Vector3d& p = surface.vertices[v];
    const auto [first, last] = g.cell_range(p, p);
    double best_min = -std::numeric_limits<double>::infinity();
    for (int k = first.z(); k <= last.z(); ++k) {
      for (int j = first.y(); j <= last.y(); ++j) {
        for (int i = first.x(); i <= last.x(); ++i) {
          const int kc = kept_index[g.cell_id(Vector3i(i, j, k))];
          if (kc < 0) continue;
          for (int e = 6 * kc; e < 6 * kc + 6; ++e) {
            const Eigen::Vector4d w = barycentric(body.mesh, body.mesh.tets[e], p);
            if (w.minCoeff() > best_min) {
              best_min = w.minCoeff();
              body.surface_tet[v] = e;
              body.surface_bary[v] = w;
            }
          }
        }
      }
    }
    if (!(best_min >= -kWeightTolerance)) {
      throw MeshError("surface vertex " + str(v) + " at " + str(p) +
                      " m lies outside the kept cells (surface parts more than a cell apart, or an unused vertex?)");
    }
  }
  return body;
}

int count_tets(const SurfaceMesh& surface, const std::pair<Vector3d, Vector3d>& box, double h) {
  const std::vector<char> keep = cover_cells(surface, make_grid(box, h));
  return 6 * static_cast<int>(std::count(keep.begin(), keep.end(), 1));
}

void check_spacing(double spacing) {
  if (!std::isfinite(spacing) || spacing <= 0.0)
    throw std::invalid_argument("embedded surface: spacing must be finite and positive, got " + str(spacing));
}

}  // namespace

EmbeddedBody embed_surface_with_spacing(const SurfaceMesh& surface, double spacing) {
  check_spacing(spacing);
  check_surface(surface);
  return build_body(surface, bounding_box(surface), spacing);
}

EmbeddedBody embed_surface(const SurfaceMesh& surface, int target_tets) {
  if (target_tets <= 0)
    throw std::invalid_argument("embedded surface: target_tets must be positive, got " + str(target_tets));
  check_surface(surface);
  const auto box = bounding_box(surface);
  const Vector3d extent = box.second - box.first;
  const double size = extent.maxCoeff();
  if (!(size > 0.0)) throw MeshError("surface has zero extent");
  // Finest: 120 cells along the longest axis stays under kMaxCells; coarsest: one cell holds everything.
  const double h_min = size / 120.0;
  const double h_max = size * 2.0;
  const double target = target_tets;
  double best_h = h_max;
  double best_err = std::numeric_limits<double>::infinity();
  auto count = [&](double h) {
    const int c = count_tets(surface, box, h);
    const double err = std::abs(c - target);
    if (err < best_err || (err == best_err && h > best_h)) {
      best_err = err;
      best_h = h;
    }
    return c;
  };
  // Volume guess for the first spacing (the cover's overhang makes it low); the count falls with h.
  const double volume = std::max(std::abs(enclosed_volume(surface)), 1e-3 * extent.prod());
  double lo = std::clamp(std::cbrt(6.0 * volume / target), h_min, h_max);
  double hi = lo;
  if (count(lo) >= target) {
    while (hi < h_max) {
      hi = std::min(hi * 1.3, h_max);
      if (count(hi) < target) break;
      lo = hi;
    }
  } else {
    while (lo > h_min) {
      lo = std::max(lo / 1.3, h_min);
      if (count(lo) >= target) break;
      hi = lo;
    }
  }
  for (int it = 0; it < 40 && best_err > 0.01 * target && hi / lo > 1.0 + 1e-6; ++it) {
    const double mid = std::sqrt(lo * hi);
    if (count(mid) >= target) lo = mid; else hi = mid;
  }
  // The centred grid shifts with h, so the count is not monotone: scan around the best when bisection
  // stalled on a large step.
  if (best_err > 0.01 * target) {
    const double centre = best_h;
    for (int i = -24; i <= 24 && best_err > 0.01 * target; ++i) {
      const double h = centre * std::pow(1.15, i / 24.0);
      if (h >= h_min && h <= h_max) count(h);
    }
  }
  return build_body(surface, box, best_h);
}

double enclosed_volume(const SurfaceMesh& surface) {
  if (surface.vertices.empty()) return 0.0;
  // Tets against a vertex of the surface instead of the origin: no cancellation far from the origin.
  const Vector3d& o = surface.vertices.front();
  double v = 0.0;
  for (const Triangle& t : surface.triangles) {
    v += signed_volume(o, surface.vertices[t[0]], surface.vertices[t[1]], surface.vertices[t[2]]);
  }
  return v;
}

SurfaceMesh load_obj(const std::string& path) {
  LineReader r(path);
  SurfaceMesh s;
  std::vector<long long> triangle_line;
  std::vector<int> polygon;
  while (r.next()) {
    const std::string_view key = r[0];
    if (key == "v") {
      if (r.size() < 4) r.fail("vertex needs 3 coordinates, found " + str(r.size() - 1));
      Vector3d p;
      for (int a = 0; a < 3; ++a) p[a] = parse_real(r, r[1 + a], "coordinate");
      for (std::size_t i = 4; i < r.size(); ++i) parse_real(r, r[i], "vertex value");
      if (s.vertices.size() >= static_cast<std::size_t>(INT_MAX)) r.fail("too many vertices");
      s.vertices.push_back(p);
    } else if (key == "f") {
      if (r.size() < 4) {
        r.fail("face needs at least 3 vertices, found " + str(r.size() - 1));
      }
      polygon.clear();
      const long long defined = static_cast<long long>(s.vertices.size());
      for (std::size_t i = 1; i < r.size(); ++i) {
        const std::string_view token = r[i].substr(0, r[i].find('/'));
        const long long index = parse_int(r, token, "vertex index", -defined, INT_MAX);
        // Positive indices may point forward; they are range-checked once every vertex is known.
        if (index == 0) r.fail("vertex index '0' is out of range (OBJ indices start at 1)");
        polygon.push_back(static_cast<int>(index > 0 ? index - 1 : defined + index));
      }
      for (std::size_t i = 1; i + 1 < polygon.size(); ++i) {
        s.triangles.push_back({polygon[0], polygon[i], polygon[i + 1]});
        triangle_line.push_back(r.line());
      }
    }
  }
  if (s.triangles.empty()) r.fail("expected faces ('f' lines), found no faces");
  const int n = static_cast<int>(s.vertices.size());
  for (std::size_t t = 0; t < s.triangles.size(); ++t) {
    const Triangle& tri = s.triangles[t];
    for (int v : tri) {
      if (v >= n) {
        fail_at(path, triangle_line[t],
                "vertex index " + str(v + 1) + " is out of range: the file has " + str(n) + " vertices");
      }
    }
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2])
      fail_at(path, triangle_line[t], "face repeats a vertex (degenerate triangle)");
  }
  return s;
}

void save_obj(const std::string& path, const SurfaceMesh& surface) {
  std::ofstream out = open_for_writing(path);
  out << "# " << surface.vertices.size() << " vertices, " << surface.triangles.size() << " triangles\n";
  for (const Vector3d& p : surface.vertices) {
    out << "v " << str(p.x()) << ' ' << str(p.y()) << ' ' << str(p.z()) << '\n';
  }
  for (const Triangle& t : surface.triangles) out << "f " << t[0] + 1 << ' ' << t[1] + 1 << ' ' << t[2] + 1 << '\n';
  finish_writing(out, path);
}

void save_embedding(const std::string& path, const EmbeddedBody& body) {
  const std::size_t nv = body.surface.vertices.size();
  if (body.surface_tet.size() != nv || body.surface_bary.size() != nv)
    throw MeshError(path + ":0: embedding has " + str(body.surface_tet.size()) +
                    " tets and " + str(body.surface_bary.size()) + " weight sets for " +
                    str(nv) + " surface vertices");
  std::ofstream out = open_for_writing(path);
  out << "hapticd-embedding 1\n# surface_vertices tets spacing_m\n"
      << nv << ' ' << body.mesh.num_tets() << ' ' << str(body.spacing) << "\n# tet w0 w1 w2 w3\n";
  for (std::size_t v = 0; v < nv; ++v) {
    const Eigen::Vector4d& w = body.surface_bary[v];
    out << body.surface_tet[v] << ' ' << str(w[0]) << ' ' << str(w[1]) << ' ' << str(w[2]) << ' ' << str(w[3])
        << '\n';
  }
  finish_writing(out, path);
}

EmbeddedBody load_embedding(const std::string& path, TetMesh mesh, SurfaceMesh surface) {
  LineReader r(path);
  if (!r.next() || r.size() != 2 || r[0] != "hapticd-embedding" || r[1] != "1")
    r.fail("expected header 'hapticd-embedding 1', found " + r.found());
  if (!r.next()) r.fail("expected '<surface vertices> <tets> <spacing>', found end of file");
  if (r.size() != 3) r.fail("expected '<surface vertices> <tets> <spacing>', found " + r.found());
  const long long nv = parse_int(r, r[0], "surface vertex count", 0, INT_MAX);
  const long long nt = parse_int(r, r[1], "tet count", 1, INT_MAX);
  const double spacing = parse_real(r, r[2], "spacing");
  if (!(spacing > 0.0)) r.fail("spacing " + quote(r[2]) + " is not positive");
  if (nv != static_cast<long long>(surface.vertices.size()))
    r.fail("file is for " + str(nv) + " surface vertices, the surface has " +
           str(surface.vertices.size()));
  if (nt != mesh.num_tets()) r.fail("file is for " + str(nt) + " tets, the mesh has " + str(mesh.num_tets()));

  Vector3d lo = Vector3d::Constant(std::numeric_limits<double>::infinity());
  Vector3d hi = -lo;
  for (const Vector3d& x : mesh.X) {
    lo = lo.cwiseMin(x);
    hi = hi.cwiseMax(x);
  }
  const double tolerance = 1e-6 * (hi - lo).norm();

  EmbeddedBody body;
  body.spacing = spacing;
  body.surface_tet.resize(nv);
  body.surface_bary.resize(nv);
  for (long long v = 0; v < nv; ++v) {
    const std::string expected = "expected '<tet> <w0> <w1> <w2> <w3>' for surface vertex " + str(v) + ", found ";
    if (!r.next()) r.fail(expected + "end of file");
    if (r.size() != 5) r.fail(expected + r.found());
    const int tet = static_cast<int>(parse_int(r, r[0], "tet", 0, nt - 1));
    Eigen::Vector4d w;
    for (int k = 0; k < 4; ++k) {
      w[k] = parse_real(r, r[1 + k], "weight");
      if (w[k] < -kWeightTolerance) r.fail("weight " + quote(r[1 + k]) + " is negative: the vertex is outside its tet");
    }
    if (std::abs(w.sum() - 1.0) > kWeightTolerance) r.fail("weights sum to " + str(w.sum()) + ", not 1");
    Vector3d x = Vector3d::Zero();
    for (int k = 0; k < 4; ++k) x += w[k] * mesh.X[mesh.tets[tet][k]];
    const Vector3d& p = surface.vertices[v];
    if ((x - p).norm() > tolerance) {
      r.fail("weights place surface vertex " + str(v) + " at " + str(x) + ", " + str((x - p).norm()) +
             " m from its position " + str(p) + " (file made for another mesh or surface?)");
    }
    body.surface_tet[v] = tet;
    body.surface_bary[v] = w;
  }
  if (r.next()) r.fail("expected end of file after " + str(nv) + " surface vertices, found " + r.found());
  body.mesh = std::move(mesh);
  body.surface = std::move(surface);
  return body;
}

EmbeddedBody load_embedded_body(const std::string& obj_path, const std::string& mesh_path,
                                const std::string& embed_path) {
  return load_embedding(embed_path, load_tet_mesh(mesh_path), load_obj(obj_path));
}

}  // namespace hapticd
