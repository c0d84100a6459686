#pragma once
// A process-level setting of the executables (hapticd, haptic-bench), not of the libraries: the
// visual step's large temporaries (the Schur complement's and the linearization's dense
// tool-by-handle blocks: 1.3 MB each for a 1700-tet hand with 16 handles) are allocated and freed
// every step. Left to glibc's defaults, each is a fresh mmap whose pages the kernel faults in and
// zeroes again every time (with mlockall(MCL_FUTURE), at the mmap itself): on the 16-frame glove
// scene that was ~30 % of the visual step (`haptic-bench world --scene scenes/glove_grasp.json`,
// step median about 17 -> 12 ms, contact-free; run-to-run spread on this machine is large).

namespace hapticd::process {

// Serves allocations of up to 32 MB (glibc's largest mmap threshold) from the heap and keeps freed
// heap memory in the process, so that a steady visual loop reuses its pages instead of faulting
// them in. Process-wide; call once at start-up, before threads. False if the allocator refused
// (a sanitizer's allocator ignores these settings).
bool keep_large_allocations_on_heap();

}  // namespace hapticd::process
