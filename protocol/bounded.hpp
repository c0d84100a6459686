#pragma once

// Fixed-capacity containers for the message structs: the storage lives inside the struct, so a
// caller-owned message is reused across datagrams without touching the heap.

#include <algorithm>
#include <array>
#include <cstddef>
#include <span>
#include <string_view>

namespace hapticd::protocol {

// A string of at most N bytes stored in place. Assigning a longer one fails instead of
// truncating: a silently cut frame name would map to the wrong handle.
template <std::size_t N>
class FixedString {
 public:
  static constexpr std::size_t kCapacity = N;

  constexpr FixedString() = default;

  // From a literal, checked at compile time: FixedString<8> s = "palm";
  template <std::size_t M>
  constexpr FixedString(const char (&literal)[M]) noexcept {  // NOLINT(google-explicit-constructor)
    static_assert(M - 1 <= N, "literal longer than the FixedString capacity");
    std::copy_n(literal, M - 1, data_.begin());
    size_ = M - 1;
  }

  // False (and unchanged) when text is longer than N.
  constexpr bool assign(std::string_view text) noexcept {
    if (text.size() > N) return false;
    std::copy(text.begin(), text.end(), data_.begin());
    size_ = text.size();
    return true;
  }

  [[nodiscard]] constexpr std::string_view view() const noexcept { return {data_.data(), size_}; }
  [[nodiscard]] constexpr std::size_t size() const noexcept { return size_; }
  [[nodiscard]] constexpr bool empty() const noexcept { return size_ == 0; }

  friend constexpr bool operator==(const FixedString& a, const FixedString& b) noexcept { return a.view() == b.view(); }

 private:
  std::array<char, N> data_{};
  std::size_t size_ = 0;
};

// Up to N elements stored in place; the used part is [0, size()).
template <typename T, std::size_t N>
class BoundedArray {
 public:
  static constexpr std::size_t kCapacity = N;

  // False (and unchanged) when full.
  constexpr bool push_back(const T& item) noexcept {
    if (size_ == N) return false;
    items_[size_++] = item;
    return true;
  }
  // False (and unchanged) when n > N. New elements keep whatever the storage held: callers that
  // resize to fill assign every element.
  constexpr bool resize(std::size_t n) noexcept {
    if (n > N) return false;
    size_ = n;
    return true;
  }
  constexpr void clear() noexcept { size_ = 0; }

  // False (and unchanged) when more than N.
  constexpr bool assign(std::span<const T> items) noexcept {
    if (items.size() > N) return false;
    std::copy(items.begin(), items.end(), items_.begin());
    size_ = items.size();
    return true;
  }

  [[nodiscard]] constexpr std::size_t size() const noexcept { return size_; }
  [[nodiscard]] constexpr bool empty() const noexcept { return size_ == 0; }
  constexpr T& operator[](std::size_t i) noexcept { return items_[i]; }
  constexpr const T& operator[](std::size_t i) const noexcept { return items_[i]; }
  constexpr T* begin() noexcept { return items_.data(); }
  constexpr T* end() noexcept { return items_.data() + size_; }
  constexpr const T* begin() const noexcept { return items_.data(); }
  constexpr const T* end() const noexcept { return items_.data() + size_; }
  [[nodiscard]] constexpr std::span<const T> span() const noexcept { return {items_.data(), size_}; }

  friend constexpr bool operator==(const BoundedArray& a, const BoundedArray& b) noexcept {
    return std::equal(a.begin(), a.end(), b.begin(), b.end());
  }

 private:
  std::array<T, N> items_{};
  std::size_t size_ = 0;
};

}  // namespace hapticd::protocol
