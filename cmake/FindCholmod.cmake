# Debian's SuiteSparse ships no CMake config: find CHOLMOD by hand and expose
# it as the imported target hapticd::cholmod.
find_path(CHOLMOD_INCLUDE_DIR cholmod.h PATH_SUFFIXES suitesparse REQUIRED)
foreach(lib cholmod suitesparseconfig amd colamd camd ccolamd)
  find_library(CHOLMOD_${lib}_LIBRARY ${lib} REQUIRED)
  list(APPEND CHOLMOD_LIBRARIES ${CHOLMOD_${lib}_LIBRARY})
endforeach()
add_library(hapticd_cholmod INTERFACE)
add_library(hapticd::cholmod ALIAS hapticd_cholmod)
target_include_directories(hapticd_cholmod SYSTEM INTERFACE ${CHOLMOD_INCLUDE_DIR})
target_link_libraries(hapticd_cholmod INTERFACE ${CHOLMOD_LIBRARIES})
message(STATUS "CHOLMOD: ${CHOLMOD_INCLUDE_DIR}")
