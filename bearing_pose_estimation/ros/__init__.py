"""The ROS 2 side: thin nodes over the core (estimator, several estimators in one process,
simulator, monitor), their shared life cycle (:mod:`.node_main`) and the executor that spins
them (:mod:`.executor`). The wire format is ``msg_defs``."""
