// The haptic client's endpoint resolution (clients/haptic/endpoint.h): a server bound to
// every interface (a container's tcp://0.0.0.0:7420) names wildcard pose endpoints, which
// the client must reach at the host it connected to.
#include <catch2/catch.hpp>

#include "endpoint.h"

using palpsim::haptic::resolve_endpoint;

TEST_CASE("wildcard hosts become the control address's host", "[haptic][endpoint]") {
  CHECK(resolve_endpoint("tcp://0.0.0.0:7421", "tcp://palpsim-server:7420") == "tcp://palpsim-server:7421");
  CHECK(resolve_endpoint("tcp://*:7421", "tcp://10.0.0.5:7420") == "tcp://10.0.0.5:7421");
  CHECK(resolve_endpoint("tcp://[::]:7421", "tcp://[fd00::2]:7420") == "tcp://[fd00::2]:7421");
  // a control address that is itself a wildcard (or not tcp) leaves only the local host
  CHECK(resolve_endpoint("tcp://0.0.0.0:7421", "tcp://0.0.0.0:7420") == "tcp://127.0.0.1:7421");
}

TEST_CASE("named hosts and other transports are kept", "[haptic][endpoint]") {
  CHECK(resolve_endpoint("tcp://127.0.0.1:7421", "tcp://10.0.0.5:7420") == "tcp://127.0.0.1:7421");
  CHECK(resolve_endpoint("tcp://server.lan:7421", "tcp://10.0.0.5:7420") == "tcp://server.lan:7421");
  CHECK(resolve_endpoint("ipc:///tmp/s.pose", "ipc:///tmp/s") == "ipc:///tmp/s.pose");
}
