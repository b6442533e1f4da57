"""Every parameter of ddarm's nodes, declared once, as data: name, type, default, range, unit, read-only flag,
description, and which nodes take it.

As generate_parameter_library's YAML is for a ros2_controllers controller, this table is where a parameter is
defined: the nodes declare theirs from it (ddarm.ros.interface.declare_from_schema), with a ParameterDescriptor
whose range rclpy itself enforces, so `ros2 param describe` shows what is here. No rclpy in this module: the core,
the CLI and the docs read it without a ROS installation.

The nodes: 'plant' (ddarm_sim plant), 'robot' (ddarm_sim robot), 'controller' (ddarm_control pd_gravity and
computed_torque), 'tuner' (ddarm_tuner tuner). A name appears in several rows when it means something else on
another node (the plant's `command_timeout` is a lockstep wait, the robot's a watchdog).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ddarm.control.laws import CONTROLLERS, MAX_DELAY
from ddarm.episodes.spec import EPISODE_DEFAULTS as EPISODE
from ddarm.motion.programmed import PAPER_TRAJECTORIES
from ddarm.physics.plant import MAX_SUBSTEPS, NODE_PERIOD_RANGE
from ddarm.realtime import PRIORITY_RANGE, SPIN_MARGIN_RANGE
from ddarm.recording.gains_file import MAX_NODE_DURATION
from ddarm.recording import DEFAULT_ROOT

NODES = ('plant', 'robot', 'controller', 'tuner')
TYPES = ('bool', 'integer', 'double', 'string', 'integer[]', 'double[]', 'string[]')

# Defaults more than one module needs.
EFFORT_COMMAND_TOPIC = 'effort_command'  # the controllers' commands to ddarm's plant
ROBOT_COMMAND_TOPIC = '/effort_controller/commands'  # ros2_controllers' effort forward_command_controller, so named
RATE_RANGE = (1.0, 10_000.0)  # Hz, the robot's
PEER_TIMEOUT = 20.0  # wall s the tuner waits for the plant and the controller to be on the graph, alone
# s: a real-time tick wakes this long before its deadline and spins to it. 1 ms took the p99 period jitter from
# a wake-up's to the spin's (bench/realtime_jitter.py); it costs a tenth of a core at 100 Hz.
DEFAULT_SPIN_MARGIN = 0.001
MAX_GAIN = 1e9  # the largest K_p or K_v a controller node takes (gains.<joint>.p or .d; 0 means unset)
GAIN_KEYS = ('p', 'd')  # gains.<joint>.p is K_p, gains.<joint>.d is K_v (ros2_controllers' pid gains)


@dataclass(frozen=True)
class NodeParameter:
    """One parameter of one or more nodes. `default` None: an array parameter the node may leave unset."""

    name: str
    type: str  # one of TYPES
    default: object
    description: str
    nodes: tuple[str, ...]
    unit: str = ''
    range: tuple[float, float] | None = None  # closed, for integer and double parameters
    read_only: bool = False
    alias_of: str = ''  # a deprecated name: setting it sets this parameter, which it mirrors


def _p(name, type_, default, description, nodes, unit='', range_=None, read_only=False) -> NodeParameter:
    return NodeParameter(name, type_, default, description, tuple(nodes.split()), unit, range_, read_only)


def _alias(old: str, parameter: NodeParameter) -> NodeParameter:
    """`old`, a deprecated name of `parameter`: still taken (a one-line notice in the node's log), mirrors it."""
    return replace(parameter, name=old, description=f'deprecated: the old name of {parameter.name}, read as it',
                   alias_of=parameter.name)


SCHEDULING = (
    _p('realtime_priority', 'integer', 0,
       f'SCHED_FIFO priority of every thread of this node process, 1-{PRIORITY_RANGE[1]} (0: off, the scheduling it '
       'started with); needs CAP_SYS_NICE or an rtprio limit (ulimit -r), else refused', 'plant controller',
       range_=PRIORITY_RANGE),
    _p('cpu_affinity', 'integer[]', None,
       'the cores this node process runs on (unset: the ones it started with); a core it may not use is refused',
       'plant controller'),
)

PLANT = (
    _p('urdf', 'string', '', 'URDF of the arm ("" = the ddarm arm)', 'plant', read_only=True),
    _p('motion', 'string', '', 'a motion file: the controlled joints, locked joints and q^d(0); "" = the paper '
       'trajectory of `trajectory`', 'plant', read_only=True),
    _p('mjcf', 'string', '', 'a MuJoCo robot (MJCF, or a URDF MuJoCo compiles) stepped instead of ddarm\'s plant, its '
       'joints those of the arm ("" = ddarm\'s plant on `urdf`)', 'plant', read_only=True),
    _p('mjcf_joints', 'string[]', None, "the MJCF's name of each joint of the arm, in its order (unset: the same "
       'names)', 'plant', read_only=True),
    _p('mode', 'string', 'lockstep', 'lockstep (deterministic) or realtime (wall clock at 1/period)', 'plant'),
    _p('period', 'double', EPISODE['period'], 'sampling period Δ in s', 'plant', 's', NODE_PERIOD_RANGE),
    _p('substeps', 'integer', EPISODE['substeps'], 'RK4 steps per sampling period', 'plant', range_=(1, MAX_SUBSTEPS)),
    _p('command_timeout', 'double', 5.0, 'lockstep: wall seconds to wait for a command', 'plant', 's',
       (1e-3, 3600.0)),
    _p('required_subscribers', 'integer', 1, 'joint_states subscribers to wait for before sample 0', 'plant',
       range_=(1, 100)),
    _p('required_clock_subscribers', 'integer', 0, '/clock subscribers to wait for before sample 0 (a recorder of '
       'every tick)', 'plant', range_=(0, 100)),
    _p('max_samples', 'integer', 0, 'periods integrated per episode (0: until reset)', 'plant', range_=(0, 10**6)),
    _p('torque_limit', 'double[]', None, 'actuator limit |P_i| in N m per joint (unset: none)', 'plant', 'N m'),
    _p('viscous_friction', 'double[]', None, "viscous friction N m s/rad per joint beyond the URDF's <dynamics "
       'damping> (unset: none)', 'plant', 'N m s/rad'),
    _p('coulomb_friction', 'double[]', None, "Coulomb friction N m per joint beyond the URDF's <dynamics friction> "
       '(unset: none)', 'plant', 'N m'),
    _p('external_torque', 'double[]', None, 'constant external joint torques P^z in N m (unset: none)', 'plant',
       'N m'),
    _p('mass_scale', 'double[]', None, 'plant link mass / model link mass per link (unset: 1)', 'plant'),
    _p('trajectory', 'integer', EPISODE['trajectory'],
       f'start at q^d(0) of the paper trajectory {list(PAPER_TRAJECTORIES)} (of '
       '`motion`, when set, whatever the number); 0: initial_position/velocity', 'plant',
       range_=(0, max(PAPER_TRAJECTORIES))),
    _p('duration', 'double', 0.0, 'T of the programmed motion in s (for the start state; a bang-bang motion is '
       'stretched to it); 0 = the motion\'s own (the paper\'s: 1 s)', 'plant', 's', (0.0, MAX_NODE_DURATION)),
    _p('tau', 'double', EPISODE['tau'], 'initial velocity disturbance (3.1): q̇(0) = -q̇^d(τ), in s', 'plant', 's',
       (0.0, 3600.0)),
    _p('initial_position', 'double[]', None, 'start position when trajectory = 0', 'plant', 'rad or m'),
    _p('initial_velocity', 'double[]', None, 'start velocity when trajectory = 0', 'plant', 'rad/s or m/s'),
    _p('autostart', 'bool', True, 'start an episode at launch (else on ~/reset)', 'plant'),
    _p('managed', 'bool', False, 'start unconfigured and wait for the lifecycle services (configure, activate: '
       'activate starts an episode, as ~/reset does); false: configured and activated at launch', 'plant',
       read_only=True),
    _p('spin_margin', 'double', DEFAULT_SPIN_MARGIN, 'realtime: s before each deadline the tick wakes and spins on '
       'the clock to it (0: no spin); less than the period', 'plant', 's', SPIN_MARGIN_RANGE),
)

ROBOT = (
    _p('mjcf', 'string', '', 'the MuJoCo robot: an MJCF, or a URDF MuJoCo compiles', 'robot', read_only=True),
    _p('joints', 'string[]', None, 'the joints, in the order of the commands and of /joint_states (unset: every hinge '
       'and slide joint of the MJCF, in its order)', 'robot', read_only=True),
    _p('command_topic', 'string', ROBOT_COMMAND_TOPIC, 'the topic of the effort commands, a Float64MultiArray in the '
       'order of joints', 'robot', read_only=True),
    _p('mode', 'string', 'realtime', 'realtime: free-running on the wall clock at rate; lockstep: one period per '
       'command, /clock published', 'robot', read_only=True),
    _p('rate', 'double', 100.0, 'samples per second, Hz: 1/rate must be a whole number of the MJCF\'s timesteps',
       'robot', 'Hz', RATE_RANGE, read_only=True),
    _p('initial_position', 'double[]', None, 'q at activation, one per joint (unset: the MJCF\'s qpos0)', 'robot',
       'rad or m'),
    _p('initial_velocity', 'double[]', None, 'q̇ at activation, one per joint (unset: zero)', 'robot',
       'rad/s or m/s'),
    _p('position_noise', 'double', 0.0, 'standard deviation of the noise on each reported position, rad or m',
       'robot', 'rad or m', (0.0, 10.0)),
    _p('velocity_noise', 'double', 0.0, 'standard deviation of the noise on each reported velocity, rad/s or m/s',
       'robot', 'rad/s or m/s', (0.0, 100.0)),
    _p('noise_seed', 'integer', 0, 'seed of the noise (the same seed, the same noise)', 'robot',
       range_=(0, 2 ** 31 - 1)),
    _p('command_latency', 'double', 0.0, 's from a command\'s arrival to the joints (lockstep: a whole number of '
       'periods)', 'robot', 's', (0.0, 10.0)),
    _p('command_timeout', 'double', 1.0, 's without a command after which the efforts are zeroed until the next '
       '(lockstep: wall s before a period runs without one); 0: never', 'robot', 's', (0.0, 3600.0)),
    _p('hold_until_commanded', 'bool', True, 'hold the joints at the start state until the first command comes into '
       'force, as brakes hold a robot until its controller starts (false: it moves under gravity from activation)',
       'robot'),
    _p('required_subscribers', 'integer', 1, 'lockstep: /joint_states subscribers to wait for before sample 0',
       'robot', range_=(1, 100)),
    _p('autostart', 'bool', True, 'configure and activate at launch (else wait for the lifecycle services)', 'robot',
       read_only=True),
)

CONTROLLER_DELAY = _p('delay', 'integer', EPISODE['delay'], 'compute delay d in samples: the command of sample n is '
                      'computed from the state of sample n - d', 'controller', 'samples', (0, MAX_DELAY))

CONTROLLER = (
    _p('urdf', 'string', '', 'URDF of the controller model ("" = the ddarm arm)', 'controller', read_only=True),
    _p('motion', 'string', '', 'motion file: its joint_names are the controlled joints (the others locked at its '
       'locked positions), and in timer mode its motion is the reference ("" = every joint of the URDF, the '
       'reference from /reference)', 'controller', read_only=True),
    _p('duration', 'double', 0.0, 'timer mode: T of the motion in s, as the gains were tuned (a bang-bang motion is '
       'stretched to it); 0 = the motion file\'s own', 'controller', 's', (0.0, MAX_NODE_DURATION), read_only=True),
    _p('joints', 'string[]', None, 'joint names in URDF order, the order of kp and kv (unset: from the motion file, '
       'else the URDF)', 'controller', read_only=True),
    _p('kp', 'double[]', None, 'deprecated: K_p diagonal in joint order, read as gains.<joint>.p (with a notice)',
       'controller'),
    _p('kv', 'double[]', None, 'deprecated: K_v diagonal in joint order, read as gains.<joint>.d (with a notice)',
       'controller'),
    _p('omega', 'double', 0.0, 'ω rule of section 2 when > 0 (overrides kp, kv and gains)', 'controller', 'rad/s',
       (0.0, 1e4)),
    CONTROLLER_DELAY,
    _alias('compute_delay_steps', CONTROLLER_DELAY),
    _p('period', 'double', EPISODE['period'],
       'sampling period Δ in s (state: to read sample indices from stamps; timer: the '
       'timer period, fixed while the node runs)', 'controller', 's', NODE_PERIOD_RANGE),
    _p('max_sample_gap', 'integer', 100, 'states more than this many samples ahead of the expected one are refused '
       '(sampling state)', 'controller', 'samples', (1, 1_000_000)),
    _p('viscous_friction', 'double[]', None, "model friction F̂ (computed torque) beyond the URDF's <dynamics "
       'damping>, N m s/rad', 'controller', 'N m s/rad'),
    _p('coulomb_friction', 'double[]', None, "model friction F̂ (computed torque) beyond the URDF's <dynamics "
       'friction>, N m', 'controller', 'N m'),
    _p('sampling', 'string', 'state', 'state: one command per stamped state (lockstep with ddarm\'s plant); timer: a '
       'timer at 1/period samples the latest /joint_states', 'controller', read_only=True),
    _p('command_type', 'string', 'joint_state', 'joint_state: a stamped JointState with names; float64_multi_array: '
       'the efforts in joint order, as a forward_command_controller takes them', 'controller', read_only=True),
    _p('command_topic', 'string', EFFORT_COMMAND_TOPIC, 'the topic of the effort commands (a robot\'s: '
       '/<controller>/commands)', 'controller', read_only=True),
    _p('clamp_efforts', 'bool', True, 'sampling timer: clamp each effort to its joint\'s limit (effort_limits, else '
       'the URDF\'s <limit effort>), counted and logged; false publishes the law\'s efforts as they are',
       'controller'),
    _p('effort_limits', 'double[]', None, 'sampling timer: the largest |effort| of each joint, N m or N, in joint '
       'order, each finite and > 0 (unset: the URDF\'s <limit effort>)', 'controller', 'N m or N'),
    _p('position_margin', 'double', 0.1, 'sampling timer: a state with a position beyond its joint\'s URDF limits by '
       'more than this (rad or m; continuous joints have none) is refused, as is one that moved since the state '
       'held by more than the velocity bound allows plus this', 'controller', 'rad or m', (0.0, 1e3)),
    _p('velocity_limit_factor', 'double', 2.0, 'sampling timer: the velocity bound is this times the URDF\'s <limit '
       'velocity>; a state beyond it is refused', 'controller', range_=(1.0, 1e6)),
    _p('max_state_lead', 'double', 0.1, 'sampling timer: a state stamped more than this many s ahead of the node\'s '
       'clock is refused, and the state held is dropped once it is that far ahead (the clock went back)',
       'controller', 's', (0.0, 3600.0)),
    _p('max_clock_jump', 'double', 0.5, 'sampling timer: ticks missed within this many s are skipped; when the '
       'node\'s clock jumps further, ahead or back, between two ticks, the motion goes on from the next sample '
       '(re-anchored)', 'controller', 's', (0.0, 3600.0)),
    _p('autostart', 'bool', True, 'configure and activate at launch (else wait for the lifecycle services)',
       'controller', read_only=True),
)

# One pair per controlled joint, declared by a controller at configure and by the tuner at start (the joints are
# known only once the URDF and the motion are read).
JOINT_GAINS = (
    _p('gains.{joint}.p', 'double', 0.0, 'K_p of {joint}, > 0 (0 = unset)', 'controller tuner',
       range_=(0.0, MAX_GAIN)),
    _p('gains.{joint}.d', 'double', 0.0, 'K_v of {joint}, > 0 (0 = unset)', 'controller tuner',
       range_=(0.0, MAX_GAIN)),
)

TUNER = (
    _p('controller', 'string', 'computed_torque', f'the law to drive: one of {CONTROLLERS}', 'tuner'),
    _p('kp', 'double[]', None, 'deprecated: K_p diagonal in joint order, read as gains.<joint>.p (with a notice)',
       'tuner'),
    _p('kv', 'double[]', None, 'deprecated: K_v diagonal in joint order, read as gains.<joint>.d (with a notice)',
       'tuner'),
    _p('gains_file', 'string', '', 'controller parameter YAML (gains, delay, period)', 'tuner'),
    _p('urdf', 'string', '', 'URDF of the plant\'s arm ("" = the ddarm arm); the plant node must run it', 'tuner',
       read_only=True),
    _p('model_urdf', 'string', '', 'URDF of the controller\'s model ("" = urdf); the controller node must run it',
       'tuner', read_only=True),
    _p('motion', 'string', '', 'a motion file: the controlled joints, locked joints and q^d ("" = the paper '
       'trajectory of `trajectory`); plant and controller must run it', 'tuner', read_only=True),
    _p('trajectory', 'integer', EPISODE['trajectory'],
       f'the paper trajectory, one of {list(PAPER_TRAJECTORIES)} (unless motion)',
       'tuner', range_=(min(PAPER_TRAJECTORIES), max(PAPER_TRAJECTORIES))),
    _p('duration', 'double', 0.0, 'T in s (0: the motion\'s own; a bang-bang motion is stretched to T)', 'tuner',
       's', (0.0, MAX_NODE_DURATION)),
    _p('period', 'double', EPISODE['period'], 'Δ in s', 'tuner', 's', NODE_PERIOD_RANGE),
    _p('delay', 'integer', EPISODE['delay'],
       'compute delay d in samples (unless gains_file)', 'tuner', 'samples', (0, MAX_DELAY)),
    _p('substeps', 'integer', EPISODE['substeps'], 'plant RK4 steps per period', 'tuner', range_=(1, MAX_SUBSTEPS)),
    _p('taus', 'double[]', [0.0], 'initial velocity disturbances τ (3.1), one episode each, s', 'tuner', 's'),
    _p('torque_limits', 'string[]', ['none'], "'none', 'paper' (2 x max nominal) and/or 'urdf' (its <limit effort>), "
       'each with every τ', 'tuner'),
    _p('output_root', 'string', str(DEFAULT_ROOT), 'folder that holds the run folders', 'tuner'),
    _p('run_name', 'string', '', 'run folder name ("" = tuner-<date>-<time>); never reused', 'tuner'),
    _p('storage', 'string', 'mcap', 'bag storage: mcap or sqlite3', 'tuner'),
    _p('episode_timeout', 'double', 120.0, 'wall seconds one episode may take', 'tuner', 's', (1.0, 86400.0)),
    _p('peer_timeout', 'double', PEER_TIMEOUT, 'wall seconds to wait for the plant and the controller on the graph '
       'before each episode', 'tuner', 's', (0.1, 3600.0)),
)

# Every row: those a node declares at construction, in its order (the scheduling rows after the plant's and the
# controllers' own), then the per-joint gains' templates.
SCHEMA = PLANT + ROBOT + CONTROLLER + SCHEDULING + TUNER + JOINT_GAINS


def parameters_of(node: str) -> tuple[NodeParameter, ...]:
    """The parameters `node` (one of NODES) declares at construction, in order; the per-joint gains are
    joint_gains'."""
    if node not in NODES:
        raise ValueError(f'no node {node!r}: one of {NODES}')
    return tuple(parameter for parameter in SCHEMA if node in parameter.nodes and parameter not in JOINT_GAINS)


def aliases(node: str) -> dict[str, str]:
    """The deprecated names `node` still takes, each with the name it is read as."""
    return {parameter.name: parameter.alias_of for parameter in parameters_of(node) if parameter.alias_of}


def read_only(node: str) -> frozenset[str]:
    """The parameters `node` takes only at start: never set through its parameter services."""
    return frozenset(parameter.name for parameter in parameters_of(node) if parameter.read_only)


def joint_gains(joint: str) -> tuple[NodeParameter, NodeParameter]:
    """gains.<joint>.p (K_p) and gains.<joint>.d (K_v) of one controlled joint."""
    return tuple(replace(parameter, name=parameter.name.format(joint=joint),
                         description=parameter.description.format(joint=joint)) for parameter in JOINT_GAINS)
