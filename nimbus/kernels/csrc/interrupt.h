// Ctrl-C inside a long compiled loop (issue 35: `--set ray_samples=...` marched for minutes and ignored Ctrl-C).
//
// torch.ops calls release the GIL, so Python's SIGINT handler only sets a flag that nothing reads until the op
// returns.  An Interrupt is polled between blocks of work: on the thread that called the op, at most every
// kPollMs, it takes the GIL and asks Python whether SIGINT arrived (PyOS_InterruptOccurred, which clears the flag;
// PyErr_SetInterrupt sets it again, so Python raises KeyboardInterrupt as soon as the op returns).  Every thread
// then stops at its next poll and the op returns early; its result is never used, because the KeyboardInterrupt
// is raised before the next Python line.  Only the order of work blocks changes nothing: the arithmetic of each
// ray is the same, so results are the same bits with or without polling.

#pragma once

#include <Python.h>

#include <atomic>
#include <chrono>
#include <thread>

namespace nimbus_interrupt {

// How often the calling thread asks Python (a GIL round trip costs about a microsecond).
constexpr int kPollMs = 50;

class Interrupt {
 public:
  Interrupt() : caller_(std::this_thread::get_id()), last_(Clock::now()) {}

  // Whether the op should stop now.  Cheap on every thread but the caller, and on the caller between polls.
  bool stop() {
    if (stopped_.load(std::memory_order_relaxed)) return true;
    if (std::this_thread::get_id() != caller_) return false;
    const auto now = Clock::now();
    if (now - last_ < std::chrono::milliseconds(kPollMs)) return false;
    last_ = now;
    if (!Py_IsInitialized()) return false;
    const PyGILState_STATE gil = PyGILState_Ensure();
    const bool hit = PyOS_InterruptOccurred() != 0;  // main thread only; elsewhere always 0
    if (hit) PyErr_SetInterrupt();                    // Python raises KeyboardInterrupt once the op returns
    PyGILState_Release(gil);
    if (hit) stopped_.store(true, std::memory_order_relaxed);
    return hit;
  }

 private:
  using Clock = std::chrono::steady_clock;
  const std::thread::id caller_;
  Clock::time_point last_;
  std::atomic<bool> stopped_{false};
};

}  // namespace nimbus_interrupt
