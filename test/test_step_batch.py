"""When an ``estimators`` process runs its agents' steps (ros/step_batch.py): after the messages
already queued, waiting briefly for an agent due at the same instant, never forever. The
executor and the agents are stand-ins: what matters here is the order of events."""
from __future__ import annotations

import time
from collections import deque

import pytest

from bearing_pose_estimation.runtime.agent import AgentRuntime
from bearing_pose_estimation.ros import step_batch
from bearing_pose_estimation.ros.step_batch import StepBatch

H = 0.01


class Agent(AgentRuntime):
    """Only what StepBatch reads: the state time, the steps ready, whom a step waits for."""

    def __init__(self, t: float = 1.0) -> None:   # no AgentRuntime.__init__: no estimator
        self.k, self.t0, self.h = 0, t, H
        self.ready, self.own, self.awaited_peer = 0, False, None

    def steps_ready(self) -> int:
        return self.ready

    def own_inputs_ready(self) -> bool:
        return self.own


class Node:
    def __init__(self, batch: StepBatch, name: str) -> None:
        self.agent, self.rt, self.batch = name, Agent(), batch
        self.log: list[str] = []
        batch.join(self)   # type: ignore[arg-type]

    def before_step(self) -> None:
        self.log.append('before')

    def after_step(self) -> None:
        self.log.append('after')


class Executor:
    """Runs one queued event per spin; a spin that waits (timeout > 0) on an empty queue takes
    the events that "arrive" meanwhile."""

    def __init__(self) -> None:
        self.queue: deque = deque()
        self.arriving: deque = deque()
        self.spins: list[float] = []

    def spin_once(self, timeout_sec: float = 0.0) -> None:
        self.spins.append(timeout_sec)
        if not self.queue and timeout_sec > 0.0 and self.arriving:
            self.queue.append(self.arriving.popleft())
        if self.queue:
            self.queue.popleft()()


@pytest.fixture
def rounds(monkeypatch):
    """Each call of advance_together: the names of the agents it stepped."""
    calls: list[list[str]] = []

    def advance_together(agents):
        calls.append([a.name for a in agents])
        for a in agents:
            a.ready -= 1
            a.k += 1
        return agents
    monkeypatch.setattr(step_batch, 'advance_together', advance_together)
    return calls


def _fleet(names: str) -> tuple[StepBatch, dict[str, Node], Executor]:
    batch = StepBatch()
    nodes = {n: Node(batch, n) for n in names}
    for node in nodes.values():
        node.rt.name = node.agent
    return batch, nodes, Executor()


def _sample(batch: StepBatch, node: Node):
    """A message that completes ``node``'s next step, through a counted callback."""
    def arrive(_msg: object) -> None:
        node.rt.ready += 1
        node.rt.own = True
        batch.request(node)   # type: ignore[arg-type]
    callback = batch.counted(arrive)
    return lambda: callback(None)


def test_the_steps_run_after_the_queued_messages_in_one_call(rounds):
    batch, nodes, ex = _fleet('abc')
    ex.queue.extend(_sample(batch, nodes[n]) for n in 'bc')
    _sample(batch, nodes['a'])()      # the first message, handled by the executor's spin
    batch.settle(ex)                  # type: ignore[arg-type]
    assert rounds == [['a', 'b', 'c']]
    assert not batch.pending and batch.summary().endswith('(3.0 agents per round)')
    assert all(n.log == ['before', 'after'] for n in nodes.values())


def test_a_step_waits_at_most_wait_s_for_an_agent_due_at_the_same_instant(rounds):
    batch, nodes, ex = _fleet('ab')
    ex.arriving.append(_sample(batch, nodes['b']))   # on its way: b's gyro is not here yet
    _sample(batch, nodes['a'])()
    batch.settle(ex)                                 # type: ignore[arg-type]
    assert rounds == [['a', 'b']]
    assert 0.0 < max(ex.spins) <= step_batch.WAIT_S

    batch, nodes, ex = _fleet('ab')   # b's sample never comes: a goes on alone
    _sample(batch, nodes['a'])()
    batch.settle(ex)                  # type: ignore[arg-type]
    assert rounds[-1] == ['a']


def test_no_wait_for_an_agent_that_waits_for_a_step_of_this_process(rounds):
    """b waits for a's estimate of this instant: it comes after a's step, so waiting for it
    before the step would only delay a."""
    batch, nodes, ex = _fleet('ab')
    b = nodes['b'].rt
    b.own, b.awaited_peer = True, 'a'
    ex.arriving.append(_sample(batch, nodes['b']))
    _sample(batch, nodes['a'])()
    batch.settle(ex)                  # type: ignore[arg-type]
    assert rounds == [['a']] and max(ex.spins) == 0.0


def test_a_queue_that_never_empties_still_gets_its_steps(rounds):
    batch, nodes, ex = _fleet('ab')

    class Endless(deque):
        def popleft(self):
            return _sample(batch, nodes['b'])
    ex.queue = Endless([None])
    _sample(batch, nodes['a'])()
    batch.settle(ex)                  # type: ignore[arg-type]
    assert rounds and rounds[0][0] == 'a'
    assert len(ex.spins) <= step_batch.MAX_SPINS + len(rounds)


def _burn(seconds: float) -> None:
    """Spend ``seconds`` of this thread's CPU."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_the_cpu_split_puts_each_part_where_it_was_spent(monkeypatch):
    """``cpu_split`` (the process's last log line with BEARING_POSE_CPU_SPLIT=1): a callback's
    CPU counts as messages, the steps' call as steps, what the nodes do around it (publishing)
    as that, and none of them twice."""
    def advance_together(agents):
        _burn(0.03)
        for a in agents:
            a.ready -= 1
        return agents
    monkeypatch.setattr(step_batch, 'advance_together', advance_together)
    batch = StepBatch(time_callbacks=True)
    node = Node(batch, 'a')
    monkeypatch.setattr(node, 'after_step', lambda: _burn(0.02))

    def arrive(_msg: object) -> None:
        _burn(0.01)
        node.rt.ready += 1
        batch.request(node)   # type: ignore[arg-type]
    ex = Executor()
    ex.queue.append(lambda: batch.counted(arrive)(None))
    ex.spin_once()
    batch.settle(ex)                  # type: ignore[arg-type]
    assert 0.01e9 <= batch.cpu_callbacks < 0.015e9
    assert 0.03e9 <= batch.cpu_steps < 0.035e9
    assert 0.02e9 <= batch.cpu_flush < 0.025e9
    split = batch.cpu_split()
    assert split.startswith('messages 0.01 s (1 callbacks,')
    assert 'steps 0.03 s (1 agent-steps' in split
    assert StepBatch().cpu_split().startswith('messages not timed, steps 0.00 s')
