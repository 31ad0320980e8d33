from setuptools import setup

setup()  # everything is in setup.cfg; colcon (ament_python) runs this file
