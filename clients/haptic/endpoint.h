// Endpoints the server names in its replies, made reachable from the client's side.
#pragma once

#include <string>

namespace palpsim::haptic {

/// `endpoint` with a wildcard host (`*`, 0.0.0.0, ::) replaced by the host of the control
/// address the client connected to: a server bound to all interfaces (tcp://0.0.0.0:7420,
/// as in a container) names its pose endpoint tcp://0.0.0.0:7421, which another machine
/// cannot connect to. Other endpoints (a named host, ipc://) are returned as they are.
/// The Python client's palpsim.client.resolve_endpoint does the same.
std::string resolve_endpoint(const std::string& endpoint, const std::string& control_address);

}  // namespace palpsim::haptic
