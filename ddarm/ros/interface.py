"""The ROS 2 interface every ddarm node shares: topic names, QoS profiles, message <-> array conversion,
and the parameter checks (descriptors, undeclared or unknown parameters).

Conversions refuse bad messages with a MessageError naming the problem, before any
number reaches the core.
"""

from __future__ import annotations

import array
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Duration, Time
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from ddarm.control.laws import GainError
from ddarm.deprecation import deprecation_notice
from ddarm.ros.cdr import stamp_of
# A node's life as an executable lives in ddarm.ros.executable; the nodes have imported these from here.
from ddarm.ros.executable import context_arguments
from ddarm.ros.parameter_files import given_parameters
from ddarm.ros.parameter_schema import GAIN_KEYS, NodeParameter, aliases, joint_gains, parameters_of
# Defined with the controllers' parameters (command_topic's default), named here with the other topics.
from ddarm.ros.parameter_schema import EFFORT_COMMAND_TOPIC  # noqa: F401
from ddarm.samples import (MAX_JOINTS, MessageError, checked_reference, finite_array, joint_order, sample_at,
                           stamp_ns)

JOINT_STATES_TOPIC = 'joint_states'
REFERENCE_TOPIC = 'reference'
CLOCK_TOPIC = '/clock'
DIAGNOSTICS_TOPIC = '/diagnostics'

# One profile per topic, used on both sides: a reliable subscriber hears nothing from a
# best-effort publisher. Lockstep needs every sample, so states and commands are reliable.
# A deep keep-last history (10 s at 100 Hz): a recorder that lags keeps every sample, and one
# that died never blocks the plant (keep-all would, until DDS noticed). A recorder that lags
# further loses samples and says so: the driver refuses an episode with a sample missing.
SAMPLE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
# The programmed motion is latched: a controller started later still receives it.
REFERENCE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Reliable on our side so the recorder keeps every tick; best-effort /clock subscribers still match.
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
# A robot (or a plant the controller did not start) in real time: only the latest state and command matter.
# Best effort on the state side hears reliable publishers too (joint_state_broadcaster's, the plant's) and
# best-effort ones (drivers publishing sensor-data QoS); reliable commands reach every subscriber
# (forward_command_controller listens reliably), and a depth of 1 never delivers a backlog of old efforts.
ROBOT_STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.VOLATILE)
ROBOT_COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)
# How a controller sends its efforts: a stamped JointState with names (ddarm's plant), or the bare array a
# ros2_control forward_command_controller on effort interfaces takes (`/<controller>/commands`).
COMMAND_TYPES = ('joint_state', 'float64_multi_array')


def time_msg(seconds: float) -> Time:
    stamp = stamp_of(seconds)
    return Time(sec=stamp.sec, nanosec=stamp.nanosec)


def duration_msg(seconds: float) -> Duration:
    stamp = time_msg(seconds)
    return Duration(sec=stamp.sec, nanosec=stamp.nanosec)


def seconds(stamp: Time | Duration) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def sample_index(stamp: Time, period: float) -> int:
    """n for a stamp t_n = n Δ; refuses a negative stamp or one between sample instants."""
    return sample_at(seconds(stamp), period)


@dataclass(frozen=True)
class StateSample:
    """A JointState read as the core wants it: sample index, and arrays in our joint order."""

    n: int
    q: np.ndarray
    v: np.ndarray
    effort: np.ndarray | None


def read_joint_state(msg: JointState, joints: list[str], period: float, what: str = 'joint state',
                     need_state: bool = True, need_effort: bool = False) -> StateSample:
    """Validate and reorder a JointState by name; positions and velocities required unless told otherwise."""
    order = joint_order(msg.name, joints, what)
    n = sample_index(msg.header.stamp, period)
    count = len(joints)

    def field(values, label: str, needed: bool) -> np.ndarray | None:
        if not needed and len(values) == 0:
            return None
        return finite_array(values, what, label, count)[order]

    return StateSample(n, field(msg.position, 'position', need_state), field(msg.velocity, 'velocity', need_state),
                       field(msg.effort, 'effort', need_effort))


@dataclass(frozen=True)
class RobotState:
    """A JointState from a robot read for our joints: its stamp (ns, on the publisher's clock) and q, q̇."""

    stamp: int
    q: np.ndarray
    v: np.ndarray


