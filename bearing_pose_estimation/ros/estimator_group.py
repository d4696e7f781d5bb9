"""``estimators``: several agents' estimator nodes in one process, spun by one executor.

Each agent keeps its own node (namespace ``/<agent>``, or ``/<fleet>/<agent>`` with
``--fleet-namespace``), its own parameter file and its own
remaps, exactly as a separate ``estimator`` process would have: only the process (a Python
interpreter and a DDS participant) is shared.

    estimators --params-dir DIR [--leader A ...] AGENT [AGENT ...] [--ros-args ...]

``DIR/<agent>.yaml`` is each agent's parameter file (what ``bearing-pose run`` writes);
``--leader A`` (repeatable) remaps agent A's ``known_pose`` to ``ground_truth`` (simulation).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rclpy.utilities import remove_ros_args

from .. import msg_defs as wire
from .estimator_node import EstimatorNode
from .node_main import run_node
from ..core.errors import ScenarioError


def parse_args(argv: list[str]) -> argparse.Namespace:
    """An ``estimators`` command line (``argv[0]``: the program), ROS arguments left out."""
    parser = argparse.ArgumentParser(prog='estimators', description=__doc__.split('\n')[0])
    parser.add_argument('--params-dir', required=True, type=Path,
                        help='folder with one <agent>.yaml parameter file per agent')
    parser.add_argument('--leader', action='append', default=[], metavar='AGENT',
                        help='an agent whose known_pose is remapped to ground_truth')
    parser.add_argument('--fleet-namespace', default='', metavar='NS',
                        help='the fleet namespace: nodes in /NS/<agent>, the clock on /NS/clock')
    parser.add_argument('agents', nargs='+', help='the agents this process runs')
    return parser.parse_args(remove_ros_args(argv)[1:])


def _nodes(opts: argparse.Namespace) -> list[EstimatorNode]:
    nodes = []
    for agent in opts.agents:
        params = opts.params_dir / f'{agent}.yaml'
        if not params.is_file():
            raise ScenarioError(f'{params}: no parameter file for {agent}. Fix: write it '
                                '(bearing-pose run does) or fix --params-dir')
        cli = ['--ros-args', '--params-file', str(params)]
        if agent in opts.leader:
            cli += ['-r', 'known_pose:=ground_truth']
        ns = wire.fleet_topic('', opts.fleet_namespace)   # '/team_a', or '' for none
        if ns:
            cli += ['-r', f'{wire.CLOCK}:={wire.fleet_topic(wire.CLOCK, ns)}']
        nodes.append(EstimatorNode(namespace=f'{ns}/{agent}', cli_args=cli))
    return nodes


def main(args: list[str] | None = None) -> None:
    argv = sys.argv if args is None else args
    opts = parse_args(argv)
    raise SystemExit(run_node(lambda: _nodes(opts), 'estimators', argv))


if __name__ == '__main__':
    main()
