"""A lean single-threaded executor: one wait, then every ready queue drained, in arrival order
(``BEARING_POSE_EXECUTOR=draining``; EventsExecutor measured cheaper, BENCHMARKS.md). rclpy's
``SingleThreadedExecutor`` runs *one* callback per wake-up (262-1 644 µs of CPU per message
against 99-144 µs here). Clients and coroutine callbacks are not served.
"""
from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from rclpy.executors import Executor, TimeoutObject
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.subscription import Subscription
from rclpy.utilities import timeout_sec_to_nsec


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    result = fn(*args)
    if inspect.iscoroutine(result):
        result.close()
        raise TypeError(f'{fn!r} is a coroutine function; DrainingExecutor runs plain callbacks')
    return result


def _run_coroutine(coro: Any) -> None:
    """Drive a coroutine that never really waits (rclpy's waitable ``execute``) to its end."""
    try:
        while True:
            coro.send(None)
    except StopIteration:
        pass


class DrainingExecutor(Executor):
    """Wait once on every entity of every node, then run everything ready: the queued messages
    (in arrival order), then timers, services, QoS events and guard conditions."""

    def add_node(self, node: Node) -> bool:
        if any(True for _ in node.clients):  # a generator, always truthy itself
            raise ValueError(f'{node.get_fully_qualified_name()} has service clients; '
                             'DrainingExecutor does not serve them. Fix: use rclpy\'s '
                             'SingleThreadedExecutor for this node')
        return super().add_node(node)

    def spin_once(self, timeout_sec: float | None = None) -> None:
        if self._is_shutdown or not self._context.ok():
            return
        nodes = self.get_nodes()
        subs = [s for n in nodes for s in n.subscriptions]
        timers = [t for n in nodes for t in n.timers]
        services = [s for n in nodes for s in n.services]
        waitables = [w for n in nodes for w in n.waitables]
        guards = [g for n in nodes for g in n.guards]
        own_guards = [g for g in (self._guard, self._sigint_gc) if g is not None]
        events = sum(w.get_num_entities().num_events for w in waitables)
        ws = _rclpy.WaitSet(len(subs), len(guards) + len(own_guards), len(timers), 0,
                            len(services), events, self._context.handle)
        ws.clear_entities()
        for add, entities in ((ws.add_subscription, subs), (ws.add_timer, timers),
                              (ws.add_service, services),
                              (ws.add_guard_condition, guards + own_guards)):
            for entity in entities:
                add(entity.handle)
        for w in waitables:
            w.add_to_wait_set(ws)
        ws.wait(timeout_sec_to_nsec(timeout_sec))
        if self._is_shutdown or not self._context.ok():
            return

        ready = ws.get_ready_entities('subscription')
        taken: list[tuple[int, int, Subscription, tuple]] = []
        for s in subs:
            if s.handle.pointer in ready:
                while (msg_info := s.handle.take_message(s.msg_type, s.raw)) is not None:
                    taken.append((msg_info[1]['received_timestamp'], len(taken), s, msg_info))
        # In arrival order across subscriptions: a bearing that arrived before the gyro sample
        # completing a step must be seen before the step runs.
        taken.sort(key=lambda item: (item[0], item[1]))
        for _, _, s, msg_info in taken:
            if s._callback_type is Subscription.CallbackType.MessageOnly:
                _call(s.callback, msg_info[0])
            else:
                _call(s.callback, *msg_info)
        ready = ws.get_ready_entities('timer')
        for t in timers:
            # is_timer_ready: rcl may report a cancelled timer as ready
            if t.handle.pointer in ready and t.handle.is_timer_ready():
                t.handle.call_timer()
                _call(t.callback)
        ready = ws.get_ready_entities('service')
        for srv in services:
            if srv.handle.pointer in ready:
                srv_type: Any = srv.srv_type  # a generated service class (rclpy types it loosely)
                request, header = srv.handle.service_take_request(srv_type.Request)
                if header is not None:
                    srv.send_response(_call(srv.callback, request, srv_type.Response()), header)
        for w in waitables:
            if w.is_ready(ws):
                _run_coroutine(w.execute(w.take_data()))
        ready = ws.get_ready_entities('guard_condition')
        for g in guards:
            if g.handle.pointer in ready and g.callback is not None:
                _call(g.callback)

    def spin_once_until_future_complete(self, future: Any,
                                        timeout_sec: float | TimeoutObject | None = None
                                        ) -> None:
        # rclpy's spin_until_future_complete passes what is left of its timeout this way.
        self.spin_once(timeout_sec.timeout if isinstance(timeout_sec, TimeoutObject)
                       else timeout_sec)
