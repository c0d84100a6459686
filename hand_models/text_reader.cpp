#include "hand_models/text_reader.hpp"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <system_error>
#include <utility>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand::detail {

void fail_at(const std::string& path, long long line, const std::string& msg) {
  throw MeshError(path + ":" + std::to_string(line) + ": " + msg);
}

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

TextReader::TextReader(std::string path, bool hash_comments) : path_(std::move(path)), hash_comments_(hash_comments) {
  std::error_code ec;
  if (std::filesystem::is_directory(path_, ec)) fail_at(path_, 0, "cannot open file: it is a directory");
  errno = 0;
  in_.open(path_, std::ios::binary);
  if (!in_) {
    const std::string why = errno ? std::error_code(errno, std::generic_category()).message() : "unknown error";
    fail_at(path_, 0, "cannot open file: " + why);
  }
}

bool TextReader::next() {
  static constexpr const char* kSpace = " \t\r\v\f";
  while (read_line()) {
    ++line_;
    if (hash_comments_) text_.erase(std::min(text_.find('#'), text_.size()));
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

void TextReader::expect_more(const std::string& what) {
  if (!next()) fail("expected " + what + ", found end of file");
}

std::string TextReader::found() const {
  if (tokens_.empty()) return "end of file";
  const char* b = tokens_.front().data();
  return quote(std::string_view(b, static_cast<std::size_t>(tokens_.back().data() + tokens_.back().size() - b)));
}

// Like std::getline, but a file without newlines (binary data, /dev/zero) cannot exhaust memory.
bool TextReader::read_line() {
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

long long parse_int(const TextReader& r, std::string_view s, const std::string& what, long long lo, long long hi) {
  long long v = 0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (ec == std::errc::invalid_argument || end != s.data() + s.size())
    r.fail(what + " " + quote(s) + " is not an integer");
  if (ec == std::errc::result_out_of_range || v < lo || v > hi)
    r.fail(what + " " + quote(s) + " is out of range [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
  return v;
}

double parse_real(const TextReader& r, std::string_view s, const std::string& what, bool finite) {
  std::string_view t = s;
  // from_chars rejects the leading '+' that printf-style writers may emit.
  if (t.size() > 1 && t[0] == '+' && t[1] != '+' && t[1] != '-') t.remove_prefix(1);
  double v = 0;
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  if (ec == std::errc::invalid_argument || end != t.data() + t.size())
    r.fail(what + " " + quote(s) + " is not a number");
  if (ec == std::errc::result_out_of_range) r.fail(what + " " + quote(s) + " is out of the range of a double");
  if (finite && !std::isfinite(v)) r.fail(what + " " + quote(s) + " is not a finite number");
  return v;
}

}  // namespace hapticd::hand::detail
