"""The math the rest builds on, with no project dependencies (SO(3), motion, sample buffers,
graphs, angle rigidity, the configuration error type). No rclpy."""
