// The Catch2 v2 main shared by every test executable: it registers the optional
// backends of this build (core/linked_backends.h), as palpsim-server does, then runs.
#define CATCH_CONFIG_RUNNER
#include <catch2/catch.hpp>

#include "core/linked_backends.h"

int main(int argc, char* argv[]) {
  palpsim::register_linked_backends();
  return Catch::Session().run(argc, argv);
}
