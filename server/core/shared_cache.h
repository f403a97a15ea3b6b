// A process-wide set of objects that every holder of the same key may share, kept only
// while some holder keeps one: the patient's device copy per device, the multigrid
// solver's scratch per device and VOI size, the held-element map per patient and material.
#pragma once

#include <algorithm>
#include <memory>
#include <mutex>
#include <vector>

namespace palpsim {

/// The live objects of one kind; get() finds one that `match` accepts or keeps a new one
/// from `make` (both called under the cache's lock, so a second caller waits for the first
/// to finish making rather than making its own).
template <typename T>
class SharedCache {
 public:
  template <typename Match, typename Make>
  std::shared_ptr<T> get(Match&& match, Make&& make) {
    std::lock_guard<std::mutex> lock(mu_);
    live_.erase(std::remove_if(live_.begin(), live_.end(), [](const auto& w) { return w.expired(); }), live_.end());
    for (const auto& w : live_)
      if (auto s = w.lock())
        if (match(*s)) return s;
    std::shared_ptr<T> s = make();
    live_.push_back(s);
    return s;
  }

  /// The objects alive now.
  int live() {
    std::lock_guard<std::mutex> lock(mu_);
    int n = 0;
    for (const auto& w : live_) n += w.expired() ? 0 : 1;
    return n;
  }

 private:
  std::mutex mu_;
  std::vector<std::weak_ptr<T>> live_;
};

}  // namespace palpsim
