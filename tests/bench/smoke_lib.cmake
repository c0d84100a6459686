# Shared by the tests/bench/*_smoke.cmake scripts (include()d): run a suite, check its rows' fields.

# Runs `${BENCH} <suite> --size tiny --json ${OUT}` and reads the JSON into `doc` and the number of
# its rows into `rows` (in the caller's scope); fails unless it ran and names the suite.
macro(smoke_run suite)
  execute_process(COMMAND ${BENCH} ${suite} --size tiny --json ${OUT} RESULT_VARIABLE rc)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "haptic-bench ${suite} --size tiny failed: ${rc}")
  endif()
  file(READ ${OUT} doc)
  string(JSON named GET "${doc}" suite)
  if(NOT named STREQUAL "${suite}")
    message(FATAL_ERROR "suite is '${named}', expected '${suite}'")
  endif()
  string(JSON rows LENGTH "${doc}" rows)
endmacro()

# Fails unless row `i` of `doc` has every field listed, of its type: smoke_check_fields(i STRINGS a b
# BOOLEANS c NUMBERS d e). A NaN or infinity is written as null, so it fails as not a NUMBER.
function(smoke_check_fields i)
  cmake_parse_arguments(ARG "" "" "STRINGS;BOOLEANS;NUMBERS" ${ARGN})
  foreach(kind STRING BOOLEAN NUMBER)
    foreach(field IN LISTS ARG_${kind}S)
      string(JSON type ERROR_VARIABLE err TYPE "${doc}" rows ${i} ${field})
      if(err)
        message(FATAL_ERROR "rows[${i}] has no ${field}: ${err}")
      endif()
      if(NOT type STREQUAL kind)
        message(FATAL_ERROR "rows[${i}].${field} is ${type}, expected ${kind}")
      endif()
    endforeach()
  endforeach()
endfunction()

# The reference rows of a suite whose rows compare against a run stepped at every tick: counts row
# `i` into `references` (caller's scope) when its `reference` is true, and fails unless such a row
# has `key` equal to `expected` at 1000 Hz and no RMS force error, while every other row has some
# (something was compared). smoke_check_reference_row(i model linearized)
macro(smoke_check_reference_row i key expected)
  string(JSON _ref_is GET "${doc}" rows ${i} reference)
  string(JSON _ref_key GET "${doc}" rows ${i} ${key})
  string(JSON _ref_hz GET "${doc}" rows ${i} visual_hz)
  string(JSON _ref_err GET "${doc}" rows ${i} rms_force_error_n)
  if(_ref_is)
    math(EXPR references "${references} + 1")
    if(NOT _ref_key STREQUAL "${expected}" OR NOT _ref_hz EQUAL 1000)
      message(FATAL_ERROR "the reference row is ${_ref_key} at ${_ref_hz} Hz, expected ${expected} at 1000 Hz")
    endif()
    if(NOT _ref_err EQUAL 0)
      message(FATAL_ERROR "the reference row's error is ${_ref_err} N RMS, expected 0")
    endif()
  elseif(NOT _ref_err GREATER 0)
    message(FATAL_ERROR "rows[${i}] (${_ref_key}, ${_ref_hz} Hz) has no force error: nothing compared")
  endif()
endmacro()
