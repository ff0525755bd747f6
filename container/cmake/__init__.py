"""CMake files for building ROS 2 interface packages against the PyPI wheels.

Not Python: this package only makes the directory installable and findable.
scikit-build-core puts it on ``CMAKE_PREFIX_PATH`` through the
``cmake.prefix`` entry point, so a plugin's ``CMakeLists.txt`` can say
``find_package(lifecycle_container REQUIRED)`` and then
``lifecycle_container_add_interfaces(<package dir>)``.
"""

__all__: list[str] = []