def read_robot_state(msg: JointState, joints: list[str], what: str = 'joint state') -> RobotState:
    """Our joints' positions and velocities by name from a JointState that may carry others (a gripper's, in any
    order): those are ignored, unchecked; a joint of ours missing, a duplicate name, or arrays of another length
    than the names are refused. The stamp is any time (a robot's clock), never a sample index."""
    names = list(msg.name)
    if len(names) > MAX_JOINTS:
        raise MessageError(f'{what}: {len(names)} joint names is more than the {MAX_JOINTS} allowed')
    if len(set(names)) != len(names):
        raise MessageError(f'{what}: duplicate joint names {sorted({n for n in names if names.count(n) > 1})}')
    missing = [joint for joint in joints if joint not in names]
    if missing:
        raise MessageError(f'{what}: missing joints {missing} (it names {names}; controlled: {joints})')
    order = np.array([names.index(joint) for joint in joints])

    def field(values, label: str) -> np.ndarray:
        if len(values) != len(names):
            raise MessageError(f'{what}: {label} has {len(values)} values for {len(names)} joint names')
        ours = np.array(values, dtype=float)[order]
        bad = [joint for joint, value in zip(joints, ours) if not np.isfinite(value)]
        if bad:
            raise MessageError(f'{what}: {label} is not finite for {bad}: {ours[~np.isfinite(ours)].tolist()}')
        return ours

    stamp = stamp_ns(msg.header.stamp)
    return RobotState(stamp, field(msg.position, 'position'), field(msg.velocity, 'velocity'))


