# colcon runs this. container.colcon's commands install the data files of
# setup.cfg plus the plugin's rclcpp_components entry in the ament index (ros2
# component types): its node types, listed by importing the built plugin.
from setuptools import setup

from container.colcon import cmdclass

setup(cmdclass=cmdclass())
