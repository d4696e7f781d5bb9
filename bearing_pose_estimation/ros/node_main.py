"""The life cycle shared by every node's ``main``: init, spin, clean shutdown on Ctrl-C; and
their parameters (:func:`declare`, :func:`warn_unknown_parameters`).

Clean shutdown matters: a node that dies without destroying its DDS participant leaves Fast DDS
files in /dev/shm. Configuration errors are logged as fatal with their fix, exit code 1.
"""
from __future__ import annotations

import difflib
import faulthandler
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.experimental.events_executor import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.timer import Timer

from .executor import DrainingExecutor
from ..core.errors import ScenarioError
from ..plan.dds import TEARDOWN_WATCHDOG_SIGNAL
from ..scenario.model import Scenario
from ..scenario.parse import load_scenario

# The nodes' executor, chosen by measurement (BENCHMARKS.md, "The executor"): rclpy's
# EventsExecutor (C++; experimental in Jazzy, in the pinned 7.1.6), 0.87x the CPU of our
# DrainingExecutor (executor.py) on the paper fleet; EXECUTOR_ENV picks another (comparisons).
EXECUTOR_ENV = 'BEARING_POSE_EXECUTOR'
EXECUTORS: dict[str, Callable[[], Executor]] = {
    'events': EventsExecutor, 'draining': DrainingExecutor, 'rclpy': SingleThreadedExecutor}
DEFAULT_EXECUTOR = 'events'


def scenario_parameter(node: Node) -> Scenario:
    """Declare the required ``scenario_file`` parameter and load the scenario it names."""
    path = declare(node, 'scenario_file', '', 'scenario YAML file')
    if not path:
        raise ScenarioError('parameter scenario_file is empty. Fix: pass '
                            '-p scenario_file:=/path/to/scenario.yaml')
    return load_scenario(path)


# --------------------------------------------------------------------------- parameters
_T = Parameter.Type
_KINDS = {_T.BOOL: 'true or false', _T.INTEGER: 'an integer', _T.DOUBLE: 'a number',
          _T.STRING: 'a string', _T.INTEGER_ARRAY: 'a list of integers',
          _T.DOUBLE_ARRAY: 'a list of numbers', _T.STRING_ARRAY: 'a list of strings',
          _T.BOOL_ARRAY: 'a list of true/false'}
_EXAMPLES = {_T.BOOL: 'true', _T.INTEGER: '1', _T.DOUBLE: '1.0', _T.STRING: 'text',
             _T.INTEGER_ARRAY: '[1, 2]', _T.DOUBLE_ARRAY: '[1.0, 2.0]',
             _T.STRING_ARRAY: '[agent_1, agent_2]', _T.BOOL_ARRAY: '[true, false]'}
_ITEM = {_T.INTEGER_ARRAY: _T.INTEGER, _T.DOUBLE_ARRAY: _T.DOUBLE, _T.STRING_ARRAY: _T.STRING,
         _T.BOOL_ARRAY: _T.BOOL}
_PYTHON: dict[Parameter.Type, Any] = {  # the Python types of a value of each scalar kind
    _T.BOOL: bool, _T.INTEGER: int, _T.DOUBLE: (int, float), _T.STRING: str}


def parameter_overrides(node: Node) -> dict[str, Parameter]:
    """The values given to ``node`` from outside: parameter files, ``-p`` and the constructor's
    ``parameter_overrides``. rclpy has no public accessor (rclcpp has
    ``get_parameter_overrides()``); Node keeps them in ``_parameter_overrides`` (rclpy 7.1.6,
    pinned; test_estimator_params.py fails if that changes)."""
    return dict(getattr(node, '_parameter_overrides', {}))


def _item(kind: Parameter.Type, value: Any) -> Any:
    """``value`` as a scalar of type ``kind`` (an int is a float too), or raise TypeError."""
    if isinstance(value, bool) != (kind == _T.BOOL) or not isinstance(value, _PYTHON.get(kind, ())):
        raise TypeError
    return float(value) if kind == _T.DOUBLE else value


def _given(name: str, kind: Parameter.Type, given: Parameter) -> Any:
    """An override converted to ``kind``, or a ScenarioError naming the parameter and the fix."""
    value = given.value
    if given.type_ == _T.NOT_SET and kind in _ITEM:  # `name: []` in YAML has no type
        return []
    try:
        if kind in _ITEM:
            if not isinstance(value, (list, tuple)) and type(value).__name__ != 'array':
                raise TypeError
            return [_item(_ITEM[kind], v) for v in value]
        return _item(kind, value)
    except TypeError:
        got = _KINDS.get(given.type_, 'no value' if given.type_ == _T.NOT_SET else
                         given.type_.name.lower())
        raise ScenarioError(f'parameter {name} must be {_KINDS[kind]}, but {got} was given '
                            f'({value!r}). Fix: e.g. `{name}: {_EXAMPLES[kind]}` in the '
                            f'parameter file, or -p {name}:={_EXAMPLES[kind]}') from None


