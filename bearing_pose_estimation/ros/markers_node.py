"""``fleet_markers``: the fleet in RViz without configuration (``bearing-pose run --rviz``):
every agent's ``estimate``, ``ground_truth`` and ``bearings`` on ``/visualization_marker_array``
(:mod:`msg_defs.rviz`) at ``rate`` [Hz]. RViz: Fixed Frame = the scenario's ``world_frame``.
"""
from __future__ import annotations

from functools import partial

import numpy as np
from rclpy.node import Node

from .. import msg_defs as wire
from ..msg_defs import cdr, rviz
from .node_main import declare, run_node, scenario_parameter, warn_unknown_parameters


class MarkersNode(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__('fleet_markers', **node_kwargs)
        fleet = self.get_namespace().strip('/')   # the fleet namespace: its topics' prefix
        self.scenario = s = scenario_parameter(self)
        rate = declare(self, 'rate', 10.0, 'marker rate [Hz] of the node clock', 0.1, 100.0)
        warn_unknown_parameters(self)
        method = s.estimator()
        self.names = [a.name for a in s.agents]
        self.by_id = {s.agent_id(n): n for n in self.names}
        self.world_frame = s.world_frame
        self.estimate_frame = wire.estimate_frame(method.frame.value, s.name, s.anchor,
                                                  s.world_frame)
        self.edges = [(a.name, nb.name) for a in s.agents for nb in a.neighbours]
        self.estimates: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.truth: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.bearings: dict[str, tuple[list[str], np.ndarray]] = {}
        self.t = 0.0
        for name in self.names:   # the messages as their serialised bytes (msg_defs/cdr.py)
            self.create_subscription(wire.PoseStamped, wire.topic(name, wire.ESTIMATE, fleet),
                                     partial(self._on_pose, self.estimates, name),
                                     wire.ESTIMATE_QOS, raw=True)
            self.create_subscription(wire.PoseStamped, wire.topic(name, wire.GROUND_TRUTH, fleet),
                                     partial(self._on_pose, self.truth, name), wire.SIM_PUB_QOS,
                                     raw=True)
            self.create_subscription(wire.PointCloud2, wire.topic(name, wire.BEARINGS, fleet),
                                     partial(self._on_bearings, name), wire.SENSOR_QOS, raw=True)
        # Relative: /visualization_marker_array, or /<fleet>/visualization_marker_array.
        self.pub = self.create_publisher(rviz.MarkerArray, rviz.MARKERS.lstrip('/'), 1)
        self.timer = self.create_timer(1.0 / rate, self.publish_markers)

    def _on_pose(self, table: dict, name: str, msg: bytes) -> None:
        try:
            t, R, p = cdr.decode_pose_raw(msg)
        except wire.WireError:
            return   # the estimators and the monitor count bad poses; nothing to draw
        table[name] = (R, p)
        self.t = max(self.t, t)

    def _on_bearings(self, name: str, msg: bytes) -> None:
        try:
            _, ids, b = cdr.decode_vectors_raw(msg)
        except wire.WireError:
            return
        known = [(self.by_id[i], row) for i, row in zip(ids.tolist(), b) if i in self.by_id]
        self.bearings[name] = ([n for n, _ in known], np.array([row for _, row in known]))

    def markers(self) -> rviz.MarkerArray:
        return rviz.encode_fleet_markers(self.t, self.names, self.estimate_frame,
                                         self.world_frame, self.estimates, self.truth,
                                         self.edges, self.bearings)

    def publish_markers(self) -> None:
        if self.estimates:
            self.pub.publish(self.markers())


def main(args: list[str] | None = None) -> None:
    raise SystemExit(run_node(MarkersNode, 'fleet_markers', args))


if __name__ == '__main__':
    main()
