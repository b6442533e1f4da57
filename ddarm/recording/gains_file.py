"""A controller YAML (`ddarm tune --out`, `ddarm omega`, or written by hand) read back as the episode it configures.

The file is what `ros2 run ddarm_control <law> --ros-args --params-file` loads: one law's node key, its
`ros__parameters` with the gains keyed by joint (`gains: {<joint>: {p, d}}`; the deprecated positional `kp`, `kv`
in joint order still read, with a notice), `delay` (formerly `compute_delay_steps`, still read), `period`, and the
`urdf` and `motion` the gains were tuned for. Read here as the node reads it, so that the episode validated is the
one the node would run: every refusal names the file and the parameter, and nothing the node would do differently
(an ω rule in force, an extra model friction) is passed over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from ddarm.control.laws import CONTROLLERS, MAX_DELAY
from ddarm.datafiles import PARAMETERS_KEY, is_missing, parameter_document, unreachable
from ddarm.episodes.spec import EPISODE_DEFAULTS, EpisodeSpec, read_motion_file
from ddarm.deprecation import deprecated_name, renamed_keys
from ddarm.errors import DdarmError
from ddarm.motion.programmed import MotionError
from ddarm.physics.arm import ModelError, movable_joints
from ddarm.physics.plant import NODE_PERIOD_RANGE

# The controller node's defaults for what a file leaves out (the episode's, as the node's are).
DEFAULT_DELAY, DEFAULT_PERIOD = EPISODE_DEFAULTS['delay'], EPISODE_DEFAULTS['period']
# The node's bound on `duration`, s (0: the motion file's own).
MAX_NODE_DURATION = 3600.0
# The controller node's deprecated parameter names, each with the one it is read as (the schema's aliases).
CONTROLLER_RENAMED = {'compute_delay_steps': 'delay'}
# Parameters that make the node's law another than the gains' in the file: validating the gains alone would be
# validating a controller the robot does not run.
LAW_CHANGING = ('viscous_friction', 'coulomb_friction')


class GainsFileError(DdarmError, ValueError):
    """A controller YAML that does not configure one law's gains on a known arm and motion; the text names the
    file and the problem."""


@dataclass(frozen=True)
class GainsFile:
    """The episode a controller YAML configures: its law, gains in the motion's joint order, compute delay d,
    period Δ, and the model URDF, motion and T it names (None: the paper's arm, the paper's trajectory, the
    motion's own T)."""

    controller: str
    joint_names: tuple[str, ...]
    kp: tuple[float, ...]
    kv: tuple[float, ...]
    delay: int
    period: float
    urdf: str | None
    motion: str | None
    duration: float | None
    path: str


def _document(path: str) -> dict:
    """The file's YAML, read as the controller node's parameter file is (ddarm.datafiles.parameter_document)."""
    if is_missing(unreachable(path)):
        raise GainsFileError(f'gains file {path} does not exist')
    return parameter_document(path, GainsFileError, 'gains file')


def _law_parameters(path: str, document: dict) -> tuple[str, dict]:
    """(law, its ros__parameters): the one node key of the file that names a law (`computed_torque` or
    `/computed_torque`, as rcl matches it to the node of that name)."""
    laws = [(str(key).removeprefix('/'), value) for key, value in document.items()
            if str(key).removeprefix('/') in CONTROLLERS]
    if len(laws) != 1:
        keys = ', '.join(repr(key) for key in document) or 'none'
        found = 'no node key' if not laws else f'{len(laws)} node keys'
        raise GainsFileError(f'gains file {path} has {found} naming a law ({" or ".join(CONTROLLERS)}); one is '
                             f'validated at a time (its keys: {keys})')
    law, node = laws[0]
    parameters = node.get(PARAMETERS_KEY) if isinstance(node, dict) else None
    if not isinstance(parameters, dict):
        raise GainsFileError(f'gains file {path}: {law} has no {PARAMETERS_KEY} mapping, so it configures nothing')
    return law, parameters


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _gain(path: str, name: str, value) -> float:
    """A gain as the node takes it: a finite number > 0 (the node reads 0 as unset)."""
    if not (_is_number(value) and math.isfinite(value) and value > 0):
        raise GainsFileError(f'gains file {path}: {name} is {value!r}, not a finite number > 0')
    return float(value)


def _input_file(path: str, name: str, value) -> str | None:
    """The `urdf` or `motion` parameter as a path: None for '' or absent (the node's default), else a file that
    is there, made absolute from the working folder as the node, started there, would open it."""
    if value is None or value == '':
        return None
    if not isinstance(value, str):
        raise GainsFileError(f'gains file {path}: {name} is {value!r}, not a path')
    failure = unreachable(value)
    if is_missing(failure):
        raise GainsFileError(f'gains file {path}: its {name} {value} does not exist')
    if failure is not None:
        raise GainsFileError(f'gains file {path}: its {name} {value}: {failure.strerror or failure}')
    return str(Path(value).absolute())


def _joint_names(path: str, urdf: str | None, motion: str | None) -> tuple[str, ...]:
    """The joints the node controls: the motion's; without one, the paper arm's (only the paper's trajectory
    gives a motion then, and it drives no other arm's joints)."""
    try:
        joints = read_motion_file(motion).joint_names
        movable = movable_joints(urdf) if motion is None and urdf is not None else joints
    except (MotionError, ModelError) as error:
        raise GainsFileError(f'gains file {path}: {error}') from error
    if sorted(movable) != sorted(joints):
        raise GainsFileError(f'gains file {path}: urdf {urdf} but no motion: the paper\'s trajectory drives the '
                             f'paper arm\'s joints {list(joints)}, not this URDF\'s {list(movable)}; add the motion '
                             'the gains were tuned for (motion: FILE) to its ros__parameters')
    return tuple(joints)


def _gains(path: str, parameters: dict, joints: tuple[str, ...]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(kp, kv) in joint order, from the keyed form or the positional one (exactly one of them)."""
    keyed = parameters.get('gains')
    positional = [name for name in ('kp', 'kv') if name in parameters]
    if keyed is not None and positional:
        raise GainsFileError(f'gains file {path} gives the gains twice, keyed by joint (gains) and positional '
                             f'({" and ".join(positional)}): give them one way')
    if keyed is not None:
        if not isinstance(keyed, dict):
            raise GainsFileError(f'gains file {path}: gains is {type(keyed).__name__}, not a mapping '
                                 '<joint>: {p: K_p, d: K_v}')
        strangers = [str(joint) for joint in keyed if joint not in joints]
        if strangers:
            raise GainsFileError(f'gains file {path} has gains for {", ".join(repr(j) for j in strangers)}, which '
                                 f'the motion does not control: its joints are {list(joints)}')
        missing = [joint for joint in joints if joint not in keyed]
        if missing:
            raise GainsFileError(f'gains file {path} has no gains for {", ".join(repr(j) for j in missing)}: give '
                                 f'gains.<joint>.p and .d for each of {list(joints)}')
        for joint in joints:
            if not isinstance(keyed[joint], dict) or set(keyed[joint]) != {'p', 'd'}:
                raise GainsFileError(f'gains file {path}: gains.{joint} is {keyed[joint]!r}, not {{p: K_p, d: K_v}}')
        return tuple(tuple(_gain(path, f'gains.{joint}.{key}', keyed[joint][key]) for joint in joints)
                     for key in ('p', 'd'))
    if len(positional) != 2:
        raise GainsFileError(f'gains file {path} has no gains: give gains.<joint>.p and .d for each of {list(joints)}'
                             + (f', or kp with kv (only {positional[0]} is there)' if positional else ''))
    deprecated_name('kp and kv', 'gains (by joint)', f'gains file {path}')
    if 'joints' in parameters and parameters['joints'] != list(joints):
        raise GainsFileError(f"gains file {path}: joints {parameters['joints']!r}, the order of kp and kv, are not "
                             f'the joints the motion controls {list(joints)}')
    gains = []
    for name in ('kp', 'kv'):
        values = parameters[name]
        if not isinstance(values, list) or len(values) != len(joints):
            raise GainsFileError(f'gains file {path}: {name} is {values!r}, not {len(joints)} values, one per joint '
                                 f'of {list(joints)}')
        gains.append(tuple(_gain(path, f'{name}[{i}] ({joint})', value)
                           for i, (joint, value) in enumerate(zip(joints, values))))
    return gains[0], gains[1]


def read_gains_file(path: str | Path) -> GainsFile:
    """The controller YAML at `path`, read and checked as the controller node would run it.

    Raises:
        GainsFileError: naming the file and the problem: no single law's node key or no ros__parameters, gains
            missing, given both ways, not finite numbers > 0 or for joints the motion does not control, a
            compute delay or period the node refuses, a urdf or motion that is not there, an ω rule or extra model
            friction that would replace or change the law the gains are for.
    """
    path = str(path)
    law, parameters = _law_parameters(path, _document(path))
    parameters = renamed_keys(parameters, CONTROLLER_RENAMED, f'gains file {path}', GainsFileError)
    omega = parameters.get('omega', 0.0)
    if not (_is_number(omega) and omega == 0):
        raise GainsFileError(f'gains file {path}: omega is {omega!r}: the controller node would replace its gains '
                             'by the ω rule; validate the gains themselves (omega: 0.0)')
    changing = [name for name in LAW_CHANGING if parameters.get(name)]
    if changing:
        raise GainsFileError(f'gains file {path} gives {" and ".join(changing)}, a model friction F̂ beyond the '
                             'URDF\'s that ddarm does not validate yet: put it in the URDF\'s <dynamics>')
    urdf = _input_file(path, 'urdf', parameters.get('urdf'))
    motion = _input_file(path, 'motion', parameters.get('motion'))
    joints = _joint_names(path, urdf, motion)
    kp, kv = _gains(path, parameters, joints)
    delay = parameters.get('delay', DEFAULT_DELAY)
    if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= MAX_DELAY:
        raise GainsFileError(f'gains file {path}: delay is {delay!r}, not a whole number of samples '
                             f'in [0, {MAX_DELAY}]')
    period = parameters.get('period', DEFAULT_PERIOD)
    if not (_is_number(period) and NODE_PERIOD_RANGE[0] <= period <= NODE_PERIOD_RANGE[1]):
        raise GainsFileError(f'gains file {path}: period is {period!r}, not a number of s within '
                             f'[{NODE_PERIOD_RANGE[0]:g}, {NODE_PERIOD_RANGE[1]:g}] (the controller node\'s range)')
    duration = parameters.get('duration', 0.0)
    if not (_is_number(duration) and 0 <= duration <= MAX_NODE_DURATION):
        raise GainsFileError(f'gains file {path}: duration is {duration!r}, not a number of s within '
                             f'[0, {MAX_NODE_DURATION:g}] (0: the motion\'s own)')
    return GainsFile(controller=law, joint_names=joints, kp=kp, kv=kv, delay=delay, period=float(period), urdf=urdf,
                     motion=motion, duration=float(duration) or None, path=str(Path(path).absolute()))


def validation_spec(gains: GainsFile, **overrides) -> EpisodeSpec:
    """The episode the YAML's controller runs: its law, gains, delay and period on its URDF (plant and model alike)
    and motion over its T; `overrides` give what the file does not hold (tau, torque_limit, mjcf, mjcf_joints,
    substeps; trajectory, the paper's motion, only for a file without a motion).

    Raises:
        GainsFileError: a trajectory for a file that names its motion.
        EpisodeError: an episode the overrides make that cannot run.
    """
    if gains.motion is not None and overrides.get('trajectory') is not None:
        raise GainsFileError(f'gains file {gains.path} names its motion {gains.motion}: a paper trajectory '
                             '(--trajectory) is for a file without one')
    if overrides.get('trajectory') is None:
        overrides.pop('trajectory', None)  # the spec's default: the paper's trajectory 1
    return EpisodeSpec(controller=gains.controller, kp=gains.kp, kv=gains.kv, duration=gains.duration,
                       period=gains.period, delay=gains.delay, urdf=gains.urdf, motion=gains.motion, **overrides)
