"""run_node's life cycle in a real process: a signal stops the spin loop and the node is torn
down in order (exit 0); a teardown that hangs is cut short by the watchdog, said loudly, even
when it hangs holding the GIL, and ends by the signal the launcher knows
(plan.dds.TEARDOWN_HUNG)."""
import os
import signal
import subprocess
import sys
import time

import pytest

from bearing_pose_estimation.plan import dds

pytestmark = pytest.mark.dds

CHILD = r'''
import sys, time
from rclpy.node import Node
from bearing_pose_estimation.ros import node_main

node_main.TEARDOWN_TIMEOUT_S = 1.0
hang = sys.argv[1]

class Probe(Node):
    def __init__(self):
        super().__init__('probe')
        self.create_timer(0.01, lambda: None)
        print('READY', flush=True)

    def destroy_node(self):
        print('DESTROYING', flush=True)
        super().destroy_node()  # the last node: the DDS participant goes with it
        if hang == 'hang':
            time.sleep(60)  # what a deadlocked teardown looks like from Python
        elif hang == 'hang_holding_gil':  # a C call that blocks without releasing the GIL
            import ctypes
            ctypes.PyDLL(None).sleep(60)

raise SystemExit(node_main.run_node(Probe, 'probe'))
'''


def _start(mode: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, '-c', CHILD, mode], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    assert proc.stdout.readline().strip() == 'READY'
    return proc


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_loop_and_the_node_exits_0(sig):
    proc = _start('clean')
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert 'DESTROYING' in out
    assert f'{signal.Signals(sig).name}: shutting down' in err


def test_a_hung_teardown_is_cut_short_by_the_watchdog():
    shm = dds.shm_files()
    proc = _start('hang')
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert time.monotonic() - t0 < 10.0
    # Its work was done: it ends as the launcher expects a hung teardown to (counted clean)
    assert proc.returncode == dds.TEARDOWN_HUNG, err
    assert 'DDS teardown did not finish in 1 s' in err and 'fastdds shm clean' in err
    assert 'in destroy_node' in err  # the stack dump shows where it hung
    assert not dds.leaked_shm(shm)  # the hang came after the participant was released


def test_a_teardown_hung_holding_the_gil_still_ends():
    """The Python watchdog cannot run then (the Fast DDS deadlock holds the GIL); the kernel's
    alarm one second later runs faulthandler's C handler (the stacks), then ends the process
    by SIGALRM, which the launcher counts as a hung teardown, not a crash."""
    proc = _start('hang_holding_gil')
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert time.monotonic() - t0 < 10.0
    assert proc.returncode == dds.TEARDOWN_HUNG, err
    assert 'in destroy_node' in err and 'DDS teardown did not finish' not in err
