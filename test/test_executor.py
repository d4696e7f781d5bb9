"""DrainingExecutor (the nodes' executor): every message delivered once and in order, timers,
parameter services and QoS events still served, unsupported callbacks refused. In-process,
one context on the test's own domain."""
import time

import pytest
import rclpy
from rcl_interfaces.srv import GetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32

from bearing_pose_estimation.ros.executor import DrainingExecutor

pytestmark = pytest.mark.dds

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _spin_until(executor, condition, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def test_every_message_arrives_once_in_order_and_timers_fire(context):
    sender = rclpy.create_node('sender', context=context)
    receiver = rclpy.create_node('receiver', context=context)
    got, ticks = [], []
    receiver.create_subscription(Int32, 'numbers', lambda m: got.append(m.data), RELIABLE)
    receiver.create_timer(0.01, lambda: ticks.append(time.monotonic()))
    pub = sender.create_publisher(Int32, 'numbers', RELIABLE)
    executor = DrainingExecutor(context=context)
    for node in (sender, receiver):
        executor.add_node(node)
    try:
        assert _spin_until(executor, lambda: pub.get_subscription_count() == 1)
        for k in range(500):  # a burst: many queued at once, drained in one go
            pub.publish(Int32(data=k))
        assert _spin_until(executor, lambda: len(got) >= 500)
        assert got == list(range(500))
        ticks.clear()
        assert _spin_until(executor, lambda: len(ticks) >= 10, timeout=5.0)
    finally:
        executor.shutdown()
        sender.destroy_node()
        receiver.destroy_node()


def test_messages_of_several_topics_run_in_arrival_order(context):
    """Two topics published alternately, drained in one go: the callbacks interleave as the
    messages arrived, not topic by topic."""
    sender = rclpy.create_node('sender2', context=context)
    receiver = rclpy.create_node('receiver2', context=context)
    got = []
    for topic in ('first', 'second'):
        receiver.create_subscription(Int32, topic, lambda m, t=topic: got.append((t, m.data)),
                                     RELIABLE)
    pubs = [sender.create_publisher(Int32, t, RELIABLE) for t in ('first', 'second')]
    executor = DrainingExecutor(context=context)
    executor.add_node(receiver)  # the sender is not spun: everything queues up first
    try:
        assert _spin_until(executor, lambda: all(p.get_subscription_count() == 1 for p in pubs))
        expected = []
        for k in range(50):
            pub = pubs[k % 2]
            pub.publish(Int32(data=k))
            expected.append((pub.topic_name.lstrip('/'), k))
        assert _spin_until(executor, lambda: len(got) >= 50)
        assert got == expected
    finally:
        executor.shutdown()
        sender.destroy_node()
        receiver.destroy_node()


def test_parameter_services_still_answer(context):
    """`ros2 param get` on a node spun by DrainingExecutor: served from another executor."""
    served = rclpy.create_node('served', context=context)
    served.declare_parameter('k_R', 2.5)
    asker = rclpy.create_node('asker', context=context)
    client = asker.create_client(GetParameters, '/served/get_parameters')
    ours, theirs = DrainingExecutor(context=context), SingleThreadedExecutor(context=context)
    ours.add_node(served)
    theirs.add_node(asker)
    try:
        deadline = time.monotonic() + 10.0
        while not client.service_is_ready() and time.monotonic() < deadline:
            ours.spin_once(timeout_sec=0.01)
            theirs.spin_once(timeout_sec=0.01)
        future = client.call_async(GetParameters.Request(names=['k_R']))
        while not future.done() and time.monotonic() < deadline:
            ours.spin_once(timeout_sec=0.01)
            theirs.spin_once(timeout_sec=0.01)
        assert future.done() and future.result().values[0].double_value == 2.5
    finally:
        ours.shutdown()
        theirs.shutdown()
        served.destroy_node()
        asker.destroy_node()


def test_incompatible_qos_is_still_reported(context):
    """QoS events (waitables) run: a best-effort publisher and a reliable reader never match,
    and the reader's incompatible-QoS event callback says so."""
    from rclpy.event_handler import SubscriptionEventCallbacks
    node = rclpy.create_node('qos', context=context)
    events = []
    node.create_subscription(
        Int32, 'qos_topic', lambda m: None, RELIABLE,
        event_callbacks=SubscriptionEventCallbacks(incompatible_qos=events.append))
    node.create_publisher(Int32, 'qos_topic', QoSProfile(
        depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    executor = DrainingExecutor(context=context)
    executor.add_node(node)
    try:
        assert _spin_until(executor, lambda: events)
        assert events[0].total_count >= 1
    finally:
        executor.shutdown()
        node.destroy_node()


def test_refuses_clients_and_coroutine_callbacks(context):
    node = rclpy.create_node('bad', context=context)
    node.create_client(GetParameters, '/nobody/get_parameters')
    executor = DrainingExecutor(context=context)
    with pytest.raises(ValueError, match='service clients'):
        executor.add_node(node)
    node.destroy_node()

    node = rclpy.create_node('async_timer', context=context)

    async def tick():
        pass
    node.create_timer(0.01, tick)
    executor.add_node(node)
    try:
        with pytest.raises(TypeError, match='coroutine'):
            _spin_until(executor, lambda: False, timeout=2.0)
    finally:
        executor.shutdown()
        node.destroy_node()
