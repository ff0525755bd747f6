# lifecycle_container: build ROS 2 interface packages (.msg/.srv/.action) into a
# Python wheel, against the ROS 2 prefix the PyPI wheels installed.
#
#   find_package(lifecycle_container REQUIRED)       # found through scikit-build-core's
#                                                     # cmake.prefix entry point
#   lifecycle_container_add_interfaces(my_interfaces [DEPENDS other_interfaces ...])
#
# <dir> is an ordinary ament_cmake interface package (package.xml, a
# CMakeLists.txt calling rosidl_generate_interfaces): the same package a ROS
# workspace builds with colcon, so its types and their RIHS01 hashes are the
# ones a ROS install generates. It is configured and built as a project of its
# own (rosidl wants one package per project), installed into a staging prefix,
# and that tree installed into the wheel's data directory: the environment
# root, where the ROS wheels keep their own packages (lib/, share/, and the
# Python package under lib/pythonX.Y/site-packages), so pip records every file
# and `pip uninstall` removes them. DEPENDS names packages added by earlier
# calls that this one's definitions use.
#
# Needs CMake 3.21 and, in the build environment, the ROS build tools
# (ament_cmake, rosidl_default_generators and the message packages used):
# build with `pip install --no-build-isolation` in an environment set up by
# lifecycle-container (see its docs/guide/interfaces.md).

include_guard(GLOBAL)
include(ExternalProject)

set(LIFECYCLE_CONTAINER_CMAKE_DIR "${CMAKE_CURRENT_LIST_DIR}")

# The ROS prefixes to build against: every prefix on the interpreter's path
# that holds an ament index. With pip's build isolation the build tools live
# in an overlay prefix, not in the environment; without it both are the
# environment.
function(_lifecycle_container_ros_prefixes out)
  find_package(Python3 REQUIRED COMPONENTS Interpreter)
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" -c [=[
import os, sys, sysconfig
prefixes = []
for site in [*sys.path, sysconfig.get_path("purelib")]:
    prefix = os.path.abspath(os.path.join(site, "..", "..", ".."))  # <prefix>/lib/pythonX.Y/site-packages
    if site.endswith("site-packages") and prefix not in prefixes \
            and os.path.isdir(os.path.join(prefix, "share", "ament_index")):
        prefixes.append(prefix)
print(";".join(prefixes), end="")
]=]
    OUTPUT_VARIABLE prefixes
    COMMAND_ERROR_IS_FATAL ANY
  )
  if(NOT prefixes)
    message(FATAL_ERROR
      "lifecycle_container: no ROS 2 prefix found for ${Python3_EXECUTABLE}: install the ROS 2 wheels "
      "(ros-<distro>-rosidl-default-generators and the message packages used) and build without "
      "build isolation (pip install --no-build-isolation)")
  endif()
  set(${out} "${prefixes}" PARENT_SCOPE)
endfunction()

function(lifecycle_container_add_interfaces dir)
  cmake_parse_arguments(PARSE_ARGV 1 arg "" "" "DEPENDS")
  get_filename_component(source "${dir}" ABSOLUTE BASE_DIR "${CMAKE_CURRENT_SOURCE_DIR}")
  if(NOT EXISTS "${source}/package.xml")
    message(FATAL_ERROR "lifecycle_container_add_interfaces: ${source} has no package.xml")
  endif()
  get_filename_component(package "${source}" NAME)
  _lifecycle_container_ros_prefixes(ros_prefixes)
  find_package(Python3 REQUIRED COMPONENTS Interpreter)

  set(stage_root "${CMAKE_BINARY_DIR}/lifecycle_container_stage")
  set(prefixes ${ros_prefixes})
  foreach(dependency IN LISTS arg_DEPENDS)
    list(PREPEND prefixes "${stage_root}/${dependency}")
  endforeach()
  string(REPLACE ";" ":" ament_prefix_path "${prefixes}")
  # ament's CMake reads AMENT_PREFIX_PATH from the environment (resource index
  # look-ups of the type support generators), at configure and build time.
  set(env "${CMAKE_COMMAND}" -E env "AMENT_PREFIX_PATH=${ament_prefix_path}")
  set(stage "${stage_root}/${package}")

  ExternalProject_Add(${package}
    SOURCE_DIR "${source}"
    BINARY_DIR "${CMAKE_BINARY_DIR}/lifecycle_container_build/${package}"
    DEPENDS ${arg_DEPENDS}
    CONFIGURE_COMMAND ${env} "${CMAKE_COMMAND}"
      -G "${CMAKE_GENERATOR}"
      "-DCMAKE_MAKE_PROGRAM=${CMAKE_MAKE_PROGRAM}"
      # -O1: measured here, -O2 costs ~40% more compile time (fastcdr C++
      # templates) for no gain that matters to small messages.
      "-DCMAKE_BUILD_TYPE=Release"
      "-DCMAKE_C_FLAGS_RELEASE=-O1 -DNDEBUG"
      "-DCMAKE_CXX_FLAGS_RELEASE=-O1 -DNDEBUG"
      "-DCMAKE_INSTALL_PREFIX=${stage}"
      "-DCMAKE_PREFIX_PATH=${prefixes}"
      "-DPython3_EXECUTABLE=${Python3_EXECUTABLE}"
      # The wheels' exported targets name another machine's Python: see ros_wheels.cmake.
      "-DCMAKE_PROJECT_INCLUDE=${LIFECYCLE_CONTAINER_CMAKE_DIR}/ros_wheels.cmake"
      -DBUILD_TESTING=OFF
      -S <SOURCE_DIR> -B <BINARY_DIR>
    BUILD_COMMAND ${env} "${CMAKE_COMMAND}" --build <BINARY_DIR>
    INSTALL_COMMAND "${CMAKE_COMMAND}" --install <BINARY_DIR>
    # Rebuild when a .msg/.srv/.action, package.xml or CMakeLists.txt changes.
    BUILD_ALWAYS ON
  )

  # Under scikit-build-core: the wheel's data directory (the environment
  # root once installed). Elsewhere (colcon, plain CMake): the install prefix.
  if(DEFINED SKBUILD_DATA_DIR)
    set(destination "${SKBUILD_DATA_DIR}")
  else()
    set(destination ".")
  endif()
  install(DIRECTORY "${stage}/" DESTINATION "${destination}" USE_SOURCE_PERMISSIONS)
endfunction()
