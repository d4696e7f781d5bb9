"""Session-wide test set-up: keep any DDS on loopback, on a domain of its own, logs in a tmp dir.

The environment is set at import time, before any test module can import rclpy.
"""
import atexit
import os
from pathlib import Path
import shutil
import signal
import tempfile

import pytest

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# Per run, so that two test runs on one machine never see each other: 1..101 (0 avoided).
os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 101)
_ROS_LOG_DIR = tempfile.mkdtemp(prefix='bpe-test-roslog-')
os.environ['ROS_LOG_DIR'] = _ROS_LOG_DIR
atexit.register(shutil.rmtree, _ROS_LOG_DIR, ignore_errors=True)

# A shell that starts the suite as a background job (`cmd &` without job control) leaves
# SIGINT ignored, and every process a test starts would inherit that: the Ctrl-C tests would
# then see a `bearing-pose run` that cannot be interrupted. Their processes get the default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO_ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope='session')
def repo_root() -> Path:
    """Root of the repository (the folder holding package.xml)."""
    return REPO_ROOT


@pytest.fixture()
def context():
    """A fresh rclpy context for in-process nodes (rclpy imported here, after the environment
    above is set)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)
