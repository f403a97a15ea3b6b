// Thread attributes of the server's threads: names (Linux: at most 15 characters), so
// that top -H, ps -L and debuggers tell them apart (pose, control, deform, render,
// stream), and the low priority of the background ones.
#pragma once

#ifdef __linux__
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace palpsim {

/// Gives the calling thread a name; does nothing where the platform has no thread names.
inline void name_this_thread(const char* name) {
#ifdef __linux__
  pthread_setname_np(pthread_self(), name);
#else
  (void)name;
#endif
}

/// Lowers the calling thread below every thread that serves poses, and the threads it
/// starts later inherit it (Mesa's llvmpipe rasteriser threads of the render thread):
/// its nice value, and with `idle` Linux's SCHED_IDLE, under which any other thread
/// that wakes takes the core at once rather than after the scheduler's minimum slice.
///
/// Why SCHED_IDLE by default: on the 2-core VM, lumbar phantom at 2 mm, VOI 32 on the
/// CPU, palpsim-haptic pressing at 1 kHz on the same machine (3 runs each): with the
/// deformation worker alone at nice 19 the round trip p99 was 0.5-1.8 ms and 18-34
/// deadlines of 5000 were missed, under SCHED_IDLE 0.35-0.39 ms and 6-14; with a viewer
/// rendering with llvmpipe too, nice 19 gave 0.7-2.8 ms and 62-97 missed, SCHED_IDLE
/// 0.47-0.49 ms and 14-35. A background thread then runs only on a core nothing else
/// wants, which is what the deformation and render paths are for (fewer steps, fewer
/// frames on a busy machine; the haptic path never waits).
inline void lower_this_thread(int nice, bool idle) {
#ifdef __linux__
  setpriority(PRIO_PROCESS, pid_t(syscall(SYS_gettid)), nice);
  if (idle) {
    sched_param sp{};
    sched_setscheduler(0, SCHED_IDLE, &sp);
  }
#else
  (void)nice;
  (void)idle;
#endif
}

}  // namespace palpsim
