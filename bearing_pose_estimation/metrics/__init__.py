"""What a run is measured by (:mod:`.results`): the pose errors after each estimate frame's
alignment and a run's recording, for the simulators, the monitor and the studies. No rclpy."""
