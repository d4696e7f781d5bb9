"""The steps of the agents that share an ``estimators`` process, run together in one call
(:mod:`runtime.together` says why; ``bench/covariance_cost.py``, ``bench/de_carli_cost.py``).

An agent whose step is ready asks this batch; once the executor has handled every message
already queued (the simulator sends each instant's samples in one burst), the batch runs the
steps of every agent that asked, waiting at most :data:`WAIT_S` for the others. Second-round
replies go out at once; only the step waits for the batch.

The rclpy EventsExecutor of the pinned wheels has no guard conditions, and nothing tells
whether its queue is empty: :meth:`StepBatch.settle` spins it without waiting until a spin
runs no callback of the process's subscriptions (counted by :meth:`StepBatch.counted`).
"""
from __future__ import annotations

import re
import resource
import time
from collections.abc import Callable
from typing import Any, Protocol

from rclpy.executors import Executor

from ..runtime.agent import AgentRuntime
from ..runtime.together import advance_together


class Member(Protocol):
    """What the batch needs of an agent that runs its steps in it (the estimator node): its
    name and runtime, and what goes before and after each of its steps."""

    agent: str
    rt: AgentRuntime | None

    def before_step(self) -> None: ...

    def after_step(self) -> None: ...

# Spins before the steps run even if messages keep coming (a process that never sees an
# empty queue still steps), and the longest wait [s] for an agent due at the same instant
# (one that never gets its inputs delays the others' steps this much, once).
MAX_SPINS = 64
WAIT_S = 0.002

# A StepBatch.cpu_split line with its callbacks timed, as the process logs it.
_PART = r'(\S+) s \((\d+) [a-z-]+, \S+ µs each\)'
_CPU_LINE = re.compile(rf'CPU: messages {_PART}, steps {_PART}, around them '
                       rf'\(readiness, publishing\) {_PART}, executor and the rest (\S+) s; '
                       r'other threads \(DDS\) (\S+) s')


