# Make CMake targets exported by the ROS 2 PyPI wheels usable here.
#
# The wheels were built in a manylinux container: their exported
# `*__rosidl_generator_py` targets name include directories under
# /opt/python/... (that container's CPython and NumPy), which do not exist on
# this machine, and CMake refuses imported targets with missing include
# directories at generate time. Those targets are created by find_package()
# calls made deep inside rosidl_generate_interfaces(), so the fix runs deferred,
# at the end of configuring the calling directory: drop the foreign paths and
# add this interpreter's Python and NumPy include directories instead.
# Needs CMake 3.21 (IMPORTED_TARGETS, cmake_language(DEFER)). Included into an
# interface package's build by lifecycle_container_add_interfaces through
# CMAKE_PROJECT_INCLUDE (after its project() call), so the package itself
# stays an ordinary ament_cmake package; harmless where the targets are sound
# (a ROS install from source or Debian packages).
include_guard(GLOBAL)

function(_ros_wheels_fix_dir dir)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
  get_property(targets DIRECTORY "${dir}" PROPERTY IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(includes ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT includes OR NOT includes MATCHES "/opt/python/")
      continue()
    endif()
    list(FILTER includes EXCLUDE REGEX "^/opt/python/")
    list(APPEND includes ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
    set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${includes}")
  endforeach()
  get_property(subdirs DIRECTORY "${dir}" PROPERTY SUBDIRECTORIES)
  foreach(subdir IN LISTS subdirs)
    _ros_wheels_fix_dir("${subdir}")
  endforeach()
endfunction()

function(_ros_wheels_fix_imported_targets)
  _ros_wheels_fix_dir("${CMAKE_SOURCE_DIR}")
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _ros_wheels_fix_imported_targets)
