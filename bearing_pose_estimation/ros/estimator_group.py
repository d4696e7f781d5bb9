"""``estimators``: several agents' estimator nodes in one process, spun by one executor.

Each agent keeps its own node, parameter file (``--params-dir DIR``: ``DIR/<agent>.yaml``) and
remaps, exactly as a separate ``estimator`` process: only the interpreter and the DDS
participant are shared. ``--leader A`` remaps agent A's ``known_pose`` to ``ground_truth``.

With ``use_sim_time``, the process reads ``/clock`` once (:func:`share_clock`); the first
agent's ``use_sim_time`` rules them all. The agents' steps run together (:mod:`.step_batch`;
``--separate-steps``: each on its own). ``BEARING_POSE_CPU_SPLIT=1``: the last log lines say
where the CPU went (:meth:`.step_batch.StepBatch.cpu_split`; ~0.1 % of a core per agent).
"""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import rclpy.logging
from rclpy.clock import ROSClock
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from .. import msg_defs as wire
from .estimator_node import EstimatorNode
from .node_main import run_node
from .step_batch import StepBatch
from ..core.errors import ScenarioError

CPU_SPLIT_ENV = 'BEARING_POSE_CPU_SPLIT'


def parse_args(argv: list[str]) -> argparse.Namespace:
    """An ``estimators`` command line (``argv[0]``: the program), ROS arguments left out."""
    parser = argparse.ArgumentParser(prog='estimators', description=__doc__.split('\n')[0])
    parser.add_argument('--params-dir', required=True, type=Path,
                        help='folder with one <agent>.yaml parameter file per agent')
    parser.add_argument('--leader', action='append', default=[], metavar='AGENT',
                        help='an agent whose known_pose is remapped to ground_truth')
    parser.add_argument('--fleet-namespace', default='', metavar='NS',
                        help='the fleet namespace: nodes in /NS/<agent>, the clock on /NS/clock')
    parser.add_argument('--separate-steps', action='store_true',
                        help='each agent steps on its own instead of in one call with the '
                        "others' (for comparisons; the results are the same)")
    parser.add_argument('agents', nargs='+', help='the agents this process runs')
    return parser.parse_args(remove_ros_args(argv)[1:])


def _nodes(opts: argparse.Namespace, batch: StepBatch | None) -> list[EstimatorNode]:
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
        nodes.append(EstimatorNode(batch, namespace=f'{ns}/{agent}', cli_args=cli))
    share_clock(nodes)
    return nodes


def share_clock(nodes: Sequence[Node]) -> None:
    """One ``/clock`` subscription for nodes that share a process: under ``use_sim_time`` each
    node's time source subscribes on its own, so every tick would reach the process once per
    node (a message costs ~40-90 µs here, BENCHMARKS.md). The first node's time source drives
    the clocks of the others that use simulated time; theirs let go of the topic. (rclpy 7.1.6
    keeps a node's time source in ``Node._time_source``, the wheels' pinned version.)"""
    lead = nodes[0]
    if not lead.get_parameter('use_sim_time').value:
        return
    for node in nodes[1:]:
        clock = node.get_clock()
        if node.get_parameter('use_sim_time').value and isinstance(clock, ROSClock):
            node._time_source.detach_node()
            lead._time_source.attach_clock(clock)


def main(args: list[str] | None = None) -> None:
    argv = sys.argv if args is None else args
    opts = parse_args(argv)
    batch = (None if opts.separate_steps or len(opts.agents) < 2
             else StepBatch(time_callbacks=os.environ.get(CPU_SPLIT_ENV) == '1'))

    def report(_node: Node) -> None:
        if batch is not None:
            logger = rclpy.logging.get_logger('estimators')
            logger.info(f'steps run together: {batch.summary()}')
            logger.info(f'CPU: {batch.cpu_split()}')

    raise SystemExit(run_node(lambda: _nodes(opts, batch), 'estimators', argv,
                              on_interrupt=report,
                              after_spin=None if batch is None else batch.settle))


if __name__ == '__main__':
    main()
