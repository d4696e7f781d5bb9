"""Simulation, on the scenario's one truth model (:mod:`scenario.truth`): the noise models
(:mod:`.noise`), the simulator node's sampled world (:mod:`.world`), the batch simulator
(:mod:`.batch`) and the distributed system without DDS (:mod:`.netsim`). No rclpy."""
