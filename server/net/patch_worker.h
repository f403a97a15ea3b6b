// The patch worker: cuts local force model patches (PROTOCOL.md, "Local force model") off
// the pose thread. The pose thread decides that a session's patch is due and hands the
// worker a request (the tip, the box size, the parameters) through the session's
// PatchChannel, newest-wins; the worker copies C, F and grad F into a serialized
// LocalForceModel and hands it back the same way; the pose thread appends those bytes to
// the session's next reply. Neither waits for the other. A channel is made by the worker
// the first time a session's poses ask for patches, so sessions that never ask cost nothing.
#pragma once

#include "runtime/patch_channel.h"

namespace palpsim::runtime {
struct ServerShared;
}

namespace palpsim::net {

/// Runs the worker until shared.stop is set: every millisecond while some session asks for
/// patches (every 20 ms while none ever did), makes the channels asked for and answers
/// every fresh request.
void run_patch_worker(runtime::ServerShared& shared);

}  // namespace palpsim::net
