"""The life cycle shared by every node's ``main``: init, spin, clean shutdown on Ctrl-C.

Clean shutdown matters: a node that dies without destroying its DDS participant leaves Fast DDS
files in /dev/shm. SIGINT and SIGTERM only ask the spin loop to stop; everything after happens
on the main thread, in order (see :class:`_StopRequest`). Configuration errors
(:class:`ScenarioError`) are logged as fatal with their fix and give exit code 1, without a
traceback.
"""
from __future__ import annotations

import faulthandler
import os
import signal
import sys
import threading
from collections.abc import Callable

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from .executor import DrainingExecutor
from .scenario import Scenario, ScenarioError, load_scenario

# Which executor spins the nodes: 'draining' (ours, the default; see executor.py and
# BENCHMARKS.md) or 'rclpy' (its SingleThreadedExecutor), kept for comparisons.
EXECUTOR_ENV = 'BEARING_POSE_EXECUTOR'
EXECUTORS = {'draining': DrainingExecutor, 'rclpy': SingleThreadedExecutor}


def scenario_parameter(node: Node) -> Scenario:
    """Declare the required ``scenario_file`` parameter and load the scenario it names."""
    path = node.declare_parameter('scenario_file', '').value
    if not path:
        raise ScenarioError('parameter scenario_file is empty. Fix: pass '
                            '-p scenario_file:=/path/to/scenario.yaml')
    return load_scenario(path)


# How long one executor wait may block: the longest delay between a stop signal and the
# spin loop noticing it when no timer or message wakes the executor.
_POLL_S = 0.1


class _StopRequest:
    """SIGINT/SIGTERM handler that only records the request; a second signal interrupts.

    rclpy's own handler shuts the context down from its signal thread while the executor may be
    taking a message or destroying a handle; on shutdown that race crashed (SIGSEGV), hung in
    ``destroy_node`` or raised from ``take_message`` in about one fleet shutdown in twelve
    (``bench/shutdown_stress.py`` reproduces it). Stopping from the spin loop instead leaves one
    thread doing everything, in order.
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


def run_node(factory: Callable[[], Node | list[Node]], name: str,
             args: list[str] | None = None, until: Callable[[Node], Future] | None = None,
             on_interrupt: Callable[[Node], None] | None = None) -> int:
    """Create the node (or nodes: one executor spins them all), spin it (until ``until(node)``
    completes, or until SIGINT/SIGTERM), and shut down cleanly. Returns the process exit code.

    Args:
        factory: builds the node, or a list of nodes (after ``rclpy.init``).
        name: logger name for fatal configuration errors.
        until: a future whose completion ends the spin (e.g. "outputs written").
        on_interrupt: called when a signal stopped the spin (e.g. write partial outputs).
    """
    # SIGUSR1 dumps every thread's stack to stderr (the log): `bearing-pose run` sends it to a
    # node that did not stop on SIGINT, so a hang explains itself.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    stop = _StopRequest()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    nodes: list[Node] = []
    executor = None
    code = 0
    try:
        choice = os.environ.get(EXECUTOR_ENV, 'draining')
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
        if stop.signal is not None:
            rclpy.logging.get_logger(name).info(
                f'{signal.Signals(stop.signal).name}: shutting down')
            if on_interrupt is not None:
                on_interrupt(node)
        elif future is not None:
            code = 0 if future.result() in (None, True) else 1
    except KeyboardInterrupt:  # a second signal while stopping, or one during start-up
        if node is not None and on_interrupt is not None:
            on_interrupt(node)
    except ScenarioError as exc:
        rclpy.logging.get_logger(name).fatal(str(exc))
        code = 1
    finally:
        watchdog = threading.Timer(TEARDOWN_TIMEOUT_S, _teardown_hung, (name, code))
        watchdog.daemon = True
        watchdog.start()
        if executor is not None:
            executor.shutdown(timeout_sec=2.0)
        for each in nodes:
            try:
                each.destroy_node()
            except Exception as exc:  # noqa: BLE001
                rclpy.logging.get_logger(name).warning(f'destroy_node failed: {exc!r}')
        rclpy.try_shutdown()  # releases the DDS participant: no files left in /dev/shm
        watchdog.cancel()
        stop.restore()
    return code


# Destroying nodes takes well under a second. Fast DDS (2.14, in the Jazzy wheels) sometimes
# deadlocks inside rcl_node_fini when many participants leave at once: about one process in
# 200 in bench/shutdown_stress.py, always in rclpy's Node.destroy_node. Nothing can unblock it.
TEARDOWN_TIMEOUT_S = 5.0


def _teardown_hung(name: str, code: int) -> None:
    """The watchdog's end: say what hung, with the stacks, and exit with the node's own code
    (its work is done) instead of waiting for SIGKILL."""
    sys.stderr.write(f'[ERROR] [{name}]: DDS teardown did not finish in {TEARDOWN_TIMEOUT_S:g} s '
                     '(a Fast DDS deadlock in node destruction); exiting without it. Its files '
                     'may stay in /dev/shm: `fastdds shm clean` removes them. Stacks:\n')
    faulthandler.dump_traceback(all_threads=True)
    sys.stderr.flush()
    os._exit(code)
