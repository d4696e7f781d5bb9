"""The math the rest builds on, with no project dependencies: SO(3) (:mod:`.so3`), motion
profiles and their integration (:mod:`.motion`), gyro buffers (:mod:`.gyro`), directed-graph
helpers (:mod:`.graph`) and the configuration error type (:mod:`.errors`). No rclpy."""
