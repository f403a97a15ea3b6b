// Factories of the optional backends, by the setting value that asks for them: server/
// defines the interfaces and one registry per choice (the deformation backend, the JPEG
// encoder, the overlay writer), and a module built apart (cuda/) adds its variants when
// the executable's main calls register_linked_backends() (core/linked_backends.h). The
// choosers in server/ look a variant up here and never name the module that made it.
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

namespace palpsim {

/// The registered makers of T, one per setting value `Key` (an enum of core/scene.h).
/// Filled at start-up, read when a backend is chosen (session set-up, the render
/// thread's start); guarded by a mutex, so lookups from any thread are safe.
template <class T, class Key>
class BackendRegistry {
 public:
  /// One registered variant: whether it can be used on this machine (false: `why` says
  /// why; true: `why` says what it runs on) and how to make one (may throw palpsim::Error).
  struct Factory {
    std::function<bool(std::string* why)> usable;
    std::function<std::unique_ptr<T>()> make;
  };

  /// Registers the variant `key` asks for, replacing an earlier one.
  void add(Key key, Factory f) {
    std::lock_guard<std::mutex> lock(mutex_);
    factories_[key] = std::move(f);
  }
  /// Removes the variant of `key` (the tests' fakes restore what they replaced).
  void remove(Key key) {
    std::lock_guard<std::mutex> lock(mutex_);
    factories_.erase(key);
  }
  /// The variant of `key`, or nothing when none is registered (a build without it).
  std::optional<Factory> find(Key key) const {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto it = factories_.find(key);
    if (it == factories_.end()) return std::nullopt;
    return it->second;
  }

 private:
  mutable std::mutex mutex_;
  std::map<Key, Factory> factories_;
};

}  // namespace palpsim
