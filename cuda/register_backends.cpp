// register_linked_backends() of a CUDA build: cuda's deformation backend, nvJPEG encoder
// and CUDA-GL overlay writer go into server/'s registries.
#include "cuda/register_backends.h"

#include "core/linked_backends.h"

namespace palpsim {

void cuda::register_backends() {
  register_deform_backend();
  register_render_backends();
}

void register_linked_backends() { cuda::register_backends(); }

}  // namespace palpsim
