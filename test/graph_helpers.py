"""Shared by the graph tests: the plant and a controller as nodes of this process, driven by the episode driver."""

from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from ddarm_control.node import ControllerNode
from ddarm_sim.node import PlantNode
from ddarm.episodes.spec import plan_episode
from ddarm.ros.driver import GraphDriver
from ddarm.ros.node_parameters import node_parameters


def overrides(values: dict) -> list:
    return [Parameter(name, value=value) for name, value in values.items()]


class InProcessGraph:
    """Plant, controller and driver nodes under one executor, in one context."""

    def __init__(self, context, spec, plant_extra=None, controller_extra=None, bag=None):
        self.spec, self.plan = spec, plan_episode(spec)
        parameters = node_parameters(spec, self.plan)
        plant_values = {**parameters['plant']['ros__parameters'], **(plant_extra or {})}
        controller_values = {**parameters[spec.controller]['ros__parameters'], **(controller_extra or {})}
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
