#pragma once

// The pre-shared key file of hapticd and its clients (protocol/README.md, "Key file"): one line of
// 64 hexadecimal digits (32 bytes), optionally followed by a newline; readable by its owner only.
// `hapticd --generate-key FILE` writes one.

#include <stdexcept>
#include <string>
#include <string_view>

#include "protocol/auth.hpp"

namespace hapticd::protocol {

// Says which file and what is wrong with it, and how to fix it.
class KeyFileError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Reads and checks a key file. Refused (KeyFileError): not a regular file, unreadable, any
// permission for group or others (chmod 600), longer than 4 KiB, anything but 64 hex digits on one
// line (surrounding blanks and one trailing newline allowed), an all-zero key.
Key load_key_file(const std::string& path);

// 64 hex digits -> key; throws KeyFileError whose message starts with `where`.
Key parse_key_hex(std::string_view text, const std::string& where);

// Writes a new random key to `path`, created with mode 0600; refuses to overwrite an existing file.
Key generate_key_file(const std::string& path);

// 8 hex digits naming a key in logs without revealing it (BLAKE2b of the key, domain-separated).
std::string key_fingerprint(const Key& key);

}  // namespace hapticd::protocol
