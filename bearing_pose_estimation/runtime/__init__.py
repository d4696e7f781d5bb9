"""The one agent runtime: an agent's logic without ROS, configured by its method's
declarations (:class:`.agent.AgentRuntime`), with the table of what each agent reads
(:mod:`.table`), the steps of several agents in one call (:mod:`.together`), link faults
(:mod:`.faults`) and the health report (:mod:`.health`)."""
