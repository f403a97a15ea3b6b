// Host loops over the nodes of a box, shared by the CPU solvers.
#pragma once

#include "core/vec3.h"

namespace palpsim::deform {

/// Calls fn(i, j, k) for every node of a box of `n` nodes, i fastest.
template <typename Fn>
void each_node(const Vec3i& n, Fn fn) {
  for (int k = 0; k < n.z; ++k)
    for (int j = 0; j < n.y; ++j)
      for (int i = 0; i < n.x; ++i) fn(i, j, k);
}

}  // namespace palpsim::deform
