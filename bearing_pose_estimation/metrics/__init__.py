"""What a run is measured by: the pose errors after each estimate frame's alignment and the
recording of a run (:mod:`.results`), below the simulators, the monitor and the studies that
all measure with them. No rclpy."""
