"""The controller nodes: PD + gravity or computed torque on /joint_states, publishing the effort for each sample."""

from __future__ import annotations

import json
import sys
from collections import deque

import numpy as np
import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from ddarm.control.gains import gains_from_parameters
from ddarm.control.laws import (CONTROLLERS, MAX_DELAY, GainError, Measurement, ReferencePoint, SampledController,
                                checked_delay, checked_friction, gravity_feedforward, make_law, warm_up)
from ddarm.physics.arm import Arm, ModelError
from ddarm.physics.dynamics import chain_from_model
from ddarm.physics.plant import NODE_PERIOD_RANGE
from ddarm.ros.interface import (EFFORT_COMMAND_TOPIC, JOINT_STATES_TOPIC, REFERENCE_QOS, REFERENCE_TOPIC,
                                     SAMPLE_QOS, Reference, descriptor, joint_state_msg, plain_parameters,
                                     proposed_values, read_joint_state, read_reference,
                                     refuse_undeclared_parameters, undeclared_overrides)
from ddarm.ros.executable import run_node
from ddarm.samples import MessageError

# States that arrive before the programmed motion wait for it, up to this many.
MAX_WAITING_STATES = 10_000


def effective_gains(law: str, values: dict, model: Arm, reference: Reference | None):
    """K_p, K_v from the parameters (`gains_from_parameters`); None while the PD + gravity rule waits for q_f."""
    return gains_from_parameters(law, values['omega'], values['kp'], values['kv'], model,
                                 None if reference is None else reference.q[-1])


