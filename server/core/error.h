// The project's exception type: thrown at boundaries (files, scenes, network).
#pragma once

#include <stdexcept>
#include <string>

namespace palpsim {

/// An error a user can act on; the message names the file, field or message and
/// what is wrong with it.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

}  // namespace palpsim
