// The 4-connected flood of a 2D slice that prep's hole filling and the spine's canal test
// share.
#pragma once
#include <cstddef>
#include <vector>

namespace palpsim {

/// Floods a slice of nu x nv pixels (pixel p = c * nu + a) from queue[first] on: each pixel
/// taken from the queue offers its four neighbours inside the slice to visit(a, c), which
/// appends to the queue those that join (and marks them, so each joins once).
template <typename Visit>
inline void flood_4(const std::vector<int>& queue, std::size_t first, int nu, int nv, const Visit& visit) {
  for (std::size_t q = first; q < queue.size(); ++q) {
    const int p = queue[q], a = p % nu, c = p / nu;
    if (a > 0) visit(a - 1, c);
    if (a < nu - 1) visit(a + 1, c);
    if (c > 0) visit(a, c - 1);
    if (c < nv - 1) visit(a, c + 1);
  }
}

}  // namespace palpsim
