"""Cooperative pose estimation for multi-agent systems from relative bearing measurements."""

# The package version: package.xml and setup.py say the same (test_packaging.py checks).
__version__ = '0.1.0'
