"""Cooperative pose estimation for multi-agent systems from relative bearing measurements."""
