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
# The processes a test starts run this checkout's package: the venv's editable install points
# at one checkout, and a git worktree's tests would otherwise start another's nodes.
os.environ['PYTHONPATH'] = os.pathsep.join(
    [str(REPO_ROOT), *filter(None, [os.environ.get('PYTHONPATH')])])


@pytest.fixture(scope='session')
def repo_root() -> Path:
    """Root of the repository (the folder holding package.xml)."""
    return REPO_ROOT


NOT_A_DDS_TEST = 'unset: a test that starts DDS carries @pytest.mark.dds'


@pytest.fixture(autouse=True)
def _dds_only_when_marked(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test without the `dds` marker gets a ROS_DOMAIN_ID that rcl refuses ("not an integral
    number"): whatever it starts in-process or inherits the environment cannot join DDS, so
    `-m 'not dds'` really is the suite without DDS."""
    if request.node.get_closest_marker('dds') is None:
        monkeypatch.setenv('ROS_DOMAIN_ID', NOT_A_DDS_TEST)


@pytest.fixture()
def context(request: pytest.FixtureRequest):
    """A fresh rclpy context for in-process nodes (rclpy imported here, after the environment
    above is set)."""
    if request.node.get_closest_marker('dds') is None:
        pytest.fail(f'{request.node.nodeid} uses the rclpy context: mark it @pytest.mark.dds')
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)
