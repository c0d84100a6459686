#include "protocol/key_file.hpp"

#include <fcntl.h>
#include <sodium.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>

namespace hapticd::protocol {

namespace {

constexpr std::size_t kMaxKeyFileBytes = 4096;

int hex_value(char c) noexcept {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

bool blank(char c) noexcept { return c == ' ' || c == '\t' || c == '\r'; }

std::string octal_mode(mode_t mode) {
  char text[8];
  std::snprintf(text, sizeof text, "%04o", static_cast<unsigned>(mode & 07777));
  return text;
}

}  // namespace

Key parse_key_hex(std::string_view text, const std::string& where) {
  // One line: blanks around the digits, at most one newline at the very end.
  if (!text.empty() && text.back() == '\n') text.remove_suffix(1);
  if (text.find('\n') != std::string_view::npos)
    throw KeyFileError(where + ": more than one line (expected one line of 64 hexadecimal digits)");
  while (!text.empty() && blank(text.front())) text.remove_prefix(1);
  while (!text.empty() && blank(text.back())) text.remove_suffix(1);
  for (std::size_t i = 0; i < text.size(); ++i)
    if (hex_value(text[i]) < 0)
      throw KeyFileError(where + ": character " + std::to_string(i + 1) + " is not a hexadecimal digit " +
                         "(expected 64 of 0-9, a-f)");
  if (text.size() != 2 * kKeyBytes)
    throw KeyFileError(where + ": " + std::to_string(text.size()) + " hexadecimal digits, expected 64 (a " +
                       std::to_string(kKeyBytes) + "-byte key; hapticd --generate-key FILE writes one)");
  Key key;
  bool all_zero = true;
  for (std::size_t i = 0; i < kKeyBytes; ++i) {
    key[i] = static_cast<std::uint8_t>(hex_value(text[2 * i]) * 16 + hex_value(text[2 * i + 1]));
    all_zero = all_zero && key[i] == 0;
  }
  if (all_zero) throw KeyFileError(where + ": the key is all zeros (hapticd --generate-key FILE writes a random one)");
  return key;
}

Key load_key_file(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
  if (fd < 0) {
    const int err = errno;
    if (err == ELOOP) throw KeyFileError(path + ": is a symbolic link; give the key file itself");
    throw KeyFileError(path + ": cannot open the key file (" + std::strerror(err) + ")");
  }
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  struct stat st {};
  if (::fstat(fd, &st) != 0) throw KeyFileError(path + ": cannot stat the key file (" + std::strerror(errno) + ")");
  if (!S_ISREG(st.st_mode)) throw KeyFileError(path + ": not a regular file");
  // As ssh does with private keys: a key others can read (or replace) is no secret.
  if ((st.st_mode & 077) != 0)
    throw KeyFileError(path + ": permissions " + octal_mode(st.st_mode) +
                       " let other users read or change the key; run chmod 600 " + path);
  if (static_cast<std::size_t>(st.st_size) > kMaxKeyFileBytes)
    throw KeyFileError(path + ": " + std::to_string(st.st_size) +
                       " bytes, too large for a key file (one line of 64 "
                       "hexadecimal digits)");
  std::string text(kMaxKeyFileBytes + 1, '\0');
  std::size_t used = 0;
  for (;;) {
    const ssize_t n = ::read(fd, text.data() + used, text.size() - used);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) throw KeyFileError(path + ": cannot read the key file (" + std::strerror(errno) + ")");
    if (n == 0) break;
    used += static_cast<std::size_t>(n);
    if (used == text.size()) throw KeyFileError(path + ": too large for a key file");
  }
  text.resize(used);
  const Key key = parse_key_hex(text, path);
  sodium_memzero(text.data(), text.size());
  return key;
}

Key generate_key_file(const std::string& path) {
  if (sodium_init() < 0) throw KeyFileError("libsodium failed to initialize");
  Key key;
  do randombytes_buf(key.data(), key.size());
  while (std::all_of(key.begin(), key.end(), [](std::uint8_t b) { return b == 0; }));
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string line;
  for (const std::uint8_t b : key) line += {kDigits[b >> 4], kDigits[b & 15]};
  line += '\n';
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0600);
  if (fd < 0) {
    const int err = errno;
    if (err == EEXIST) throw KeyFileError(path + ": exists; not overwritten (remove it first to replace the key)");
    throw KeyFileError(path + ": cannot create the key file (" + std::strerror(err) + ")");
  }
  // The umask may only remove bits; make sure no group or other bit survives either way.
  const bool ok = ::fchmod(fd, 0600) == 0 &&
                  ::write(fd, line.data(), line.size()) == static_cast<ssize_t>(line.size()) && ::fsync(fd) == 0;
  const int err = errno;
  ::close(fd);
  sodium_memzero(line.data(), line.size());
  if (!ok) {
    ::unlink(path.c_str());
    throw KeyFileError(path + ": cannot write the key file (" + std::strerror(err) + ")");
  }
  return key;
}

std::string key_fingerprint(const Key& key) {
  if (sodium_init() < 0) throw KeyFileError("libsodium failed to initialize");
  static constexpr char kLabel[] = "hapticd key fingerprint";
  std::uint8_t digest[16];
  crypto_generichash(digest, sizeof digest, reinterpret_cast<const unsigned char*>(kLabel), sizeof kLabel - 1,
                     key.data(), key.size());
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string text;
  for (int i = 0; i < 4; ++i) text += {kDigits[digest[i] >> 4], kDigits[digest[i] & 15]};
  return text;
}

}  // namespace hapticd::protocol
