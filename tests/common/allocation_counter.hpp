#pragma once
// Counts heap allocations made by the threads that ask: global operator new is
// replaced, in allocation_counter.cpp, for every test binary that links it.
// Per thread, so a helper thread (a fake server, a client) running meanwhile
// is not what is measured.
namespace hapticd::testing_util {

void count_allocations_on_this_thread(bool on);
long allocations_on_this_thread();

// Allocations the calling thread makes inside `body`.
template <typename F>
long allocations_in(F&& body) {
  const long before = allocations_on_this_thread();
  count_allocations_on_this_thread(true);
  body();
  count_allocations_on_this_thread(false);
  return allocations_on_this_thread() - before;
}

}  // namespace hapticd::testing_util
