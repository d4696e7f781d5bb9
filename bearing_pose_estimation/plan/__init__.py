"""The plan of a run, shared by the nodes (:mod:`ros`) and the command line (:mod:`cli`): what
processes a run starts and with which parameters (:mod:`.processes`), and the DDS environment
they share (:mod:`.dds`). No rclpy."""
