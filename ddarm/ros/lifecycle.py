"""The managed (lifecycle) node every ddarm node is: rclpy's LifecycleNode, the one-step start at launch, the
configure and release every node does alike, and two of rclpy's Jazzy faults mended."""

from __future__ import annotations

from collections.abc import Callable

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer


class ManagedNode(LifecycleNode):
    """rclpy.lifecycle.LifecycleNode as ddarm's node processes live with it.

    A node says what configure makes (`_configure`) and what cleanup frees (`_release`); `launch` is the one-step
    start every documented command relies on. A configure that fails leaves the node unconfigured, its error in
    `configure_error` (logged; raised from `launch`).

    ~/change_state answers success False for a transition the current state does not have (activate from
    unconfigured), as it does for an unknown label: rclpy (Jazzy) lets rcl's error out of the service callback,
    and out of the executor's spin, which would end the node's process. rcl_lifecycle logs the refusal.
    `destroy_node` destroys the lifecycle state machine too: rclpy leaves it, and with it the node in the graph,
    to the garbage collector, and a second node of the same name would then be seen beside the next.
    """

    def __init__(self, node_name: str, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.configure_error: Exception | None = None
        self.launching = False  # in `launch`: a refusal is raised from the constructor, not logged
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

    def launch(self, refused: type[Exception], after_configure: Callable[[], None] | None = None) -> None:
        """Configure, then activate, now; a node refused is destroyed (gone from the graph now, not when collected)
        and the error raised: configure's as it is, else `refused`. `after_configure`, a check that needs what
        configure made, runs between the two."""
        self.launching = True
        try:
            if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                self.destroy_node()
                raise self.configure_error or refused(f'{self.get_name()} did not configure')
            try:
                if after_configure is not None:
                    after_configure()
            except Exception:
                self.destroy_node()
                raise
            if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                self.destroy_node()
                raise refused(f'{self.get_name()} did not activate')
        finally:
            self.launching = False

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except Exception as error:  # kept; at launch raised from the constructor as it is
            self._release()
            self.configure_error = error
            if not self.launching:
                self.get_logger().error(f'configure refused: {error}')
            return TransitionCallbackReturn.FAILURE
        self.configure_error = None
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _configure(self) -> None:
        raise NotImplementedError

    def _release(self) -> None:
        raise NotImplementedError

    def destroy_entities(self, *names: str) -> None:
        """Destroy the publishers, subscriptions, timers and services held in these attributes, and unset them."""
        for name in names:
            entity = getattr(self, name, None)
            if isinstance(entity, Publisher):
                self.destroy_publisher(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            elif isinstance(entity, Timer):
                self.destroy_timer(entity)
            elif isinstance(entity, Service):
                self.destroy_service(entity)
            setattr(self, name, None)

    def destroy_node(self) -> None:
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()
