"""The command line: ``bearing-pose`` (:mod:`.main`) and the process launcher of its ``run``
(:mod:`.launch`, no rclpy)."""
