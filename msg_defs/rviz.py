"""What RViz and TF users see of a fleet: the estimate as a TF transform, and the fleet as one
MarkerArray (RViz cannot draw FLOAT64 point clouds), ids stable so each replaces the last:
``estimate``, ``label``, ``truth``, ``edges`` and ``bearings`` (each measured ray from p̂_i along
R̂_i b_ij, as long as the estimated distance to j, else 1 m)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from geometry_msgs.msg import Point, TransformStamped
from numpy.typing import NDArray
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from bearing_pose_estimation.core import so3

from . import to_stamp

Array = NDArray[np.float64]
MARKERS = '/visualization_marker_array'   # the name RViz users look for
MARKER_NAMESPACES = ('estimate', 'label', 'truth', 'edges', 'bearings')
_BLUE, _GREEN = ColorRGBA(r=0.1, g=0.4, b=1.0, a=1.0), ColorRGBA(r=0.1, g=0.8, b=0.2, a=0.6)
_GREY, _YELLOW = ColorRGBA(r=0.6, g=0.6, b=0.6, a=0.8), ColorRGBA(r=1.0, g=0.85, b=0.0, a=0.9)
_WHITE = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)


def encode_transform(t: float, parent: str, child: str, R: Array, p: Array) -> TransformStamped:
    """The pose ``(R, p)`` of ``child`` in ``parent`` as a TF transform (REP-105: parent →
    child, e.g. ``world`` → ``agent_3/base_link``)."""
    msg = TransformStamped(child_frame_id=child)
    msg.header.stamp, msg.header.frame_id = to_stamp(t), parent
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = map(float, p)
    rot.x, rot.y, rot.z, rot.w = map(float, so3.to_quat(R))
    return msg


def _marker(t: float, frame: str, ns: str, k: int, kind: int, color: ColorRGBA) -> Marker:
    m = Marker(ns=ns, id=k, type=kind, action=Marker.ADD, color=color)
    m.header.stamp, m.header.frame_id = to_stamp(t), frame
    return m


def _arrow(m: Marker, R: Array, p: Array) -> Marker:
    m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, p)
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = map(float, so3.to_quat(R))
    m.scale.x, m.scale.y, m.scale.z = 0.4, 0.06, 0.06
    return m


def _point(v: Array) -> Point:
    return Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def encode_fleet_markers(t: float, names: Sequence[str], estimate_frame: str, world_frame: str,
                         estimates: Mapping[str, tuple[Array, Array]],
                         truth: Mapping[str, tuple[Array, Array]],
                         edges: Sequence[tuple[str, str]],
                         bearings: Mapping[str, tuple[Sequence[str], Array]]) -> MarkerArray:
    """The fleet at ``t``: ``estimates``, ``truth``: agent -> (R, p); ``edges``: (i, j);
    ``bearings``: i -> (the agents j it measured, their body bearings as rows)."""
    out = MarkerArray()
    for k, name in enumerate(names):
        if name in estimates:
            R, p = estimates[name]
            out.markers.append(_arrow(_marker(t, estimate_frame, 'estimate', k, Marker.ARROW,
                                              _BLUE), R, p))
            label = _marker(t, estimate_frame, 'label', k, Marker.TEXT_VIEW_FACING, _WHITE)
            label.pose.position = _point(np.asarray(p, dtype=float) + (0.0, 0.0, 0.3))
            label.scale.z, label.text = 0.2, name
            out.markers.append(label)
        if name in truth:
            R, p = truth[name]
            out.markers.append(_arrow(_marker(t, world_frame, 'truth', k, Marker.ARROW, _GREEN),
                                      R, p))
    lines = _marker(t, estimate_frame, 'edges', 0, Marker.LINE_LIST, _GREY)
    lines.scale.x = 0.02
    for i, j in edges:
        if i in estimates and j in estimates:
            lines.points += [_point(estimates[i][1]), _point(estimates[j][1])]
    rays = _marker(t, estimate_frame, 'bearings', 0, Marker.LINE_LIST, _YELLOW)
    rays.scale.x = 0.015
    for i, (seen, b) in bearings.items():
        if i not in estimates:
            continue
        R, p = estimates[i]
        for j, b_ij in zip(seen, np.asarray(b, dtype=float)):
            length = float(np.linalg.norm(estimates[j][1] - p)) if j in estimates else 1.0
            rays.points += [_point(p), _point(p + length * (R @ b_ij))]
    out.markers += [lines, rays]
    return out
