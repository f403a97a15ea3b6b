// libFuzzer target: the CT header checks (server/prep/ct_header.h) on any bytes. The first
// byte picks the file name, so the format (NIfTI .nii and .nii.gz, NRRD .nrrd and .nhdr,
// MetaImage .mha and .mhd); the rest are the file's first bytes. A header is either
// accepted or refused with palpsim::Error; any other exception, an abort, a memory error
// (ASan) or undefined behaviour (UBSan) is a finding.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/error.h"
#include "prep/ct_header.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const char* const kNames[] = {"ct.nii", "ct.nii.gz", "ct.nrrd", "ct.nhdr", "ct.mha", "ct.mhd"};
  if (size == 0) return 0;
  const std::string name = kNames[data[0] % (sizeof kNames / sizeof *kNames)];
  try {
    palpsim::check_ct_header(name, std::string_view(reinterpret_cast<const char*>(data) + 1, size - 1));
  } catch (const palpsim::Error&) {
    // refused, as bad input should be
  }
  return 0;
}
