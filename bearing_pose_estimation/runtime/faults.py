"""Injected link faults: each neighbour message lost with ``drop_rate`` and delivered
``delay`` seconds late. The estimator node's ``inject_*`` parameters and netsim's fault
matrix both go through :class:`FaultyLink`."""
from __future__ import annotations

import heapq
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinkFaults:
    drop_rate: float = 0.0  # probability of losing each neighbour message
    delay: float = 0.0      # extra delay of each neighbour message [s]
    seed: int = 0

    def __bool__(self) -> bool:
        return self.drop_rate > 0.0 or self.delay > 0.0


class FaultyLink:
    """Messages through the faults: :meth:`send` drops one or holds it for ``delay``;
    :meth:`release` delivers those whose time has come, in the order they were sent."""

    def __init__(self, faults: LinkFaults) -> None:
        self.faults = faults
        self.rng = np.random.default_rng(faults.seed)
        self._held: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = 0
        self.dropped = 0

    def send(self, now: float, deliver: Callable[[float], None]) -> None:
        """``deliver(at)`` now, later (at its time), or never."""
        if self.faults.drop_rate and self.rng.uniform() < self.faults.drop_rate:
            self.dropped += 1
            return
        if self.faults.delay > 0.0:
            self._seq += 1
            heapq.heappush(self._held, (now + self.faults.delay, self._seq, deliver))
            return
        deliver(now)

    def release(self, now: float) -> None:
        """Deliver what was held until ``now``."""
        while self._held and self._held[0][0] <= now + 1e-9:
            heapq.heappop(self._held)[2](now)

    @property
    def holding(self) -> bool:
        return bool(self._held)
