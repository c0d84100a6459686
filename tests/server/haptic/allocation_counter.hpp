#pragma once
// Counts heap allocations made by the threads that ask (global operator new is
// replaced for the haptic_tests binary in allocation_counter.cpp).
namespace hapticd::testing_util {
void count_allocations_on_this_thread(bool on);
long allocations_on_this_thread();
}  // namespace hapticd::testing_util
