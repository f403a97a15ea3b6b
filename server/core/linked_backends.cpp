// register_linked_backends() of a build without CUDA (PALPSIM_CUDA off): the cpu
// deformation backend, turbojpeg and the upload overlay writer are built into server/,
// so no registry gets an entry.
#include "core/linked_backends.h"

namespace palpsim {

void register_linked_backends() {}

}  // namespace palpsim