class StepBatch:
    """Steps asked for by the nodes of one process, run together by :meth:`settle`."""

    def __init__(self, time_callbacks: bool = False) -> None:
        self.nodes: list[Member] = []           # every node that runs its steps here
        self.pending: dict[Member, None] = {}   # in the order they asked
        self.callbacks = 0   # subscription callbacks run so far
        self.rounds = 0      # calls of advance_together: one step of each ready agent
        self.steps = 0
        # CPU time [ns] of this thread in the steps' calls, in the rest of the flushes (what
        # each step publishes) and, if ``time_callbacks``, in the callbacks: where an
        # estimator process's time goes (:meth:`cpu_split`). Reading the thread's clock costs
        # ~1 µs: twice per callback is 0.1 % of a core per agent, so on demand only.
        self.time_callbacks = time_callbacks
        self.cpu_callbacks = 0
        self.cpu_steps = 0
        self.cpu_flush = 0

    def join(self, node: Member) -> None:
        """``node`` runs its steps here."""
        self.nodes.append(node)

    def summary(self) -> str:
        """How many steps ran together, on average."""
        return (f'{self.steps} steps of {len(self.nodes)} agents in {self.rounds} rounds '
                f'({self.steps / max(self.rounds, 1):.1f} agents per round)')

    def cpu_split(self) -> str:
        """Where this process's CPU went so far: the main thread's callbacks (if timed), steps,
        readiness and publishing (the rest of the flushes) and the remainder (the executor,
        the callbacks if not timed), and the other threads (DDS)."""
        main = time.thread_time_ns()
        usage = resource.getrusage(resource.RUSAGE_SELF)
        total = round((usage.ru_utime + usage.ru_stime) * 1e9)
        rest = main - self.cpu_callbacks - self.cpu_steps - self.cpu_flush

        def part(ns: int, count: int, what: str) -> str:
            return f'{ns * 1e-9:.2f} s ({count} {what}, {ns * 1e-3 / max(count, 1):.0f} µs each)'

        messages = (part(self.cpu_callbacks, self.callbacks, 'callbacks')
                    if self.time_callbacks else 'not timed')
        return (f'messages {messages}, '
                f'steps {part(self.cpu_steps, self.steps, "agent-steps")}, '
                f'around them (readiness, publishing) '
                f'{part(self.cpu_flush, self.steps, "agent-steps")}, '
                f'executor and the rest {rest * 1e-9:.2f} s; '
                f'other threads (DDS) {(total - main) * 1e-9:.2f} s')

    def counted(self, callback: Callable[[Any], None]) -> Callable[[Any], None]:
        """``callback``, counting its runs (what tells :meth:`settle` the queue is empty)
        and, with ``time_callbacks``, their CPU time."""
        if not self.time_callbacks:
            def count(msg: Any) -> None:
                self.callbacks += 1
                callback(msg)
            return count

        def run(msg: Any) -> None:
            self.callbacks += 1
            start = time.thread_time_ns()
            try:
                callback(msg)
            finally:
                self.cpu_callbacks += time.thread_time_ns() - start
        return run

    def request(self, node: Member) -> None:
        """``node`` may have a step ready: :meth:`settle` runs it."""
        self.pending[node] = None

    def settle(self, executor: Executor) -> None:
        """After a spin: while steps are asked for, handle what is queued and wait (at most
        :data:`WAIT_S`) for the agents due at the same instant, then run the steps."""
        spins, started = 0, time.monotonic()
        while self.pending:
            seen = self.callbacks
            executor.spin_once(timeout_sec=0.0)
            spins += 1
            if self.callbacks != seen and spins < MAX_SPINS:
                continue
            left = started + WAIT_S - time.monotonic()
            if left > 0.0 and spins < MAX_SPINS and self._someone_due():
                executor.spin_once(timeout_sec=left)
                continue
            self.flush()

    def _someone_due(self) -> bool:
        """Whether an agent of this process is at the instant of the earliest ready step
        without its own step ready, and waits for something from outside the process: its
        inputs are on their way (a simulator sends an instant's samples agent after agent).
        One that waits for another agent of the process waits for this round's steps."""
        ready: list[AgentRuntime] = []
        waiting: list[AgentRuntime] = []
        for node in self.nodes:
            if node.rt is not None:
                (ready if node.rt.steps_ready() > 0 else waiting).append(node.rt)
        if not ready or not waiting:
            return False
        t = min(rt.t for rt in ready)
        local = {node.agent for node in self.nodes}
        return any(abs(rt.t - t) < 0.5 * rt.h
                   and (not rt.own_inputs_ready() or rt.awaited_peer not in local)
                   for rt in waiting)

    def flush(self) -> None:
        """Every step the asking agents have ready, one step of all of them at a time."""
        start = time.thread_time_ns()
        ready = list(self.pending)
        self.pending.clear()
        try:
            while True:
                # An agent with no step ready stays so until a message comes (none is handled
                # here): only those that stepped are asked again.
                ready = [n for n in ready if n.rt is not None and n.rt.steps_ready() > 0]
                if not ready:
                    return
                for node in ready:
                    node.before_step()
                begun = time.thread_time_ns()
                stepped = advance_together([n.rt for n in ready if n.rt is not None])
                spent = time.thread_time_ns() - begun
                self.cpu_steps += spent
                self.cpu_flush -= spent   # counted as steps, not publishing
                self.rounds += 1
                self.steps += len(stepped)
                for node in ready:
                    node.after_step()
        finally:
            self.cpu_flush += time.thread_time_ns() - start


def read_cpu_split(text: str) -> dict[str, tuple[float, int]] | None:
    """The last :meth:`StepBatch.cpu_split` line with timed callbacks in a log's ``text``:
    CPU seconds and count of ``messages`` (callbacks), ``steps`` and ``around`` (agent-steps),
    seconds of ``executor`` and ``dds`` (count 0); None if there is none."""
    found = _CPU_LINE.findall(text)
    if not found:
        return None
    v = found[-1]
    parts = {name: (float(v[2 * k]), int(v[2 * k + 1]))
             for k, name in enumerate(('messages', 'steps', 'around'))}
    parts.update(executor=(float(v[6]), 0), dds=(float(v[7]), 0))
    return parts
