"""Shared by the graph tests: the plant and a controller as nodes of this process, driven by the episode driver;
spinning an executor until a condition holds, and calling services (lifecycle ones too) from a test."""

import time
from contextlib import contextmanager

import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from ddarm_control.node import ControllerNode
from ddarm_sim.node import PlantNode
from ddarm.episodes.spec import plan_episode
from ddarm.ros.interface import flat_parameters
from ddarm.ros.driver import GraphDriver
from ddarm.ros.node_parameters import node_parameters


def overrides(values: dict) -> list:
    return [Parameter(name, value=value) for name, value in values.items()]


def spin_until(executor, condition, resend=None, timeout: float = 30.0) -> None:
    """Spin until `condition()`; `resend()` again now and then (a best-effort /clock or state may be lost)."""
    deadline, sent = time.monotonic() + timeout, time.monotonic()
    while not condition():
        assert time.monotonic() < deadline, 'condition not met in time (a hang guard, not a timing check)'
        executor.spin_once(timeout_sec=0.01)
        if resend is not None and time.monotonic() - sent > 0.5:
            resend()
            sent = time.monotonic()


def call_service(executor, client, request, again_after: float | None = None):
    """The reply of a service, once the service is up. `again_after` (s, for a request that may be repeated): asked
    again when no reply came in that long: a reply sent before the server matched the client's reply reader is lost
    (DDS discovery is not symmetric), and `service_is_ready` says only that the request side matched."""
    spin_until(executor, client.service_is_ready)
    future, asked = client.call_async(request), time.monotonic()

    def answered() -> bool:
        nonlocal future, asked
        if not future.done() and again_after is not None and time.monotonic() - asked > again_after:
            client.remove_pending_request(future)
            future, asked = client.call_async(request), time.monotonic()
        return future.done()
    spin_until(executor, answered)
    return future.result()


def change_state(executor, client, transition: int) -> bool:
    """Ask a node's ~/change_state (`client`) for a lifecycle transition: whether it was made."""
    return call_service(executor, client, ChangeState.Request(transition=Transition(id=transition))).success


def lifecycle_state(executor, client) -> str:
    """A node's lifecycle state, from its ~/get_state (`client`)."""
    return call_service(executor, client, GetState.Request(), again_after=2.0).current_state.label


class InProcessGraph:
    """Plant, controller and driver nodes under one executor, in one context."""

    def __init__(self, context, spec, plant_extra=None, controller_extra=None, bag=None):
        self.spec, self.plan = spec, plan_episode(spec)
        parameters = node_parameters(spec, self.plan)
        plant_values = {**parameters['plant']['ros__parameters'], **(plant_extra or {})}
        controller_values = {**flat_parameters(parameters[spec.controller]['ros__parameters']),
                             **(controller_extra or {})}
        self.plant = PlantNode(context=context, parameter_overrides=overrides(plant_values))
        self.controller = ControllerNode(spec.controller, context=context,
                                         parameter_overrides=overrides(controller_values))
        self.driver = GraphDriver(context=context)
        self.bag = bag
        self.executor = SingleThreadedExecutor(context=context)
        for node in (self.plant, self.controller, self.driver):
            self.executor.add_node(node)

    def run(self, timeout=60.0):
        return self.driver.run_episode(self.executor, self.spec, self.plan, self.bag, timeout=timeout)

    def close(self):
        self.executor.shutdown()
        for node in (self.plant, self.controller, self.driver):
            node.destroy_node()


def run_in_process(context, spec, **options):
    """One episode of `spec` on in-process plant, controller and driver nodes."""
    graph = InProcessGraph(context, spec, **options)
    try:
        return graph.run()
    finally:
        graph.close()


@contextmanager
def parameter_client(context, node, name: str):
    """A client of `node`'s parameter services (as `ros2 param` is), once they are up, and wait(future): spins the
    node and the client until the future is done and returns its result."""
    client_node = rclpy.create_node(f'{name}_parameter_client', context=context)
    executor = SingleThreadedExecutor(context=context)
    for each in (node, client_node):
        executor.add_node(each)
    client = AsyncParameterClient(client_node, name)

    def wait(future):
        while not future.done():
            executor.spin_once(timeout_sec=0.05)
        return future.result()

    try:
        while not client.services_are_ready():
            executor.spin_once(timeout_sec=0.05)
        yield client, wait
    finally:
        executor.shutdown()
        client_node.destroy_node()
