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
