"""TUM trajectories from a run's bag (``bearing-pose export-tum DIR``) for evo: per agent,
``<agent>_estimate.tum`` (estimate frame), ``<agent>_truth.tum``: ``t x y z qx qy qz qw``, t
the message stamp [s] (a stamp sent twice, once)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import ScenarioError

# What each file holds: the topic (relative to the agent) and the file name's suffix.
TRACKS = {'estimate': 'estimate', 'ground_truth': 'truth'}


def read_tracks(bag: Path) -> dict[tuple[str, str], NDArray[np.float64]]:
    """``(agent, track) -> (n, 8)`` rows ``t x y z qx qy qz qw`` of every PoseStamped on an
    agent's ``estimate`` and ``ground_truth`` topics in the rosbag2 ``bag``, by stamp."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    if not (bag / 'metadata.yaml').is_file():
        raise ScenarioError(f'{bag}: not a finished rosbag2 (no metadata.yaml). Fix: record one '
                            'with `bearing-pose run --record`')
    typestore = get_typestore(Stores.ROS2_JAZZY)
    rows: dict[tuple[str, str], dict[int, list[float]]] = {}
    with Reader(bag) as reader:
        wanted = [c for c in reader.connections
                  if c.msgtype == 'geometry_msgs/msg/PoseStamped'
                  and c.topic.count('/') == 2 and c.topic.rsplit('/', 1)[1] in TRACKS]
        for connection, _, raw in reader.messages(connections=wanted):
            msg: Any = typestore.deserialize_cdr(raw, connection.msgtype)
            _, agent, track = connection.topic.split('/')
            ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            p, q = msg.pose.position, msg.pose.orientation
            rows.setdefault((agent, track), {}).setdefault(
                ns, [ns * 1e-9, p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    return {key: np.array([by_ns[ns] for ns in sorted(by_ns)]) for key, by_ns in rows.items()}


def export_tum(bag: Path, out_dir: Path) -> list[Path]:
    """Write every agent's trajectories found in ``bag`` into ``out_dir``; the files written."""
    tracks = read_tracks(bag)
    if not tracks:
        raise ScenarioError(f'{bag}: no estimate or ground_truth topic in it')
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for (agent, track), rows in sorted(tracks.items()):
        path = out_dir / f'{agent}_{TRACKS[track]}.tum'
        np.savetxt(path, rows, fmt='%.9f %.12g %.12g %.12g %.12g %.12g %.12g %.12g',
                   header=f'{agent} {track} from {bag}: t x y z qx qy qz qw')
        written.append(path)
    return written
