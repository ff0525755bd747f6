# lifecycle_container: build a plugin's own ROS 2 interface packages
# (.msg/.srv/.action), against the ROS 2 prefix the PyPI wheels installed or a
# ROS install, into its Python wheel or its colcon install.
#
#   find_package(lifecycle_container REQUIRED)
#   lifecycle_container_add_interfaces(my_interfaces [DEPENDS other_interfaces ...])
#
# find_package finds this file through scikit-build-core's cmake.prefix entry
# point (a pip build), in <prefix>/share/lifecycle_container/cmake (the
# container's wheel installs it there, and so does its colcon build, through
# ament's CONFIG_EXTRAS).
#
# <dir> is an ordinary ament_cmake interface package (package.xml, a
# CMakeLists.txt calling rosidl_generate_interfaces): the same package a ROS
# workspace builds with colcon, so its types and their RIHS01 hashes are the
# ones a ROS install generates. It is configured and built as a project of its
# own (rosidl wants one package per project), installed into a staging prefix,
# and that tree installed into the wheel's data directory: the environment
# root, where the ROS wheels keep their own packages (lib/, share/, and the
# Python package under lib/pythonX.Y/site-packages), so pip records every file
# and `pip uninstall` removes them. Outside scikit-build-core (colcon, plain
# CMake) it goes into the install prefix. DEPENDS names packages added by
# earlier calls that this one's definitions use.
#
# A plugin's project (a pyproject.toml beside the top CMakeLists.txt that
# declares container.plugins entry points) is checked, or completed, when it
# finds this package:
#
# * built by scikit-build-core, it must be built through
#   build-backend = "container.build_backend", which adds the plugin's ament
#   index entries to its wheel: scikit_build_core.build alone would leave
#   them out (ros2 pkg list, ros2 component types would not see the plugin);
# * built by colcon or plain CMake, the rest of what its wheel would hold is
#   installed too: its Python packages ([tool.scikit-build] wheel.packages),
#   their distribution metadata (the entry points the container finds plugins
#   by) and, at the end of the install, its ament index entries (the package
#   marker and rclcpp_components, written by `container index`). Its
#   project() must then be named as its ROS package (the distribution's name,
#   - and . as _), and a package.xml of that <name> beside it makes it an
#   ament_cmake package to colcon (ament_package() is called for it), which
#   puts its prefix on AMENT_PREFIX_PATH.
#
# Needs CMake 3.21 and, in the build environment, the ROS build tools
# (ament_cmake, rosidl_default_generators and the message packages used):
# build with `pip install --no-build-isolation` in an environment set up by
# lifecycle-container (see its docs/guide/interfaces.md), or with colcon over
# a sourced ROS (docs/guide/install.md).

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

  # One argument, however many prefixes (colcon's workspace has one a package).
  list(JOIN prefixes "|" prefix_path)
  ExternalProject_Add(${package}
    LIST_SEPARATOR "|"
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
      "-DCMAKE_PREFIX_PATH=${prefix_path}"
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

# What the plugin project of pyproject.toml (if it is one) installs: see the top of this file.
function(_lifecycle_container_plugin_project)
  get_property(done GLOBAL PROPERTY _LIFECYCLE_CONTAINER_PLUGIN_PROJECT)
  set(pyproject "${CMAKE_SOURCE_DIR}/pyproject.toml")
  if(done OR NOT EXISTS "${pyproject}")
    return()
  endif()
  set_property(GLOBAL PROPERTY _LIFECYCLE_CONTAINER_PLUGIN_PROJECT ON)
  find_package(Python3 REQUIRED COMPONENTS Interpreter)
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" "${LIFECYCLE_CONTAINER_CMAKE_DIR}/dist_info.py" --plugin "${pyproject}"
    OUTPUT_VARIABLE plugin
    RESULT_VARIABLE failed
    ERROR_VARIABLE problem
  )
  if(failed)
    message(FATAL_ERROR "lifecycle_container: ${problem}")
  endif()
  if(NOT plugin)
    return()  # no container.plugins entry points: not a plugin
  endif()
  list(POP_FRONT plugin distribution package)
  if(DEFINED SKBUILD)
    if(NOT "$ENV{LIFECYCLE_CONTAINER_BUILD_BACKEND}")
      message(FATAL_ERROR
        "lifecycle_container: ${distribution} is a plugin (container.plugins entry points) built by "
        "scikit-build-core's own backend, so its wheel would carry no ament index entries: ros2 pkg list and "
        "ros2 component types would not see it. Build it through the container's backend (which builds with "
        "scikit-build-core and adds them): in pyproject.toml, [build-system] build-backend = "
        "\"container.build_backend\".")
    endif()
    return()
  endif()
  if(NOT CMAKE_PROJECT_NAME STREQUAL package)
    message(FATAL_ERROR
      "lifecycle_container: the plugin ${distribution} registers its node types as ${package}::<Type>, so its "
      "project must be named ${package} (the ROS package colcon builds, by its package.xml or else by the "
      "project's name): project(${package} ...), not project(${CMAKE_PROJECT_NAME} ...).")
  endif()
  set(site_packages "lib/python${Python3_VERSION_MAJOR}.${Python3_VERSION_MINOR}/site-packages")
  foreach(directory IN LISTS plugin)
    install(DIRECTORY "${CMAKE_SOURCE_DIR}/${directory}" DESTINATION "${site_packages}"
      PATTERN "__pycache__" EXCLUDE)
  endforeach()
  set(dist_info "${CMAKE_BINARY_DIR}/lifecycle_container_dist_info")
  file(REMOVE_RECURSE "${dist_info}")
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" "${LIFECYCLE_CONTAINER_CMAKE_DIR}/dist_info.py" "${dist_info}" "${pyproject}"
    COMMAND_ERROR_IS_FATAL ANY
  )
  install(DIRECTORY "${dist_info}/" DESTINATION "${site_packages}")
  message(STATUS "lifecycle_container: plugin ${distribution} (ROS package ${package}; Python: ${plugin})")
  # A package.xml beside it makes it a ROS package to colcon (ament_cmake),
  # which then puts its prefix on AMENT_PREFIX_PATH; a plain CMake package
  # gets no such thing from colcon.
  set(manifest "${CMAKE_SOURCE_DIR}/package.xml")
  if(EXISTS "${manifest}")
    file(READ "${manifest}" xml)
    string(REGEX MATCH "<name>[ \t\r\n]*([^< \t\r\n]+)" found "${xml}")
    if(NOT CMAKE_MATCH_1 STREQUAL package)
      message(FATAL_ERROR
        "lifecycle_container: ${manifest} names the package '${CMAKE_MATCH_1}', but the plugin ${distribution} "
        "registers its node types as ${package}::<Type>: make its <name> ${package}.")
    endif()
    set(ament ON)
  else()
    set(ament OFF)
    message(WARNING
      "lifecycle_container: the plugin ${distribution} has no package.xml beside its pyproject.toml, so colcon "
      "builds it as a plain CMake package and leaves its prefix off AMENT_PREFIX_PATH: ros2 pkg list, "
      "ros2 component types and launch_ros would not find ${package}. Add one whose <name> is ${package} and "
      "whose build_type is ament_cmake (see the container's docs/guide/colcon.md); "
      "this package then calls ament_package() for it.")
  endif()
  # The rest at the end of the top directory, once everything the plugin
  # imports is to be installed (its interface packages too). A deferred
  # call's arguments are read when it runs: the values go in now.
  cmake_language(EVAL CODE "
    cmake_language(DEFER DIRECTORY [[${CMAKE_SOURCE_DIR}]] CALL _lifecycle_container_finish_plugin
      [[${Python3_EXECUTABLE}]] [[${distribution}]] [[${site_packages}]] ${ament})")
endfunction()

# A macro: ament_package() and the find_package() it needs act on the project's scope.
macro(_lifecycle_container_finish_plugin python distribution site_packages ament)
  if(${ament} AND NOT _${PROJECT_NAME}_AMENT_PACKAGE)
    find_package(ament_cmake_core REQUIRED)
    ament_package()
  endif()
  _lifecycle_container_index_plugin("${python}" "${distribution}" "${site_packages}")
endmacro()

# At the end of the install: the plugin's ament index entries (its package
# marker, unless ament_package() installs it, and rclcpp_components), written
# by the container from the installed plugin.
function(_lifecycle_container_index_plugin python distribution site_packages)
  install(CODE "
    set(ENV{PYTHONPATH} \"\${CMAKE_INSTALL_PREFIX}/${site_packages}:\$ENV{PYTHONPATH}\")
    set(ENV{LD_LIBRARY_PATH} \"\${CMAKE_INSTALL_PREFIX}/lib:\$ENV{LD_LIBRARY_PATH}\")
    execute_process(
      COMMAND \"${python}\" -m container index --quiet --prefix \"\${CMAKE_INSTALL_PREFIX}\"
        --distribution \"${distribution}\"
      COMMAND_ERROR_IS_FATAL ANY
    )
  ")
endfunction()

if(CMAKE_FIND_PACKAGE_NAME STREQUAL "lifecycle_container")
  _lifecycle_container_plugin_project()
endif()
