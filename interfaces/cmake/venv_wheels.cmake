# Building interface packages against the ROS 2 wheels installed in a Python venv (no ROS
# installation). Included by each package's CMakeLists.txt, after its find_package() calls.
#
# The wheels' exported CMake targets carry the include directories of the container they were
# built in (/opt/python/...): swap them for this interpreter's Python and NumPy headers. Done
# here, in the repository, because patching the venv's files would be undone by pip.

if(NOT Python3_FOUND OR NOT Python3_NumPy_FOUND)
  # -DPython3_EXECUTABLE=<venv>/bin/python selects the venv's interpreter
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development NumPy)
endif()

# the foreign include directories of an imported target are replaced by this interpreter's
function(venv_wheels_fix_target target)
  get_target_property(_dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
  if(NOT _dirs)
    return()
  endif()
  set(_kept "")
  set(_foreign FALSE)
  foreach(_dir IN LISTS _dirs)
    if(_dir MATCHES "^/opt/python/")
      set(_foreign TRUE)
    else()
      list(APPEND _kept "${_dir}")
    endif()
  endforeach()
  if(_foreign)
    list(APPEND _kept ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
    list(REMOVE_DUPLICATES _kept)
    set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
  endif()
endfunction()

# every imported target found so far in this directory (call after the find_package() calls)
function(venv_wheels_fix_imported_targets)
  get_property(_targets DIRECTORY "${CMAKE_CURRENT_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    venv_wheels_fix_target(${_target})
  endforeach()
endfunction()
