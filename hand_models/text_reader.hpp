#pragma once
// Internal: strict line-by-line reading of the text formats in hand_models (TetGen,
// Gmsh ASCII, OBJ, .embed). Every failure is a MeshError (tet_mesh.hpp)
// "<path>:<line>: ..." (line 0: the file as a whole).
#include <climits>
#include <fstream>
#include <string>
#include <string_view>
#include <vector>

namespace hapticd::hand::detail {

[[noreturn]] void fail_at(const std::string& path, long long line, const std::string& msg);

// Keeps messages short and printable when the offending text is long or binary.
std::string quote(std::string_view s);

// Token lines of a text file: blank-separated tokens, optionally with '#' comments.
class TextReader {
 public:
  TextReader(std::string path, bool hash_comments);

  // Advances to the next line holding any token; false at end of file, where
  // line() stays at the last line so end-of-file errors point there.
  bool next();
  void expect_more(const std::string& what);  // next(), failing "expected <what>, found end of file"

  const std::string& path() const { return path_; }
  long long line() const { return line_; }
  std::size_t size() const { return tokens_.size(); }
  std::string_view operator[](std::size_t i) const { return tokens_[i]; }
  std::string found() const;  // the line's tokens quoted, or "end of file"
  [[noreturn]] void fail(const std::string& msg) const { fail_at(path_, line_, msg); }

 private:
  bool read_line();

  std::string path_;
  bool hash_comments_;
  std::ifstream in_;
  std::string text_;
  std::vector<std::string_view> tokens_;
  long long line_ = 0;
};

// The whole token as a decimal integer in [lo, hi], or r.fail naming `what`.
long long parse_int(const TextReader& r, std::string_view s, const std::string& what, long long lo = LLONG_MIN,
                    long long hi = LLONG_MAX);

// The whole token as a double (a leading '+' allowed); finite: reject inf and nan.
double parse_real(const TextReader& r, std::string_view s, const std::string& what, bool finite = true);

}  // namespace hapticd::hand::detail