def declare(node: Node, name: str, default: Any, description: str = '',
            low: float | None = None, high: float | None = None,
            read_only: bool = True) -> Any:
    """Declare a parameter of the default's type and return its value (read-only unless
    ``read_only`` is False: the node then validates changes, and rclpy the range). It accepts
    what a ROS user writes (``100`` for a float, ``[]`` for any list); another type, or a number
    outside ``[low, high]``, raises a one-line :class:`ScenarioError` (rclpy: a traceback)."""
    kind = Parameter.Type.from_parameter_value(default)
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    given = parameter_overrides(node).get(name)
    value = default if given is None else _given(name, kind, given)
    if low is not None and high is not None:
        if any(not low <= v <= high for v in (value if isinstance(value, list) else [value])):
            raise ScenarioError(f'parameter {name} must be in [{low:g}, {high:g}], but '
                                f'{value!r} was given. Fix: a value in that range')
        if kind == _T.INTEGER:   # step 0 (the default): no step
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high))]
        else:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high))]
    if value == [] and kind in _ITEM:  # declared with its type, without a value
        node.declare_parameter(name, kind, descriptor, ignore_override=True)
        return []
    return node.declare_parameter(name, value, descriptor, ignore_override=True).value


def warn_unknown_parameters(node: Node) -> list[str]:
    """Warn (one log line) about given parameters this node never declared (``neighbour_timout``):
    rclpy ignores them, so a misspelt key would silently keep its default. Returns them."""
    unknown = sorted(k for k in parameter_overrides(node) if not node.has_parameter(k))
    if unknown:
        known = sorted(node.list_parameters([], 0).names)  # depth 0: all
        close = {key: difflib.get_close_matches(key, known, n=1) for key in unknown}
        hints = [f'{key} (did you mean {c[0]}?)' if c else key for key, c in close.items()]
        node.get_logger().warning(
            f'unknown parameter(s) ignored: {", ".join(hints)}. Known parameters: '
            f'{", ".join(known)}')
    return unknown


# How long one executor wait may block: the longest delay between a stop signal and the
# spin loop noticing it when no timer or message wakes the executor.
_POLL_S = 0.1