@dataclass(frozen=True)
class RobotLimits:
    """What a controller in robot mode (sampling timer) takes from a robot and sends it, by joint: positions
    within the URDF's limits widened by `margin`, velocities within `velocity` (a multiple of the URDF's limits),
    moves between states no faster than that, and efforts clamped to `effort`. inf: no bound; effort None: no
    clamping."""

    joints: tuple[str, ...]
    lower: np.ndarray  # the URDF's <limit lower> (-inf for a continuous joint or none)
    upper: np.ndarray
    margin: float  # rad or m
    velocity: np.ndarray  # rad/s or m/s
    effort: np.ndarray | None  # N m or N
    units: tuple[str, ...]  # 'rad' or 'm' by joint

    def refusal(self, state: RobotState, previous: RobotState | None) -> str | None:
        """Why `state` is no state a robot within its limits can be in (None if it can), naming each joint: a
        position beyond its joint's limits by more than the margin, a velocity beyond the bound, or a move since
        `previous` (the state held) that no velocity within the bound makes in the time between their stamps,
        margin added."""
        q, v = state.q, state.v
        outside = np.flatnonzero((q < self.lower - self.margin) | (q > self.upper + self.margin))
        if outside.size:
            return '; '.join(f'{self.joints[j]} at {q[j].item()!r} {self.units[j]} is outside its URDF limits '
                             f'[{self.lower[j].item()!r}, {self.upper[j].item()!r}] by more than position_margin '
                             f'= {self.margin!r}' for j in outside)
        fast = np.flatnonzero(np.abs(v) > self.velocity)
        if fast.size:
            return '; '.join(f'{self.joints[j]} moves at {v[j].item()!r} {self.units[j]}/s, beyond the velocity '
                             f'bound (velocity_limit_factor times its URDF velocity limit) {self.velocity[j].item()!r}'
                             for j in fast)
        if previous is None:
            return None
        elapsed = abs(state.stamp - previous.stamp) * 1e-9
        # Positions of any size (a move of inf is refused as one); no velocity bound times no time is no bound.
        with np.errstate(over='ignore', invalid='ignore'):
            moved = np.abs(q - previous.q)
            reach = np.where(np.isfinite(self.velocity), self.velocity * elapsed, np.inf) + self.margin
        jumped = np.flatnonzero(moved > reach)
        if jumped.size:
            return '; '.join(f'{self.joints[j]} moved {moved[j].item()!r} {self.units[j]} in {elapsed:.9f} s since '
                             f'the state held: more than the {reach[j].item()!r} the velocity bound allows, '
                             f'position_margin added' for j in jumped)
        return None

    def clamped(self, effort: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """`effort` within the limits, and the joints whose effort was beyond them."""
        if self.effort is None:
            return effort, []
        beyond = np.abs(effort) > self.effort
        if not beyond.any():
            return effort, []
        return np.clip(effort, -self.effort, self.effort), [self.joints[j] for j in np.flatnonzero(beyond)]


def joint_state_msg(joints: list[str], t: float, q: np.ndarray | None = None, v: np.ndarray | None = None,
                    effort: np.ndarray | None = None) -> JointState:
    msg = JointState()
    msg.header.stamp = time_msg(t)
    msg.name = list(joints)
    msg.position = _doubles(q)
    msg.velocity = _doubles(v)
    msg.effort = _doubles(effort)
    return msg


def _doubles(values: np.ndarray | None) -> array.array:
    """A float64[] field's value: the message takes an array.array('d') as it is, a list element by element."""
    doubles = array.array('d')
    if values is not None:
        doubles.frombytes(np.ascontiguousarray(values, dtype=float).tobytes())
    return doubles


def effort_array_msg(effort: np.ndarray) -> Float64MultiArray:
    """The efforts as a forward_command_controller takes them: the data in its `joints` order, no layout."""
    return Float64MultiArray(data=[float(x) for x in effort])


@dataclass(frozen=True)
class Reference:
    """The programmed motion at the samples j = 0 … k_max, with the nominal torque P^nom."""

    times: np.ndarray
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray
    nominal: np.ndarray

    def point(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at sample n; after the last sample q_f is held at rest."""
        if n < len(self.times):
            return self.q[n], self.v[n], self.a[n]
        rest = np.zeros_like(self.q[-1])
        return self.q[-1], rest, rest


def reference_msg(joints: list[str], times, q, v, a, nominal) -> JointTrajectory:
    msg = JointTrajectory()
    msg.joint_names = list(joints)
    for j, t in enumerate(times):
        msg.points.append(JointTrajectoryPoint(
            positions=[float(x) for x in q[j]], velocities=[float(x) for x in v[j]],
            accelerations=[float(x) for x in a[j]], effort=[float(x) for x in nominal[j]],
            time_from_start=duration_msg(float(t))))
    return msg


def read_reference(msg: JointTrajectory, joints: list[str], period: float) -> Reference:
    """Validate a reference: our joints by name, one point per sample from t = 0, every field finite."""
    points = ((seconds(point.time_from_start), point.positions, point.velocities, point.accelerations,
               point.effort) for point in msg.points)
    return Reference(*checked_reference(msg.joint_names, points, joints, period))


def descriptor(description: str, *, floating: tuple[float, float] | None = None,
               integer: tuple[int, int] | None = None, read_only: bool = False):
    """A ParameterDescriptor whose range rclpy itself enforces."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    described = ParameterDescriptor(description=description, read_only=read_only)
    if floating is not None:
        described.floating_point_range = [FloatingPointRange(from_value=float(floating[0]),
                                                             to_value=float(floating[1]))]
    if integer is not None:
        described.integer_range = [IntegerRange(from_value=int(integer[0]), to_value=int(integer[1]), step=1)]
    return described


def _declare(node, parameter: NodeParameter) -> None:
    from rclpy.parameter import Parameter

    unset = {'integer[]': Parameter.Type.INTEGER_ARRAY, 'double[]': Parameter.Type.DOUBLE_ARRAY,
             'string[]': Parameter.Type.STRING_ARRAY}
    ranged = {} if parameter.range is None else {
        'floating' if parameter.type == 'double' else 'integer': parameter.range}
    node.declare_parameter(parameter.name, unset[parameter.type] if parameter.default is None else parameter.default,
                           descriptor(parameter.description, read_only=parameter.read_only, **ranged))


def declare_from_schema(node, kind: str, refused: type[Exception]) -> None:
    """Declare the parameters of a node of `kind` (ddarm.ros.parameter_schema.NODES) as the schema gives them.

    A deprecated name given at start (a parameter file, -p) sets the parameter it is the old name of, with a
    notice in the node's log; `refused` names both when they are given different values.
    """
    from rclpy.parameter import Parameter

    for parameter in parameters_of(kind):
        _declare(node, parameter)
    defaults = {parameter.name: parameter.default for parameter in parameters_of(kind)}
    for old, new in aliases(kind).items():
        given, current = node.get_parameter(old).value, node.get_parameter(new).value
        if given != defaults[old]:
            if current != defaults[new] and current != given:
                node.destroy_node()
                raise refused(f'{new} given twice, as {new} ({current}) and by its deprecated name {old} ({given}): '
                              f'give {new} only')
            node.get_logger().warning(deprecation_notice(old, new, f'{kind} parameter'))
            current = given
        node.set_parameters([Parameter(new, value=current), Parameter(old, value=current)])  # the old mirrors it


def mirrored_aliases(node, kind: str, parameters: list) -> list:
    """A set of parameters as it is applied: a deprecated name sets the parameter it names (with a notice in the
    node's log), and each such pair keeps one value, the new name's when a set gives both."""
    from rclpy.parameter import Parameter

    old_names = aliases(kind)
    if not old_names:
        return parameters
    new_names = {new: old for old, new in old_names.items()}
    by_name = {parameter.name: parameter for parameter in parameters}
    for parameter in parameters:
        if parameter.name in old_names and old_names[parameter.name] not in by_name:
            new = old_names[parameter.name]
            node.get_logger().warning(deprecation_notice(parameter.name, new, f'{kind} parameter'))
            by_name[new] = Parameter(new, value=parameter.value)
    for new, old in new_names.items():
        if new in by_name:
            by_name[old] = Parameter(old, value=by_name[new].value)
    return list(by_name.values())


def declare_joint_gains(node, joint: str) -> None:
    """Declare gains.<joint>.p and gains.<joint>.d, unless an earlier configure did."""
    for parameter in joint_gains(joint):
        if not node.has_parameter(parameter.name):
            _declare(node, parameter)


# Gains keyed by joint name, as ros2_controllers' pid gains: `gains: {joint: {p: …, d: …}}` in a parameter file,
# which ROS 2 flattens into the parameters gains.<joint>.p (K_p) and gains.<joint>.d (K_v).
GAINS_PREFIX = 'gains'


def gain_parameter(joint: str, key: str) -> str:
    """gains.<joint>.<key>: the parameter of one joint's K_p (key p) or K_v (key d)."""
    return f'{GAINS_PREFIX}.{joint}.{key}'


def gain_joint(name: str) -> str | None:
    """The joint a gains.<joint>.<key> parameter name is for (None for any other name)."""
    head, dot, rest = name.partition('.')
    joint, dot, key = rest.rpartition('.')
    return joint if head == GAINS_PREFIX and dot and joint and key in GAIN_KEYS else None


# The deprecated positional diagonals, each with the key of gains.<joint>.<key> it is read as.
POSITIONAL_GAINS = dict(zip(('kp', 'kv'), GAIN_KEYS))


def positional_gains(values: dict) -> list[str]:
    """Which of the positional kp and kv `values` (a node's, flat) give: set and not empty."""
    return [name for name in POSITIONAL_GAINS if values.get(name) is not None and len(values[name])]


def keyed_gains_given(values: dict) -> bool:
    """Whether `values` give any gains.<joint>.p or .d (0 is unset)."""
    return any(value for name, value in values.items() if gain_joint(name) is not None)


def positional_gains_notice(name: str, where: str) -> str:
    """The one line that says a positional diagonal is read as the gains by joint."""
    return deprecation_notice(name, f'gains.<joint>.{POSITIONAL_GAINS[name]}', where)


def given_gains(values: dict, joints: list[str]) -> tuple:
    """(kp, kv) as a controller's parameters give them (flat names, as a node holds them: `flat_parameters`):
    by joint name (gains.<joint>.p and .d, every joint's or none) or the positional kp and kv (None where
    unset). GainError when given both ways, by name for some joints only or for a joint not in `joints`, or not
    at all with omega = 0.
    """
    strangers = sorted({gain_joint(name) for name in values} - {None} - set(joints))
    if strangers:
        raise GainError(f'gains for {"joint" if len(strangers) == 1 else "joints"} '
                        f'{", ".join(repr(joint) for joint in strangers)}, which the controller does not control: '
                        f'its joints are {list(joints)}')
    keyed = {gain_parameter(joint, key): values.get(gain_parameter(joint, key), 0.0)
             for joint in joints for key in GAIN_KEYS}
    set_keyed = [name for name, value in keyed.items() if value != 0.0]
    positional = positional_gains(values)
    if set_keyed and positional:
        more = f' and {len(set_keyed) - 1} more gains.<joint> parameters' if len(set_keyed) > 1 else ''
        raise GainError(f'gains given twice: by {" and ".join(positional)} and by {set_keyed[0]}{more}; give '
                        f'them one way, gains.<joint>.p and .d or the positional kp and kv')
    if set_keyed:
        unset = [name for name, value in keyed.items() if value == 0.0]
        if unset:
            raise GainError(f'{", ".join(unset)} unset (0): give gains.<joint>.p and .d for every joint of '
                            f'{joints}, or for none')
        return tuple([keyed[gain_parameter(joint, key)] for joint in joints] for key in GAIN_KEYS)
    if not values.get('omega') and not positional:
        raise GainError(f'set the gains: gains.<joint>.p and .d for each joint of {joints}, or kp and kv '
                        f'(one value per joint, in that order), or omega > 0')
    return values.get('kp'), values.get('kv')


def flat_parameters(parameters: dict, prefix: str = '') -> dict:
    """A `ros__parameters` mapping as ROS 2 reads it: nested mappings flattened into dotted names
    (`gains: {joint1: {p: 1.0}}` is gains.joint1.p)."""
    flat = {}
    for key, value in parameters.items():
        if isinstance(value, dict):
            flat.update(flat_parameters(value, f'{prefix}{key}.'))
        else:
            flat[f'{prefix}{key}'] = value
    return flat


def unknown_parameters_reason(names, what: str, joints=None) -> str:
    """Why undeclared parameters are refused: gains for joints the node does not control named as such."""
    names = sorted(set(names))
    strangers = sorted({gain_joint(name) for name in names} - {None} - set(joints or ()))
    if strangers:
        return (f'{names} (gains for {"joint" if len(strangers) == 1 else "joints"} '
                f'{", ".join(repr(joint) for joint in strangers)}, which the {what} controller does not control: '
                f'its joints are {list(joints or ())})')
    kind = f'a {what} parameter' if len(names) == 1 else f'{what} parameters'
    return f'{names} (not {kind}: a typo?)'


def undeclared_overrides(node, given=()) -> list[str]:
    """Parameters given to the node that it never declared: most likely typos.

    Given: by its context's command line (parameter files and -p rules, matched to the node's
    name by rcl's rules: `ddarm.ros.parameter_files.given_parameters`), and the `given`
    Parameters of its constructor's parameter_overrides. rclpy has no public view of a node's
    overrides, so the node's own cli_args are not seen (ddarm's nodes set parameters with none).
    """
    names = {*given_parameters(context_arguments(node.context), node.get_fully_qualified_name()),
             *(parameter.name for parameter in given or ())}
    return sorted(name for name in names
                  if not node.has_parameter(name) and name != 'use_sim_time' and not name.startswith('qos_overrides.'))


def refuse_undeclared_parameters(node, what: str, joints=None, rewrite=None, kind: str | None = None) -> None:
    """Make the node refuse to set undeclared parameters with a reason that names them.

    rclpy (7.1) refuses them with "undeclared parameter(s): []": its check consumes the
    generator of names before it lists them. A pre-set callback runs before that check, so
    both the parameter services and a local set_parameters give this reason instead.
    `what` names the node's kind for the hint ("not a plant parameter"); a controller gives its
    `joints`, so that gains.<joint>.p for a joint it does not control is refused naming the joint.
    `rewrite(parameters) -> parameters` then adds to a change what must change with it: rclpy (7.1)
    concatenates what each pre-set callback returns, so a node has this one. A deprecated name of a node of
    `kind` (the schema's; default `what`) sets the parameter it names (`mirrored_aliases`) before `rewrite`.
    """
    def check(parameters: list) -> list:
        unknown = sorted({parameter.name for parameter in parameters if not node.has_parameter(parameter.name)})
        if unknown:
            raise ParameterNotDeclaredException(unknown_parameters_reason(unknown, what, joints))
        parameters = mirrored_aliases(node, kind or what, parameters)
        return parameters if rewrite is None else rewrite(parameters)

    node.add_pre_set_parameters_callback(check)


def proposed_values(node, changes) -> dict:
    """The node's parameter values as they would be after `changes` (for cross-parameter checks)."""
    values = {name: parameter.value for name, parameter in node.get_parameters_by_prefix('').items()}
    values.update({parameter.name: parameter.value for parameter in changes})
    return values


def plain_parameters(values: dict) -> dict:
    """Parameter values as JSON takes them (arrays as lists), for replies that say what a node runs with."""
    return {name: list(value) if isinstance(value, (list, tuple, array.array)) else value
            for name, value in values.items()}
