// The cache of prepared patients: one folder per content key (SHA-256 of the CT's
// bytes, the prep and force settings and a format version), written to a
// temporary folder and renamed into place, so a half-written entry is never used.
#pragma once

#include <string>

#include "core/patient.h"
#include "core/scene.h"

namespace palpsim {

/// Bumped whenever the preparation's results change for the same inputs, or prep.json's keys do.
constexpr int kPrepFormatVersion = 5;

/// The cache folder: prep.cache_dir, else $PALPSIM_CACHE, else ~/.cache/palpsim.
std::string cache_root(const PrepSettings& prep);

/// Reads the entry `entry_dir` into `p` (grid, intensity, body, bone, A, B,
/// has_bone, source; F and grad F are left for the caller to derive) and the
/// stored report into `json`. Returns false when the entry is absent; an entry
/// that is corrupt or of another format is removed and false returned.
bool load_cached_patient(const std::string& entry_dir, Patient& p, std::string& json);

/// Stores `p` and `json` as the entry `root/key`: written into a temporary folder
/// and renamed into place (an entry another process finished first is kept).
/// Returns the entry's path. Throws palpsim::Error when the cache is not writable.
std::string store_cached_patient(const std::string& root, const std::string& key, const Patient& p,
                                 const std::string& json);

}  // namespace palpsim
