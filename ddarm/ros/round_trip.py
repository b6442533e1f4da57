"""The bare DDS round trip: the ceiling of a lockstep sample, measured with nothing of ddarm's loop in it.

Two processes on the executor every ddarm node spins with: this one publishes a 3-joint JointState on
`ping` and waits for it to come back on `pong` from an echo process, then sends the next, with the
profile of the episode's states and commands (`SAMPLE_QOS`). One lockstep sample is one such round
trip (a state out, a command back) plus the plant's and the controller's work, so the ratio of a
lockstep episode's samples per second to these round trips per second says how much of the DDS
ceiling ddarm's loop reaches.

`serialized`: both sides hand rclpy the CDR bytes (subscriptions with raw=True, bytes published), as the
plant and the controller do (ddarm.ros.cdr), so that the round trip is DDS's alone; otherwise rclpy's
JointState messages, converted at each take and publish.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

from ddarm.errors import DdarmError
from ddarm.ros.lifetime import child_environment, follow_parent, stop_processes

PING_TOPIC = 'ping'
PONG_TOPIC = 'pong'
JOINTS = ('joint_1', 'joint_2', 'joint_3')
# Until the echo answers, a ping goes out this often: one sent before both sides matched is lost.
HELLO_PERIOD_S = 0.1
START_TIMEOUT_S = 30.0


class RoundTripError(DdarmError, RuntimeError):
    """The echo process did not answer, or died."""


def _state(n: int, serialized: bool):
    from ddarm.ros.cdr import JointStateEncoder
    from ddarm.ros.interface import joint_state_msg

    values = np.full(len(JOINTS), 0.1 * n)
    if serialized:
        return JointStateEncoder(JOINTS).encode(n * 1e-3, values, values, values)
    return joint_state_msg(list(JOINTS), n * 1e-3, values, values, values)


def echo(namespace: str, serialized: bool) -> int:
    """The echo process: every JointState heard on `ping` goes back unchanged on `pong`, until SIGTERM or SIGINT."""
    import rclpy
    from sensor_msgs.msg import JointState

    from ddarm.ros.executable import run_node
    from ddarm.ros.interface import SAMPLE_QOS

    def make_node():
        node = rclpy.create_node('round_trip_echo', namespace=namespace)
        publisher = node.create_publisher(JointState, PONG_TOPIC, SAMPLE_QOS)
        node.create_subscription(JointState, PING_TOPIC, publisher.publish, SAMPLE_QOS, raw=serialized)
        return node

    return run_node(make_node, 'round_trip_echo', ())


def measure_round_trips(count: int, timeout: float = 120.0, serialized: bool = False) -> dict:
    """`count` round trips to an echo process of its own, one at a time: their rate and their latency quantiles.

    Its participant is this process's only one (`round_trips_in_process` keeps it so beside a graph session).
    """
    import rclpy
    from rclpy.task import Future
    from sensor_msgs.msg import JointState

    from ddarm.ros.executors import node_executor
    from ddarm.ros.cdr import read_stamp
    from ddarm.ros.interface import SAMPLE_QOS
    from ddarm.ros.session import session_namespace

    namespace = session_namespace()
    # Its output only if it fails: a SIGTERM that lands in a callback is logged as a fatal exception.
    log = tempfile.TemporaryFile()
    process = subprocess.Popen([sys.executable, '-m', 'ddarm.ros.round_trip', 'echo', namespace, str(serialized)],
                               env=child_environment(), start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(args=[], context=context)  # not sys.argv: ddarm's command line holds no ROS arguments
    node = rclpy.create_node('round_trip_ping', namespace=namespace, context=context)
    executor = node_executor(context)
    executor.add_node(node)
    publisher = node.create_publisher(JointState, PING_TOPIC, SAMPLE_QOS)
    sent = np.zeros(count + 1, dtype=np.int64)
    returned = np.zeros(count + 1, dtype=np.int64)
    started, finished = Future(), Future()
    next_sample = [0]
    messages = [_state(n, serialized) for n in range(count + 1)]  # built beforehand: the measurement is DDS's

    def send(n: int) -> None:
        sent[n] = time.perf_counter_ns()
        publisher.publish(messages[n])

    def on_pong(msg) -> None:
        stamp = read_stamp(msg, 'pong') if serialized else msg.header.stamp
        n = round(stamp.nanosec * 1e-6) + 1000 * stamp.sec
        if not started.done():
            started.set_result(True)  # the hello came back: both directions are matched; sample 0 was the hello
        elif n != next_sample[0]:
            return  # a late hello
        returned[n] = time.perf_counter_ns()
        if n == count:
            finished.set_result(True)
            return
        next_sample[0] = n + 1
        send(n + 1)

    node.create_subscription(JointState, PONG_TOPIC, on_pong, SAMPLE_QOS, raw=serialized)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not started.done():
            if process.poll() is not None:
                log.seek(0)
                raise RoundTripError(f'the echo process exited with code {process.returncode}: '
                                     f'{log.read().decode(errors="replace")[-2000:]}')
            if time.monotonic() > deadline:
                raise RoundTripError(f'the echo process did not answer within {START_TIMEOUT_S} s')
            send(0)
            executor.spin_until_future_complete(started, timeout_sec=HELLO_PERIOD_S)
        begin = time.perf_counter_ns()
        next_sample[0] = 1
        send(1)
        executor.spin_until_future_complete(finished, timeout_sec=timeout)
        if not finished.done():
            raise RoundTripError(f'{next_sample[0] - 1} of {count} round trips in {timeout} s: the echo stopped '
                                 'answering')
        wall = (returned[count] - begin) * 1e-9
        latencies = (returned[1:] - sent[1:]) * 1e-6
    finally:
        stop_processes([process], signal.SIGTERM)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        log.close()
    return {'round_trips': count, 'wall_time_s': wall, 'round_trips_per_s': count / wall,
            'latency_p50_ms': float(np.percentile(latencies, 50)),
            'latency_p99_ms': float(np.percentile(latencies, 99))}


def round_trips_in_process(count: int, timeout: float = 120.0, serialized: bool = False) -> dict:
    """`measure_round_trips` in a process of its own: a driver's process keeps its DDS participant to itself."""
    done = subprocess.run([sys.executable, '-m', 'ddarm.ros.round_trip', 'ping', str(count), str(timeout),
                           str(serialized)],
                          env=child_environment(), capture_output=True, text=True, timeout=timeout + 2 * START_TIMEOUT_S)
    if done.returncode != 0:
        raise RoundTripError(f'the round-trip measurement exited with code {done.returncode}: {done.stderr[-2000:]}')
    return json.loads(done.stdout)


if __name__ == '__main__':
    if sys.argv[1] == 'echo':
        raise SystemExit(echo(sys.argv[2], sys.argv[3] == 'True'))
    follow_parent()
    print(json.dumps(measure_round_trips(int(sys.argv[2]), float(sys.argv[3]), sys.argv[4] == 'True')))
