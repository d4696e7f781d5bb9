"""``monitor``: errors of a distributed run, in the same files as ``bearing-pose simulate``.

Pairs every follower's ``estimate`` and the ``ground_truth`` at identical stamps on a
``record_every`` grid, measures them as the batch simulator does (:func:`watched`) and writes
``out_dir`` at ``t = duration``, when interrupted, or after :data:`END_PATIENCE_S` of waiting
for an estimate that does not come (a dead robot, named); ``bag``: a rosbag2 (:mod:`.recorder`).
"""
from __future__ import annotations

import sys
import time
from array import array
from collections import deque
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Empty

from .. import msg_defs as wire
from ..msg_defs import cdr
from ..core.errors import ScenarioError
from ..estimators.base import EstimateFrame
from ..metrics.results import PoseErrors, Recording, pose_errors, to_world
from ..scenario.model import Scenario
from ..studies.summary import format_summary, summarize, write_metrics_csv, write_summary_json
from .node_main import (declare, run_node, scenario_parameter, wall_timer,
                        warn_unknown_parameters)


# After the last row, the bag records until BAG_QUIET_S [s, wall] pass without a message
# (what was in flight is in), BAG_DRAIN_MAX_S at most.
BAG_QUIET_S, BAG_DRAIN_MAX_S = 0.5, 10.0
# How many recorded instants the monitor remembers to ignore their repeats (25.6 s at 10 Hz).
_RECENT = 256
# Wall time [s] the last truth waits for the estimates (they trail by ms; under load, a second).
END_PATIENCE_S = 10.0


def watched(scenario: Scenario) -> list[str]:
    """The agents whose ground truth the monitor reads: the followers, or the whole fleet when
    it moves (trajectories) or its method's estimates need aligning (not world poses)."""
    whole = scenario.moves or scenario.estimator().frame is not EstimateFrame.WORLD
    return [a.name for a in (scenario.agents if whole else scenario.followers)]


class MonitorNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        """``node_kwargs`` go to rclpy's Node (``context``, ``parameter_overrides``, ...)."""
        super().__init__('monitor', **node_kwargs)
        self.fleet = self.get_namespace().strip('/')   # the fleet namespace: its topics' prefix
        self.scenario = s = scenario_parameter(self)
        self.duration = declare(self, 'duration', 0.0, 'simulated time to record [s]; 0: the '
                                "scenario's", 0.0, 1e9) or s.duration
        self.out_dir = Path(declare(self, 'out_dir', 'results', 'output directory'))
        self.record_ns = int(round(declare(self, 'record_every', 0.1, 'metrics row interval '
                                           '[s]', 1e-3, 0.5) * 1e9))
        self.progress_every = declare(self, 'progress_every', max(self.duration / 10.0, 1.0),
                                      'progress line interval [s] of simulated time', 1e-3, 1e9)
        self.plots = declare(self, 'plots', True, 'write the PNG plots')
        bag = declare(self, 'bag', '', 'record the run into this new rosbag2 (MCAP) directory; '
                      'empty: no bag')
        warn_unknown_parameters(self)

        self.followers = [a.name for a in s.followers]   # every agent that estimates
        self.method = s.estimator()
        self.frame = self.method.frame
        # The method's fleet margins, on /diagnostics once per simulated second.
        self.pub_diag = self.create_publisher(wire.DiagnosticArray, wire.DIAGNOSTICS, 10)
        self.margins: dict[str, list[tuple[float, float]]] = {}
        self.watched = watched(s)
        self.whole = len(self.watched) == len(s.agents) and len(self.followers) < len(s.agents)
        self._truth: dict[int, dict[int, tuple]] = {}   # ns -> watched index -> (R, p)
        self._est: dict[int, dict[int, tuple]] = {}     # ns -> follower index -> (R̂, p̂)
        self.tracks: list[tuple[float, np.ndarray, np.ndarray]] = []  # (t, p, p̂ in world)
        self._recorded: deque[int] = deque(maxlen=_RECENT)   # older: below their minimum
        # t and the errors' columns per record, as flat doubles: 8 bytes a value, not a Python
        # object per row (issue 15's soak).
        self.rows = array('d')
        self.width = 1 + len(PoseErrors._fields) * len(self.followers)
        self._last_progress = -np.inf
        self.done = False
        self.finished = Future()  # completes once the outputs are written
        self.wall_start = time.monotonic()
        topic = partial(wire.topic, fleet=self.fleet)
        for k, name in enumerate(self.watched):
            self.create_subscription(wire.PoseStamped, topic(name, wire.GROUND_TRUTH),
                                     partial(self._on_pose, self._truth, k), wire.SIM_PUB_QOS,
                                     raw=True)
        for k, name in enumerate(self.followers):
            self.create_subscription(wire.PoseStamped, topic(name, wire.ESTIMATE),
                                     partial(self._on_pose, self._est, k),
                                     wire.ESTIMATE_RECORD_QOS, raw=True)
        self.recorder = None
        if bag:   # its subscriptions are in the ready check too: the bag starts at t = 0
            if Path(bag).exists():
                raise ScenarioError(f'parameter bag: {bag} exists; a bag is never overwritten. '
                                    'Fix: remove it or choose another path')
            from .recorder import BagRecorder
            from .wiring import recorded_topics
            self.recorder = BagRecorder(self, Path(bag), recorded_topics(s, self.fleet))
        # Ready once every reader has matched and every follower's t0 estimate is in (proof the
        # writer matched too: under load one matched 0.4 s late, past its history of 20).
        self.pub_ready = self.create_publisher(
            Empty, wire.fleet_topic(wire.MONITOR_READY, self.fleet), wire.LATCHED_QOS)
        self.ready_timer = wall_timer(self, 0.05, self.on_ready_check)
        self._end_seen: float | None = None   # wall time the last instant's truth was all in
        wall_timer(self, 1.0, self.on_end_check)

    def on_ready_check(self) -> None:
        if (all(sub.get_publisher_count() > 0 for sub in self.subscriptions)
                and len(self._est.get(0, {})) == len(self.followers)):
            self.pub_ready.publish(Empty())
            self.ready_timer.cancel()

    def on_end_check(self) -> None:
        """Finish without the estimates the last instant still lacks after
        :data:`END_PATIENCE_S` (their robots are gone), saying whose."""
        end = [ns for ns, truth in self._truth.items()
               if ns >= self.duration * 1e9 - 1e3 and len(truth) == len(self.watched)]
        if self.done or not end:
            return
        now = time.monotonic()
        if self._end_seen is None:
            self._end_seen = now
        elif now - self._end_seen >= END_PATIENCE_S:
            have = self._est.get(end[0], {})
            missing = [n for k, n in enumerate(self.followers) if k not in have]
            self.get_logger().warning(
                f'no estimate of t = {end[0] * 1e-9:g} s from {", ".join(missing)} after '
                f'{END_PATIENCE_S:g} s of wall time: finishing with the rows recorded (every '
                'instant with each follower\'s estimate)')
            self.finish()

    def _on_pose(self, table: dict, k: int, msg: bytes) -> None:
        try:
            ns = cdr.read_header(msg).ns
            if ns % self.record_ns or self.done or ns in self._recorded or (
                    len(self._recorded) == _RECENT and ns < min(self._recorded)):
                return  # only grid instants, once each (t0 estimates are announced repeatedly)
            _, R, p = cdr.decode_pose_raw(msg)
        except wire.WireError as exc:
            self.get_logger().warning(f'bad pose: {exc}', throttle_duration_sec=5.0)
            return
        table.setdefault(ns, {})[k] = (R, p)
        self._complete(ns)

    def _complete(self, ns: int) -> None:
        n, s = len(self.followers), self.scenario
        truth, est = self._truth.get(ns, {}), self._est.get(ns, {})
        if len(truth) < len(self.watched) or len(est) < n:
            return
        R = np.stack([truth[k][0] for k in range(len(self.watched))])
        p = np.stack([truth[k][1] for k in range(len(self.watched))])
        t = ns * 1e-9
        if self.whole:  # every agent: the leaders know their pose, the anchor is its frame
            R_hat, p_hat = R.copy(), p.copy()
            if s.anchor_index is not None:
                R_hat[s.anchor_index], p_hat[s.anchor_index] = np.eye(3), np.zeros(3)
            rows = [s.index[name] for name in self.followers]
            for k, i in enumerate(rows):
                R_hat[i], p_hat[i] = est[k]
            errors = pose_errors(self.frame, R, p, R_hat, p_hat, rows, anchor=s.anchor_index)
        else:
            R_hat = np.stack([est[k][0] for k in range(n)])
            p_hat = np.stack([est[k][1] for k in range(n)])
            errors = pose_errors(self.frame, R, p, R_hat, p_hat, anchor=s.anchor_index)
            if n == len(s.agents):
                self._fleet_margins(t, R_hat, p_hat)
        if s.moves and (self.whole or n == len(s.agents)):   # the whole fleet's estimates
            self.tracks.append((t, p, to_world(self.frame, R, p, R_hat, p_hat, s.anchor_index)[1]))
        self.rows.frombytes(np.concatenate([[t], *errors]).tobytes())
        del self._truth[ns], self._est[ns]
        self._recorded.append(ns)
        att, pos = errors.att_err, errors.pos_err
        if t - self._last_progress >= self.progress_every - 1e-9 or t >= self.duration - 1e-9:
            self._last_progress = t
            print(f'  t = {t:7.1f} / {self.duration:g} s   mean attitude error {att.mean():.2e} '
                  f'rad   mean position error {pos.mean():.2e} m', flush=True)
        if t >= self.duration - 1e-9:
            self.finish()

    def recording(self) -> Recording | None:
        if not self.rows:
            return None
        rows = np.array(self.rows).reshape(-1, self.width)
        rows = rows[np.argsort(rows[:, 0], kind='stable')]
        times = rows[:, 0].tolist()
        errors = [PoseErrors(*np.split(r, len(PoseErrors._fields))) for r in rows[:, 1:]]
        if not self.tracks:
            return Recording.of(times, self.followers, errors)
        tracks = sorted(self.tracks, key=lambda r: r[0])
        return Recording.of(times, self.followers, errors,
                            agents=[a.name for a in self.scenario.agents],
                            leaders=list(self.scenario.leaders),
                            p=[x[1] for x in tracks], p_hat=[x[2] for x in tracks])

    def _fleet_margins(self, t: float, R_hat: np.ndarray, p_hat: np.ndarray) -> None:
        """Record the method's fleet margins at ``t``; publish them once per second."""
        values = self.method.fleet_margins(self.scenario.fleet(), R_hat, p_hat)
        for key, value in values.items():
            self.margins.setdefault(key, []).append((t, value))
        if values and (len(self.margins[next(iter(values))]) - 1) % max(
                1, int(round(1e9 / self.record_ns))) == 0:
            self.pub_diag.publish(wire.diagnostics(
                f'{self.fleet}/monitor/fleet'.lstrip('/'), 'monitor', 'margins on the estimates',
                {'t_s': f'{t:.3f}', **{k: f'{v:.4g}' for k, v in values.items()}},
                wire.to_stamp(t)))

    def finish(self, interrupted: bool = False) -> None:
        """Write the outputs (once), from whatever has been recorded."""
        if self.done:
            self._close_bag()   # interrupted while the bag drained
            return
        self.done, s = True, self.scenario
        rec = self.recording()
        if rec is None:
            print('monitor: nothing recorded', file=sys.stderr)
            self._close_bag()
            self.finished.set_result(False)
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        summary = summarize(rec, scenario=s.name, source=s.source, mode='dds', step_s=s.step,
                            wall_time_s=round(time.monotonic() - self.wall_start, 3),
                            complete=bool(rec.t[-1] >= self.duration - 1e-9))
        write_metrics_csv(rec, self.out_dir / 'metrics.csv')
        write_summary_json(summary, self.out_dir / 'summary.json')
        from ..studies.plots import write_role_outputs
        write_role_outputs(rec, self.method.agent_groups(s.fleet()), self.out_dir,
                           title=f'{s.name} over DDS: errors by role', plot=self.plots)
        if self.plots:
            from ..studies.plots import TRAJECTORY_PLOT, plot_trajectories, write_plots
            write_plots(rec, self.out_dir)
            if rec.trajectories is not None:
                plot_trajectories(rec, self.out_dir / TRAJECTORY_PLOT,
                                  title=f'{s.name} over DDS: true and estimated trajectories')
        print(format_summary(summary), flush=True)
        for key, series in self.margins.items():
            t_min, v_min = min(series, key=lambda tv: tv[1])
            print(f'{key} on the estimates: min {v_min:.4g} (t = {t_min:g} s), last '
                  f'{series[-1][1]:.4g}', flush=True)
        if self.recorder is None or interrupted:
            self._close_bag()
            self.finished.set_result(True)
            return
        # The bag still takes what is in flight, until it stops coming.
        recorder, start = self.recorder, time.monotonic()

        def close_when_quiet() -> None:
            now = time.monotonic()
            if now - recorder.last_write < BAG_QUIET_S and now - start < BAG_DRAIN_MAX_S:
                return
            timer.cancel()
            self._close_bag()
            self.finished.set_result(True)
        timer = wall_timer(self, 0.1, close_when_quiet)

    def _close_bag(self) -> None:
        if self.recorder is not None and self.recorder.open:
            n = self.recorder.close()
            print(f'recorded {n} messages on {len(self.recorder.counts)} topics into '
                  f'{self.recorder.path}', flush=True)


def main(args: list[str] | None = None) -> None:
    # Interrupted, it still writes what it measured.
    raise SystemExit(run_node(MonitorNode, 'monitor', args, until=lambda node: node.finished,
                              on_interrupt=lambda node: node.finish(interrupted=True)))


if __name__ == '__main__':
    main()