class ControllerNode(Node):
    """One law behind ROS: the command for sample n from the state of sample n - d and the reference at t_n.

    Each command is a JointState stamped with the sample it applies to, carrying names and effort.
    A state at t = 0 starts a new episode (the delay buffer is cleared), as does ~/reset.
    """

    def __init__(self, law: str, **kwargs) -> None:
        if law not in CONTROLLERS:
            raise GainError(f'controller must be one of {CONTROLLERS}, got {law!r}')
        super().__init__(law, **kwargs)
        self.law_name = law
        self.incompatible_qos_events = 0
        self.refused_messages = 0
        self._declare_parameters()
        values = proposed_values(self, ())
        self.model = Arm.from_urdf(values['urdf'] or None)
        self.chain = chain_from_model(self.model.model)
        self.joints = list(values['joints']) if values['joints'] else self.model.joint_names
        if self.joints != self.model.joint_names:
            raise ModelError(f'joints {self.joints} must be the URDF joints in URDF order {self.model.joint_names}')
        unknown = undeclared_overrides(self, kwargs.get('parameter_overrides') or ())
        if unknown:
            raise GainError(f'unknown parameters {unknown} (not {law} parameters: a typo?)')
        self.period = values['period']
        self.max_sample_gap = values['max_sample_gap']
        self.reference: Reference | None = None
        self.reference_gravity: np.ndarray | None = None  # Ĝ(q^d) at each reference sample, for PD + gravity
        gains = effective_gains(law, values, self.model, None) or (np.ones(self.model.dof),) * 2
        self.controller = SampledController(
            make_law(law, self.chain, *gains, *self._friction(values)), checked_delay(values['compute_delay_steps']))
        warm_up(self.chain)
        self.gains_ready = values['omega'] == 0 or law == 'computed_torque'
        refuse_undeclared_parameters(self, law)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.command_publisher = self.create_publisher(
            JointState, EFFORT_COMMAND_TOPIC, SAMPLE_QOS,
            event_callbacks=PublisherEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.state_subscription = self.create_subscription(
            JointState, JOINT_STATES_TOPIC, self._on_state, SAMPLE_QOS,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.reference_subscription = self.create_subscription(
            JointTrajectory, REFERENCE_TOPIC, self._on_reference, REFERENCE_QOS,
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._incompatible_qos, use_default_callbacks=False))
        self.reset_service = self.create_service(Trigger, '~/reset', self._on_reset)
        self.status_service = self.create_service(Trigger, '~/status', self._on_status)
        # Counts every change of what the commands are computed from (parameters, reference, reset), so a
        # driver can tell whether anyone touched the controller while an episode ran.
        self.configuration = 0
        self.last_sample: int | None = None
        self.waiting: deque = deque(maxlen=MAX_WAITING_STATES)
        self.get_logger().info(self._describe())

    def _declare_parameters(self) -> None:
        double_array = Parameter.Type.DOUBLE_ARRAY
        declared = [
            ('urdf', '', descriptor('URDF of the controller model ("" = the ddarm arm)', read_only=True)),
            ('joints', Parameter.Type.STRING_ARRAY, descriptor('joint names in URDF order, the order of kp and kv '
                                                               '(unset: from the URDF)', read_only=True)),
            ('kp', double_array, descriptor('K_p diagonal, one positive value per joint')),
            ('kv', double_array, descriptor('K_v diagonal, one positive value per joint')),
            ('omega', 0.0, descriptor('ω rule of section 2 when > 0 (overrides kp, kv)', floating=(0.0, 1e4))),
            ('compute_delay_steps', 1, descriptor('compute delay d in samples', integer=(0, MAX_DELAY))),
            ('period', 0.01, descriptor('sampling period Δ in s (to read sample indices from stamps)',
                                        floating=NODE_PERIOD_RANGE)),
            ('max_sample_gap', 100, descriptor('states more than this many samples ahead of the expected one '
                                               'are refused', integer=(1, 1_000_000))),
            ('viscous_friction', double_array, descriptor("model friction F̂ (computed torque), N m s/rad")),
            ('coulomb_friction', double_array, descriptor("model friction F̂ (computed torque), N m")),
        ]
        for name, default, described in declared:
            self.declare_parameter(name, default, described)

    def _friction(self, values: dict) -> tuple:
        return tuple(checked_friction(name, values[name] if values[name] is not None and len(values[name]) else None,
                                      self.model.dof) for name in ('viscous_friction', 'coulomb_friction'))

    def _check_parameters(self, changes) -> SetParametersResult:
        values = proposed_values(self, changes)
        try:
            effective_gains(self.law_name, values, self.model, self.reference)
            checked_delay(values['compute_delay_steps'])
            self._friction(values)
        except GainError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, changes) -> None:
        values = proposed_values(self, ())
        self.period = values['period']
        self.max_sample_gap = values['max_sample_gap']
        self._set_gains(values)
        self.controller.law = make_law(self.law_name, self.chain, self.controller.law.kp, self.controller.law.kv,
                                       *self._friction(values))
        if values['compute_delay_steps'] != self.controller.delay:
            self.controller.set_delay(values['compute_delay_steps'])
        self.configuration += 1
        self.get_logger().info(self._describe())

    def _set_gains(self, values: dict) -> None:
        gains = effective_gains(self.law_name, values, self.model, self.reference)
        if gains is not None:
            self.controller.law.set_gains(*gains)
        self.gains_ready = gains is not None

    def _describe(self) -> str:
        law = self.controller.law
        return (f'{self.law_name}: kp {np.round(law.kp, 6).tolist()}, kv {np.round(law.kv, 6).tolist()}, '
                f'delay {self.controller.delay} sample(s), period {self.period} s')

    def _incompatible_qos(self, event) -> None:
        self.incompatible_qos_events += 1
        self.get_logger().error(f'incompatible QoS with a peer (policy {event.last_policy_kind}): '
                                'samples will not flow; use the profiles of ddarm.ros.interface')

    def _on_reference(self, msg: JointTrajectory) -> None:
        try:
            self.reference = read_reference(msg, self.joints, self.period)
        except MessageError as error:
            self.refused_messages += 1
            self.get_logger().error(f'refused: {error}')
            return
        self.reference_gravity = gravity_feedforward(self.model, self.reference.q)
        self._set_gains(proposed_values(self, ()))
        self.configuration += 1
        self.get_logger().info(f'reference of {len(self.reference.times)} samples; {self._describe()}')
        while self.waiting:
            self._command(self.waiting.popleft())

    def _on_reset(self, request, response):
        """Clear the delay buffer; the reply (JSON, as ~/status gives) says what the next episode will run with."""
        self.controller.reset()
        self.last_sample = None
        self.waiting.clear()
        self.configuration += 1
        return self._on_status(request, response)

    def _on_status(self, request, response):
        """What the commands are computed from, changing nothing: gains, delay, reference, configuration count."""
        response.success = self.reference is not None and self.gains_ready
        law = self.controller.law
        response.message = json.dumps({
            'ready': response.success, 'kp': law.kp.tolist(), 'kv': law.kv.tolist(),
            'delay': self.controller.delay, 'period': self.period,
            'reference_samples': 0 if self.reference is None else len(self.reference.times),
            'reference_final': None if self.reference is None else self.reference.q[-1].tolist(),
            'parameters': plain_parameters(proposed_values(self, ())), 'configuration': self.configuration})
        return response

    def _on_state(self, msg: JointState) -> None:
        try:
            state = read_joint_state(msg, self.joints, self.period)
        except MessageError as error:
            self.refused_messages += 1
            self.get_logger().error(f'refused, no command sent: {error}')
            return
        expected = 0 if self.last_sample is None else self.last_sample + 1
        if state.n > expected + self.max_sample_gap:
            # Accepting it would make every real state that follows look like one from the past.
            self.refused_messages += 1
            self.get_logger().error(f'refused a state for sample {state.n}: more than max_sample_gap = '
                                    f'{self.max_sample_gap} samples after the expected sample {expected}')
            return
        if state.n == 0:
            self.controller.reset()
            self.waiting.clear()
        elif self.last_sample is not None and state.n <= self.last_sample:
            self.refused_messages += 1
            self.get_logger().error(f'refused a state for sample {state.n}: sample {self.last_sample} came already')
            return
        elif self.last_sample is not None and state.n > self.last_sample + 1:
            self.get_logger().warning(f'samples {self.last_sample + 1}..{state.n - 1} never arrived')
        self.last_sample = state.n
        if self.reference is None or not self.gains_ready:
            self.waiting.append(state)
            return
        self._command(state)

    def _command(self, state) -> None:
        q_ref, v_ref, a_ref = self.reference.point(state.n)
        measurement = Measurement(state.q, state.v, q_ref, v_ref)
        gravity_ref = self.reference_gravity[min(state.n, len(self.reference_gravity) - 1)]
        torque = self.controller.step(measurement, ReferencePoint(q_ref, v_ref, a_ref), gravity_ref)
        if not np.all(np.isfinite(torque)):
            self.get_logger().error(f'no command for sample {state.n}: the law gave {torque.tolist()}')
            return
        self.command_publisher.publish(joint_state_msg(self.joints, state.n * self.period, effort=torque))


def main(args=None, law: str | None = None) -> int:
    args = sys.argv if args is None else args
    if law is None:
        non_ros = rclpy.utilities.remove_ros_args(args)[1:]
        if len(non_ros) != 1 or non_ros[0] not in CONTROLLERS:
            print(f'usage: controller {{{",".join(CONTROLLERS)}}} [--ros-args ...]', file=sys.stderr)
            return 2
        law = non_ros[0]
    return run_node(lambda: ControllerNode(law), law, (GainError, ModelError), args)


def main_pd_gravity(args=None) -> int:
    return main(args, 'pd_gravity')


def main_computed_torque(args=None) -> int:
    return main(args, 'computed_torque')


if __name__ == '__main__':
    raise SystemExit(main())
