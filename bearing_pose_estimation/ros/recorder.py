"""A rosbag2 of a run (``bearing-pose run --record``), written with `rosbags` (the PyPI ROS wheels
have no ``ros2 bag``): each message's CDR bytes as they came, stamped with the node's clock (as
``ros2 bag record --use-sim-time``), in MCAP (:mod:`studies.tum` reads it).
"""
from __future__ import annotations

import time
from collections import Counter
from functools import partial
from pathlib import Path

from rclpy.node import Node
from rclpy.subscription import Subscription
from rosbags.interfaces import Connection
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .. import msg_defs as wire


class BagRecorder:
    """Records ``topics`` (name, message class) on ``node`` into the new bag ``path``."""

    def __init__(self, node: Node, path: Path, topics: list[tuple[str, type]]) -> None:
        typestore = get_typestore(Stores.ROS2_JAZZY)
        self.path, self.node = path, node
        self.counts: Counter[str] = Counter()
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.last_write = time.monotonic()   # wall time of the newest message written
        self.subscriptions: list[Subscription] = []
        for topic, msg_type in topics:
            connection = self.writer.add_connection(topic, wire.type_name(msg_type),
                                                    typestore=typestore)
            self.subscriptions.append(node.create_subscription(
                msg_type, topic, partial(self._write, connection), wire.RECORD_QOS, raw=True))
        self.open = True

    def _write(self, connection: Connection, data: bytes) -> None:
        if self.open:
            self.writer.write(connection, self.node.get_clock().now().nanoseconds, data)
            self.counts[connection.topic] += 1
            self.last_write = time.monotonic()

    def close(self) -> int:
        """Finish the bag (its metadata.yaml); returns the number of messages written."""
        if self.open:
            self.open = False
            self.writer.close()
        return sum(self.counts.values())