class _StopRequest:
    """SIGINT/SIGTERM handler that only records the request; a second signal interrupts.

    rclpy's own handler shuts the context down from its signal thread while the executor may be
    taking a message or destroying a handle: a crash, hang or raise in about one fleet shutdown
    in twelve (``bench/shutdown_stress.py``). The spin loop stops instead, on one thread.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        self._previous = {sig: signal.signal(sig, self._handle)
                          for sig in (signal.SIGINT, signal.SIGTERM)}

    def _handle(self, signum: int, _frame: object) -> None:
        if self.signal is not None:  # asked twice: stop waiting for the loop
            raise KeyboardInterrupt
        self.signal = signum

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


N = TypeVar('N', bound=Node)


def run_node(factory: Callable[[], N | list[N]], name: str,
             args: list[str] | None = None, until: Callable[[N], Future] | None = None,
             on_interrupt: Callable[[N], None] | None = None,
             after_spin: Callable[[Executor], None] | None = None) -> int:
    """Create the node(s) with ``factory`` (after ``rclpy.init``), spin until ``until(node)``
    completes or SIGINT/SIGTERM (then ``on_interrupt``), and shut down cleanly; ``after_spin``
    gets the executor after each spin (:mod:`.step_batch`). Returns the process exit code."""
    # SIGUSR1 dumps every thread's stack to stderr (the log): `bearing-pose run` sends it to a
    # node that did not stop on SIGINT, so a hang explains itself.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    stop = _StopRequest()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    log = rclpy.logging.get_logger(name)
    node: N | None = None
    nodes: list[N] = []
    executor = None
    code = 0
    try:
        choice = os.environ.get(EXECUTOR_ENV, DEFAULT_EXECUTOR)
        if choice not in EXECUTORS:
            raise ScenarioError(f'{EXECUTOR_ENV}={choice!r} is not an executor. Fix: one of '
                                f'{", ".join(EXECUTORS)}, or unset it')
        made = factory()
        nodes = made if isinstance(made, list) else [made]
        node = nodes[0]
        executor = EXECUTORS[choice]()
        for each in nodes:
            executor.add_node(each)
        future = until(node) if until is not None else None
        while stop.signal is None and (future is None or not future.done()):
            executor.spin_once(timeout_sec=_POLL_S)
            if after_spin is not None:
                after_spin(executor)
        if stop.signal is not None:
            log.info(f'{signal.Signals(stop.signal).name}: shutting down')
            if on_interrupt is not None:
                on_interrupt(node)
        elif future is not None:
            code = 0 if future.result() in (None, True) else 1
    except KeyboardInterrupt:  # a second signal while stopping, or one during start-up
        if node is not None and on_interrupt is not None:
            on_interrupt(node)
    except ScenarioError as exc:
        log.fatal(str(exc))
        code = 1
    except ParameterException as exc:  # e.g. `use_sim_time: 1`, declared by rclpy itself
        log.fatal(f'parameter error: {exc}. Fix: give the parameter the type and range it is '
                  'declared with (see `ros2 param describe`) in the parameter file or -p')
        code = 1
    finally:
        watchdog = threading.Timer(TEARDOWN_TIMEOUT_S, _teardown_hung, (name, code))
        watchdog.daemon = True
        watchdog.start()
        # The watchdog is a Python thread: a teardown that hangs holding the GIL (the Fast DDS
        # deadlock does) never lets it run. The kernel's alarm needs no GIL: one second later
        # faulthandler's C handler dumps the stacks, then SIGALRM's default action ends the
        # process. The launcher knows that exit (plan.dds.TEARDOWN_WATCHDOG_SIGNAL) from a crash.
        faulthandler.register(TEARDOWN_WATCHDOG_SIGNAL, all_threads=True, chain=True)
        signal.setitimer(signal.ITIMER_REAL, TEARDOWN_TIMEOUT_S + 1.0)
        if executor is not None:
            executor.shutdown(timeout_sec=2.0)
        for each in nodes:
            try:
                each.destroy_node()
            except Exception as exc:  # noqa: BLE001
                log.warning(f'destroy_node failed: {exc!r}')
        rclpy.try_shutdown()  # releases the DDS participant: no files left in /dev/shm
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        faulthandler.unregister(TEARDOWN_WATCHDOG_SIGNAL)
        watchdog.cancel()
        stop.restore()
    return code


# Destroying nodes takes well under a second. Fast DDS (2.14, in the Jazzy wheels) sometimes
# deadlocks in rcl_node_fini, holding the GIL: about one process in 200 in
# bench/shutdown_stress.py (eProsima/Fast-DDS#6502, open). Nothing in Python can unblock it.
TEARDOWN_TIMEOUT_S = 5.0


def _teardown_hung(name: str, code: int) -> None:
    """The watchdog's end: say what hung, with the stacks, and exit. A node whose work succeeded
    ends by TEARDOWN_WATCHDOG_SIGNAL, as the C-level watchdog would, so the launcher counts it
    clean and cleans /dev/shm; a failed one keeps its own exit code."""
    sys.stderr.write(f'[ERROR] [{name}]: DDS teardown did not finish in {TEARDOWN_TIMEOUT_S:g} s '
                     '(a Fast DDS deadlock in node destruction); exiting without it. Its files '
                     'may stay in /dev/shm: `fastdds shm clean` removes them. Stacks:\n')
    faulthandler.dump_traceback(all_threads=True)
    sys.stderr.flush()
    if code != 0:
        os._exit(code)
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    faulthandler.unregister(TEARDOWN_WATCHDOG_SIGNAL)  # back to SIG_DFL; the stacks are out
    os.kill(os.getpid(), TEARDOWN_WATCHDOG_SIGNAL)


def tf_broadcaster(node: Node, wanted: bool) -> Any:
    """tf2_ros's TransformBroadcaster, when wanted and installed (a full Jazzy install; the
    PyPI wheels have no tf2_ros), else None."""
    if not wanted:
        return None
    try:
        from tf2_ros import TransformBroadcaster
    except ImportError:
        node.get_logger().info('tf2_ros is not installed: no TF broadcast (the estimate topic '
                               'carries the same pose)')
        return None
    return TransformBroadcaster(node)


def wall_timer(node: Node, period: float, callback: Callable[[], None]) -> Timer:
    """A timer on the steady clock: it fires whatever the node's (simulated) clock does."""
    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def take_waiting(node: Node) -> int:
    """Take what ``node``'s subscriptions hold and run their callbacks: for a node stalled on
    messages its executor was not told of. Returns how many it took."""
    found = 0
    for sub in list(node.subscriptions):
        with sub.handle:
            while (taken := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                found += 1
                sub.callback(taken[0])
    return found
