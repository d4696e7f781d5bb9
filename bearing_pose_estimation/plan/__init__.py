"""The plan of a run, shared by :mod:`ros` and :mod:`cli`: its processes (:mod:`.processes`) and
their DDS environment (:mod:`.dds`). No rclpy."""
