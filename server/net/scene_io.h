// Loading scenes: protobuf text format (proto/palpsim/scene.proto) into validated
// palpsim::Scene settings. Protobuf stays behind this header.
#pragma once

#include <cstddef>
#include <string>

#include "core/scene.h"

namespace palpsim {

/// A scene file's size, at most (scenes are a few kilobytes).
constexpr std::size_t kMaxSceneBytes = 1 << 20;

/// Parses and validates a scene file, read only when it is a regular file (opened
/// without blocking, so a FIFO cannot stall the caller) of at most kMaxSceneBytes.
/// Throws palpsim::Error naming file:line:column for unknown fields, wrong types and
/// out-of-range values (with the allowed range), and naming the file when it cannot be
/// read, is not a regular file, is too large or is empty.
Scene load_scene_file(const std::string& path);

/// Parses and validates scene text; `origin` names it in messages and is the base
/// for relative CT paths (a file path, or "" for the working folder). Text that sets no
/// field (empty, blanks or comments only) is refused.
Scene parse_scene_text(const std::string& text, const std::string& origin);

/// The built-in default scene: the phantom, haptics only.
Scene default_scene();

/// Every scene field with its default, unit and allowed range, one per line
/// (for `--scene-doc` and the README).
std::string scene_field_reference();

}  // namespace palpsim
