"""What the runtime keeps of its inputs: stamped samples with one set of operations, the time
rules' limits, and the checks of a received vector (:mod:`.agent`)."""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
# Stamps closer than this [s] are the same instant.
SAME = 1e-9
# Samples kept per input: enough for a step that waits link_wait (0.25 s: 50 samples at
# 200 Hz) and then looks back.
HISTORY = 256

# Causes that are events of the time rules, not bad input, with what they mean for the log.
TIME_EVENTS = {'time_jump': 'the clock jumped back: restarted from the initial estimate',
               'gyro_gap': 'gyro gap: the state time restarts after it, keeping the estimate',
               'odometry_gap': 'odometry gap: its integration restarts after it'}


@dataclass(frozen=True)
class Limits:
    """Input checks and timeouts. Inputs outside them are rejected with a named cause, never
    used: no input can put a non-finite value into the estimate."""

    max_rate: float = 35.0          # |ω| above this [rad/s] is absurd (2000 deg/s: gyro range)
    max_speed: float = 100.0        # an odometry speed above this [m/s] is absurd
    unit_tolerance: float = 1e-3    # a bearing with | ‖b‖ - 1 | above this is not a unit vector
    sensor_timeout: float = 0.5     # own samples older than this [s] are not used
    neighbour_timeout: float = 0.5  # a neighbour silent for longer [s] is stale: not used
    # A step waits for a neighbour's input until its own sensors are this far [s] ahead (the
    # estimate is then late by as much; a longer delay is a lost input).
    link_wait: float = 0.25
    max_gyro_gap: float = 0.5       # after a longer gyro gap [s] the state time restarts
    jump_back: float = 1.0          # a stamp this much [s] before the newest: clock jumped back
    max_future: float = 1.0         # stamps further ahead [s] than the newest gyro: rejected
    # An agent with no trustworthy estimate tries its method's warm start at every step for
    # this long [s] (its neighbours may not be heard yet); 0: never.
    warm_window: float = 2.0
    # A neighbour's stamps further ahead [s] of the own clock: its clock runs ahead (counted,
    # and /diagnostics warns); well above a LAN's latency and a step, below a 50 ms offset.
    max_clock_lead: float = 0.02
    # A neighbour whose covariance jumps (runtime.agent.RESET_JUMP) above this, in units of the
    # prior's (its std a tenth of it), announces a reset: it is left out for a while.
    reset_trust: float = 0.01


@dataclass(frozen=True)
class Exchange:
    """A simulation's deterministic exchange: the periods of the inputs a step waits for, which
    fix its inputs by their stamps (None: the spacing of the last two samples)."""

    publish_period: float                  # the neighbours' 'instant' channels [s]
    sensor_period: float | None = None     # the own point sensors [s]
    known_pose_period: float | None = None  # a leader's known pose [s]


class Stamped:
    """``(stamp, value)`` samples of one input, stamps increasing."""

    __slots__ = ('samples',)

    def __init__(self, maxlen: int = HISTORY) -> None:
        self.samples: deque[tuple[float, Array]] = deque(maxlen=maxlen)

    def __bool__(self) -> bool:
        return bool(self.samples)

    @property
    def newest_stamp(self) -> float:
        return self.samples[-1][0] if self.samples else -math.inf

    def add(self, stamp: float, value: Array) -> None:
        """Append, or replace the value of the newest stamp when ``stamp`` is the same."""
        if self.samples and abs(stamp - self.samples[-1][0]) < SAME:
            self.samples[-1] = (stamp, value)
        else:
            self.samples.append((stamp, value))

    def at(self, t: float) -> tuple[Array | None, bool]:
        """``(value, decided)``: the value stamped ``t``; or None with ``decided`` when it
        will not come (a later one is here)."""
        for stamp, value in reversed(self.samples):
            if abs(stamp - t) < SAME:
                return value, True
            if stamp < t:
                break   # the rest are older still
        return None, self.newest_stamp > t + SAME

    def newest(self, until: float = math.inf) -> tuple[float, Array] | None:
        """The newest sample stamped at or before ``until``."""
        for stamp, value in reversed(self.samples):
            if stamp <= until + SAME:
                return stamp, value
        return None

    def interpolate(self, t: float, rotate: Callable[[float, float], Array]
                    ) -> tuple[Array | None, bool]:
        """``(value, decided)`` at ``t``: the sample at t, or the two around it rotated to the
        frame at t (``rotate(s, t)``) and interpolated linearly; None with ``decided`` once a
        sample after t is here and none before, or no rotation covers the span."""
        before = after = None
        for stamp, v in reversed(self.samples):
            if abs(stamp - t) < SAME:
                return v, True
            if stamp > t:
                after = (stamp, v)
            else:
                before = (stamp, v)
                break
        if after is None:
            return None, False
        if before is None:
            return None, True
        try:
            a = rotate(before[0], t) @ before[1]
            b = rotate(after[0], t) @ after[1]
        except ValueError:   # no rotation data over the span
            return None, True
        w = (t - before[0]) / (after[0] - before[0])
        return (1.0 - w) * a + w * b, True

    def interval(self, h: float) -> float:
        """Steps of ``h`` between the last two samples, at least 1: how many steps the newest
        serves."""
        if len(self.samples) < 2:
            return 1.0
        return max(1.0, (self.samples[-1][0] - self.samples[-2][0]) / h)


def complete(stamps: deque[float], period: float | None, end: float) -> bool:
    """The samples measured by ``end`` are in: the next one due (newest stamp + period) is
    later. Unknown with one sample and no period: taken as in."""
    if not stamps:
        return False
    if period is None:
        if len(stamps) < 2:
            return True
        period = stamps[-1] - stamps[-2]
    return stamps[-1] + period > end + SAME


# ----------------------------------------------------------------------------- checks
def finite_max_norm(v: Array) -> tuple[bool, float, float]:
    """Whether every entry of the small vector ``v`` is finite, its largest magnitude and norm,
    in Python floats (numpy's per-call overhead would cost a few µs per check)."""
    values = v.ravel().tolist()
    if not all(map(math.isfinite, values)):
        return False, math.nan, math.nan
    return True, max(map(abs, values), default=0.0), math.hypot(*values)


def unit_problem(v: Array, tolerance: float) -> str | None:
    """Why ``v`` is not a usable unit vector, or None."""
    finite, largest, norm = finite_max_norm(v)
    if not finite:
        return 'non_finite'
    if largest > 2.0:
        return 'not_unit'
    if norm < 1e-6:
        return 'zero_vector'
    if abs(norm - 1.0) > tolerance:
        return 'not_unit'
    return None


def bounded_problem(v: Array, bound: float) -> str | None:
    """Why ``v`` is not a finite vector with every entry within ``±bound``, or None."""
    finite, largest, _ = finite_max_norm(v)
    if not finite:
        return 'non_finite'
    return 'absurd_value' if largest > bound else None


def twist_problem(stamp: float, v: Array, omega: Array, limits: Limits) -> str | None:
    """Why an odometry twist (``v`` [m/s], ``omega`` [rad/s] at ``stamp``) is unusable, or
    None: any entry not finite, a rate above ``max_rate``, a speed above ``max_speed``."""
    finite_v, _, speed = finite_max_norm(v)
    finite_w, _, rate = finite_max_norm(omega)
    if not (finite_v and finite_w and math.isfinite(stamp)):
        return 'non_finite'
    if rate > limits.max_rate:
        return 'absurd_rate'
    if speed > limits.max_speed:
        return 'absurd_speed'
    return None
