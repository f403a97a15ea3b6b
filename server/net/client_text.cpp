#include "net/client_text.h"

#include <algorithm>
#include <cstdint>
#include <cstdio>

namespace palpsim::net {
namespace {

// the length of the UTF-8 sequence at s[i] and its code point; 0 when it is not one
// (a stray continuation byte, a truncated or overlong sequence, a surrogate, > U+10FFFF)
std::size_t utf8_at(std::string_view s, std::size_t i, std::uint32_t& cp) {
  const auto b = [&](std::size_t k) { return std::uint8_t(s[i + k]); };
  const std::uint8_t c = b(0);
  std::size_t n = 0;
  if (c < 0x80) {
    cp = c;
    return 1;
  }
  if ((c & 0xE0) == 0xC0) n = 2, cp = c & 0x1F;
  else if ((c & 0xF0) == 0xE0) n = 3, cp = c & 0x0F;
  else if ((c & 0xF8) == 0xF0) n = 4, cp = c & 0x07;
  else return 0;
  if (i + n > s.size()) return 0;
  for (std::size_t k = 1; k < n; ++k) {
    if ((b(k) & 0xC0) != 0x80) return 0;
    cp = (cp << 6) | (b(k) & 0x3F);
  }
  static constexpr std::uint32_t kMin[5] = {0, 0, 0x80, 0x800, 0x10000};
  if (cp < kMin[n] || cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF)) return 0;
  return n;
}

// code points shown as \uXXXX: C1 controls, and those that break or reorder a line on a
// terminal (line and paragraph separators, bidirectional embeddings, overrides, isolates)
bool escaped_code_point(std::uint32_t cp) {
  return (cp >= 0x80 && cp <= 0x9F) || cp == 0x2028 || cp == 0x2029 || (cp >= 0x202A && cp <= 0x202E) ||
         (cp >= 0x2066 && cp <= 0x2069) || cp == 0x200E || cp == 0x200F || cp == 0x061C;
}

}  // namespace

std::string client_text(std::string_view s, std::size_t max_chars) {
  std::string out;
  out.reserve(std::min(s.size(), max_chars) + 16);
  char b[16];
  std::size_t i = 0, chars = 0;
  while (i < s.size() && chars < max_chars) {
    std::uint32_t cp = 0;
    const std::size_t n = utf8_at(s, i, cp);
    if (n == 0) {
      std::snprintf(b, sizeof b, "\\x%02x", unsigned(std::uint8_t(s[i])));
      out += b;
      i += 1;
    } else if (cp < 0x20 || cp == 0x7F) {
      const char* named = cp == '\n' ? "\\n" : cp == '\r' ? "\\r" : cp == '\t' ? "\\t" : nullptr;
      if (named) {
        out += named;
      } else {
        std::snprintf(b, sizeof b, "\\x%02x", unsigned(cp));
        out += b;
      }
      i += 1;
    } else if (escaped_code_point(cp)) {
      std::snprintf(b, sizeof b, "\\u%04x", unsigned(cp));
      out += b;
      i += n;
    } else {
      out.append(s.data() + i, n);
      i += n;
    }
    ++chars;
  }
  // what is left is cut, and said so
  if (i < s.size()) out += "... (" + std::to_string(s.size() - i) + " more bytes cut)";
  return out;
}

}  // namespace palpsim::net
