"""The managed (lifecycle) node every ddarm node is: rclpy's LifecycleNode, with two of its Jazzy faults mended."""

from __future__ import annotations

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode


class ManagedNode(LifecycleNode):
    """rclpy.lifecycle.LifecycleNode as a node process can live with it.

    ~/change_state answers success False for a transition the current state does not have (activate from
    unconfigured), as it does for an unknown label: rclpy (Jazzy) lets rcl's error out of the service callback,
    and out of the executor's spin, which would end the node's process. rcl_lifecycle logs the refusal.
    `destroy_node` destroys the lifecycle state machine too: rclpy leaves it, and with it the node in the graph,
    to the garbage collector, and a second node of the same name would then be seen beside the next.
    """

    def __init__(self, node_name: str, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        service = getattr(self, '_service_change_state', None)
        if service is None:  # enable_communication_interface=False
            return
        answer = service.callback

        def change_state(request, response):
            try:
                return answer(request, response)
            except _rclpy.RCLError:
                response.success = False
                return response
        service.callback = change_state

    def destroy_node(self) -> None:
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()
