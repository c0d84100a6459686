cmake_minimum_required(VERSION 3.25)
# ctest smoke run of `haptic-bench haptic_rate --size tiny`: it runs, its JSON has a row per
# haptic rate (1, 2, 4 kHz) with the documented fields, tick times are positive with p99 >= median,
# and the passive stiffness found at each rate agrees with the closed forms the bench reports
# (bench/haptic_rate_bench.cpp, Theory):
#  - above Colgate & Schenkel's sufficient bound (colgate_passivity_bound_n_per_m): no stiffness under
#    it can be active, so the first stiffness found active lies above it;
#  - under the ideal wall's stability bound (theory_n_per_m): past it the sampled loop rings and puts
#    energy into the device, so nothing beyond it is passive (a meter that missed that energy would
#    find the whole sweep passive);
#  - growing with the rate as that bound does (~ m / T^2, 4x per doubling): the ratio of the true
#    passive stiffness at 2 or 4 kHz to that at 1 kHz lies in the window the bisection's brackets
#    leave (max_passive_f / first_active_1k, first_active_f / max_passive_1k), and the theory's ratio
#    must lie in that window. The tolerance is the bracket itself (tiny: bisected to 1.5x), not a
#    chosen number.
# Usage: cmake -DBENCH=haptic-bench -DOUT=file.json -P haptic_rate_smoke.cmake
include(${CMAKE_CURRENT_LIST_DIR}/smoke_lib.cmake)
smoke_run(haptic_rate)
if(NOT rows EQUAL 3)
  message(FATAL_ERROR "${rows} rows, expected 3")
endif()
set(expected_hz 1000 2000 4000)
math(EXPR last "${rows} - 1")
foreach(i RANGE ${last})
  foreach(field haptic_hz tick_us_median tick_us_p99 max_passive_stiffness_n_per_m first_active_n_per_m
                energy_at_max_j theory_n_per_m)
    string(JSON type ERROR_VARIABLE err TYPE "${doc}" rows ${i} ${field})
    if(err)
      message(FATAL_ERROR "rows[${i}] has no ${field}: ${err}")
    endif()
    if(NOT type STREQUAL "NUMBER")  # a NaN or infinity would be written as null
      message(FATAL_ERROR "rows[${i}].${field} is ${type}")
    endif()
  endforeach()
  string(JSON probes_type TYPE "${doc}" rows ${i} probes)
  if(NOT probes_type STREQUAL "ARRAY")
    message(FATAL_ERROR "rows[${i}].probes is ${probes_type}")
  endif()
  string(JSON hz GET "${doc}" rows ${i} haptic_hz)
  list(GET expected_hz ${i} want)
  if(NOT hz EQUAL want)
    message(FATAL_ERROR "rows[${i}].haptic_hz = ${hz}, expected ${want}")
  endif()
  string(JSON median GET "${doc}" rows ${i} tick_us_median)
  string(JSON p99 GET "${doc}" rows ${i} tick_us_p99)
  if(NOT median GREATER 0 OR p99 LESS median)
    message(FATAL_ERROR "${hz} Hz: tick ${median} us median, ${p99} us p99")
  endif()
  string(JSON k GET "${doc}" rows ${i} max_passive_stiffness_n_per_m)
  string(JSON theory GET "${doc}" rows ${i} theory_n_per_m)
  string(JSON energy GET "${doc}" rows ${i} energy_at_max_j)
  string(JSON tolerance GET "${doc}" energy_tolerance_j)
  if(NOT k GREATER 0 OR NOT theory GREATER 0)
    message(FATAL_ERROR "${hz} Hz: passive stiffness ${k} N/m, theory ${theory} N/m")
  endif()
  if(energy GREATER tolerance)
    message(FATAL_ERROR "${hz} Hz: ${energy} J put into the device at the stiffness reported passive")
  endif()
  # CMake's math() is integer only: the stiffnesses as whole N/m (truncation moves a ratio by < 1e-5).
  foreach(field k theory)
    if(NOT ${field} MATCHES "^[0-9]+(\\.[0-9]*)?$")
      message(FATAL_ERROR "${hz} Hz: ${field} = ${${field}} is not a plain decimal")
    endif()
    string(REGEX REPLACE "\\..*$" "" ${field}_${hz} "${${field}}")
  endforeach()
  string(JSON active GET "${doc}" rows ${i} first_active_n_per_m)
  string(JSON colgate GET "${doc}" rows ${i} colgate_passivity_bound_n_per_m)
  if(active EQUAL 0)
    message(FATAL_ERROR "${hz} Hz: nothing active up to the sweep's top, over the stability bound ${theory} N/m")
  endif()
  if(NOT active GREATER colgate)
    message(FATAL_ERROR "${hz} Hz: ${active} N/m found active, under Colgate's sufficient passivity bound ${colgate} N/m")
  endif()
  if(NOT k LESS theory)
    message(FATAL_ERROR "${hz} Hz: ${k} N/m found passive, beyond the ideal wall's stability bound ${theory} N/m")
  endif()
  string(REGEX REPLACE "\\..*$" "" active_${hz} "${active}")
endforeach()
foreach(hz 2000 4000)
  # theory_f / theory_1k within (k_f / active_1k, active_f / k_1k), cross-multiplied.
  math(EXPR lo_lhs "${k_${hz}} * ${theory_1000}")
  math(EXPR lo_rhs "${theory_${hz}} * ${active_1000}")
  math(EXPR hi_lhs "${theory_${hz}} * ${k_1000}")
  math(EXPR hi_rhs "${active_${hz}} * ${theory_1000}")
  if(NOT lo_lhs LESS lo_rhs OR NOT hi_lhs LESS hi_rhs)
    message(FATAL_ERROR "${hz} Hz over 1 kHz: passive ${k_${hz}} / ${k_1000} N/m (active ${active_${hz}} / "
                        "${active_1000}) does not bracket the stability bound's ratio ${theory_${hz}} / ${theory_1000}")
  endif()
endforeach()
message(STATUS "haptic_rate smoke: 3 rows; passive stiffness ${k_1000} / ${k_2000} / ${k_4000} N/m at 1 / 2 / 4 kHz "
               "(stability bound ${theory_1000} / ${theory_2000} / ${theory_4000} N/m)")
