"""Test isolation for DDS: each test process takes a ROS domain ID no other running test process holds."""

import fcntl
import os
import tempfile
from pathlib import Path

import pytest

# Domain IDs whose Fast DDS ports stay valid; a lock file per ID tells running processes apart.
_DOMAIN_IDS = range(1, 200)
_held_locks = []


def claim_domain_id() -> int:
    """A domain ID no other running test process holds, reserved until this process exits."""
    folder = Path(tempfile.gettempdir()) / 'ddarm-test-domains'
    folder.mkdir(exist_ok=True)
    start = os.getpid() % len(_DOMAIN_IDS)
    for offset in range(len(_DOMAIN_IDS)):
        domain_id = _DOMAIN_IDS[(start + offset) % len(_DOMAIN_IDS)]
        handle = open(folder / f'{domain_id}.lock', 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            continue
        _held_locks.append(handle)
        return domain_id
    raise RuntimeError('every test ROS domain ID is taken by another running test process')


def pytest_configure(config):
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_id())
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


def pytest_unconfigure(config):
    """The domain IDs released as the run ends (closed here, not left to the interpreter's end, which warned)."""
    while _held_locks:
        _held_locks.pop().close()


@pytest.fixture(scope='session', autouse=True)
def compiled_loop():
    """The compiled loop built once, before any test starts a node process that loads it (a fresh checkout
    compiles it here, about a minute on two cores, instead of in every node, past their peer timeouts)."""
    from ddarm.episodes.engine import warm_up

    warm_up()


@pytest.fixture
def ros_context():
    """A fresh rclpy context for one test, shut down afterwards."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)
