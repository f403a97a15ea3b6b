// Thread attributes of the server's threads: names (Linux: at most 15 characters), so
// that top -H, ps -L and debuggers tell them apart (pose, control, deform, render,
// stream), the low priority of the background ones and the real-time one of the pose path.
#pragma once

#include <thread>

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
/// Why SCHED_IDLE by default: on the shared 2-core VM, phantom at 2 mm, VOI 32 on the
/// CPU, palpsim-haptic pressing at 1 kHz for 5 s on the same machine. Deformation alone:
/// nice 19 gave round trip p99 0.5 / 1.8 ms and 34 / 18 missed deadlines of 5000,
/// SCHED_IDLE 0.35 / 0.39 ms and 6 / 14. With a viewer rendering 640x360 with llvmpipe
/// too, 7 runs each: nice 19 p99 0.7-3.3 ms (median 2.5), 56-97 missed;
/// SCHED_IDLE 0.47-4.0 ms (median 0.58), 14-202 missed (one outlier run). The VM's noise
/// is large, SCHED_IDLE is better in most runs and never worse at p99.9. A background
/// thread then runs only on a core nothing else wants, which is what the deformation and
/// render paths are for (fewer steps, fewer frames on a busy machine; the haptic path
/// never waits).
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

/// Puts the calling thread under SCHED_FIFO at `priority` (1..99), above every thread of
/// the machine under the normal policy, as a haptic loop needs when other work shares the
/// cores. False, and nothing changed, where the process may not (it needs root or
/// CAP_SYS_NICE, or RLIMIT_RTPRIO of at least `priority`) or the platform has no such policy.
inline bool raise_this_thread(int priority) {
#ifdef __linux__
  sched_param sp{};
  sp.sched_priority = priority;
  return priority >= 1 && priority <= 99 && pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) == 0;
#else
  (void)priority;
  return false;
#endif
}

/// True when this process may put its threads under SCHED_FIFO at `priority`: tried on a
/// short-lived thread of its own, so the caller's policy is untouched. For threads that
/// others start with a policy set beforehand (libzmq's I/O threads abort when theirs
/// cannot be applied).
inline bool may_raise_threads(int priority) {
  bool ok = false;
  std::thread probe([&] { ok = raise_this_thread(priority); });
  probe.join();
  return ok;
}

}  // namespace palpsim
