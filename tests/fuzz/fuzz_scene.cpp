// libFuzzer target: the scene text parser and its checks (server/net/scene_io.h) on any
// text, as a client's LoadScene sends it. A scene is either accepted or refused with
// palpsim::Error naming the field; any other exception, an abort, a memory error (ASan)
// or undefined behaviour (UBSan) is a finding.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/error.h"
#include "net/scene_io.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    palpsim::parse_scene_text(std::string(reinterpret_cast<const char*>(data), size), "fuzz.textproto");
  } catch (const palpsim::Error&) {
    // refused, as bad input should be
  }
  return 0;
}
