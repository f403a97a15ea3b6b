// Wildcard hosts in the server's endpoints replaced by the control address's host.
#include "endpoint.h"

namespace palpsim::haptic {

namespace {

constexpr const char* kTcp = "tcp://";

// the host of a tcp://HOST:PORT address ("" for other transports or without a port)
std::string tcp_host(const std::string& address) {
  if (address.rfind(kTcp, 0) != 0) return "";
  const std::string rest = address.substr(6);
  const auto colon = rest.rfind(':');
  return colon == std::string::npos ? "" : rest.substr(0, colon);
}

bool is_wildcard(const std::string& host) { return host == "*" || host == "0.0.0.0" || host == "::" || host == "[::]"; }

}  // namespace

std::string resolve_endpoint(const std::string& endpoint, const std::string& control_address) {
  const std::string host = tcp_host(endpoint);
  if (!is_wildcard(host)) return endpoint;
  std::string control_host = tcp_host(control_address);
  if (control_host.empty() || is_wildcard(control_host)) control_host = "127.0.0.1";
  // a bare IPv6 address needs brackets before the port
  if (control_host.find(':') != std::string::npos && control_host.front() != '[') control_host = "[" + control_host + "]";
  return kTcp + control_host + endpoint.substr(endpoint.rfind(':'));
}

}  // namespace palpsim::haptic
