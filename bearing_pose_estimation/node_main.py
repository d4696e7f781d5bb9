"""The life cycle shared by every node's ``main``: init, spin, clean shutdown on Ctrl-C.

Clean shutdown matters: a node that dies without destroying its DDS participant leaves Fast DDS
files in /dev/shm. Configuration errors (:class:`ScenarioError`) are logged as fatal with their
fix and give exit code 1, without a traceback.
"""
from __future__ import annotations

import faulthandler
import signal
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

from .scenario import Scenario, ScenarioError, load_scenario


def scenario_parameter(node: Node) -> Scenario:
    """Declare the required ``scenario_file`` parameter and load the scenario it names."""
    path = node.declare_parameter('scenario_file', '').value
    if not path:
        raise ScenarioError('parameter scenario_file is empty. Fix: pass '
                            '-p scenario_file:=/path/to/scenario.yaml')
    return load_scenario(path)


def run_node(factory: Callable[[], Node | list[Node]], name: str,
             args: list[str] | None = None, until: Callable[[Node], Future] | None = None,
             on_interrupt: Callable[[Node], None] | None = None) -> int:
    """Create the node (or nodes: one executor spins them all), spin it (until ``until(node)``
    completes, or until shut down), and shut down cleanly. Returns the process exit code.

    Args:
        factory: builds the node, or a list of nodes (after ``rclpy.init``).
        name: logger name for fatal configuration errors.
        until: a future whose completion ends the spin (e.g. "outputs written").
        on_interrupt: called on Ctrl-C / external shutdown (e.g. write partial outputs).
    """
    # SIGUSR1 dumps every thread's stack to stderr (the log): `bearing-pose run` sends it to a
    # node that did not stop on SIGINT, so a hang explains itself.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=args)
    node = None
    nodes: list[Node] = []
    executor = None
    code = 0
    try:
        made = factory()
        nodes = made if isinstance(made, list) else [made]
        node = nodes[0]
        executor = SingleThreadedExecutor()
        for each in nodes:
            executor.add_node(each)
        if until is None:
            executor.spin()
        else:
            executor.spin_until_future_complete(until(node))
            result = until(node).result()
            code = 0 if result in (None, True) else 1
    except (KeyboardInterrupt, ExternalShutdownException):
        if node is not None and on_interrupt is not None:
            on_interrupt(node)
    except ScenarioError as exc:
        rclpy.logging.get_logger(name).fatal(str(exc))
        code = 1
    except Exception as exc:  # noqa: BLE001
        # Ctrl-C shuts the context down from a signal handler; an executor caught between its
        # checks then fails to build a wait set (RCLError), to take a message (pybind11's
        # RuntimeError) or to use a handle being destroyed. After shutdown that is the shutdown
        # itself (said, not hidden); while the context is valid it is a real error.
        if rclpy.ok():
            raise
        rclpy.logging.get_logger(name).info(f'shutdown interrupted a callback: {exc!r}')
        if node is not None and on_interrupt is not None:
            on_interrupt(node)
    finally:
        if executor is not None:
            # Release the executor's hold on the nodes before destroying them; do not wait
            # long for a callback that a dying context cannot finish.
            executor.shutdown(timeout_sec=2.0)
        for each in nodes:
            try:
                each.destroy_node()
            except Exception as exc:  # noqa: BLE001
                rclpy.logging.get_logger(name).warning(f'destroy_node failed: {exc!r}')
        rclpy.try_shutdown()  # releases the DDS participant: no files left in /dev/shm
    return code
