// Client strings (session names, parameter names, paths, scene names, topics) made safe
// for a log line or a reply: control characters escaped, length cut.
#pragma once

#include <cstddef>
#include <string>
#include <string_view>

namespace palpsim::net {

/// Characters of a client string kept in a log line or a reply (client_text's default).
constexpr std::size_t kClientTextChars = 128;

/// `s` as one line of valid UTF-8, at most `max_chars` characters of it: control
/// characters (C0, DEL, C1) and the Unicode line, paragraph and bidirectional controls are
/// written as escapes (\n, \t, \x1b, \u2028), bytes that are not UTF-8 as \xNN, and a
/// longer string is cut with "... (N more bytes cut)". Used for every string a client sent
/// before it reaches a log line or a reply, so that no client can forge a log line, flood
/// the log or have a huge string echoed back. Its output passes through it again unchanged
/// (a backslash is kept as it is) within the limit, so a message that embeds client strings
/// may be passed whole.
std::string client_text(std::string_view s, std::size_t max_chars = kClientTextChars);

}  // namespace palpsim::net
