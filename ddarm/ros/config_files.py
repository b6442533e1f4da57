"""The parameter files in config/, generated from the parameter schema: every parameter a node declares, with the
schema's description, unit and range beside it; set to its default unless the file's example sets it otherwise, and
shown commented out when it has no default (or an empty one, read-only: no arm file given).

`make docs` writes them (`python -m ddarm.cli.docs`); test/test_parameter_schema.py fails when a file differs from
what this module makes of the schema, so a parameter's default, range or description is changed in one place.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ddarm.ros.parameter_schema import JOINT_GAINS, NodeParameter, parameters_of

CONFIG = Path(__file__).resolve().parents[2] / 'config'
WIDTH = 120
VALUE_COLUMN = 34  # where a parameter's comment starts, when its `name: value` leaves room


@dataclass(frozen=True)
class ConfigFile:
    """One parameter file: the node it configures (its name as the file's key, and its schema kind), the lines that
    say what it is for, and the example values it sets or shows beyond the schema's defaults."""

    name: str
    node: str
    kind: str
    header: str
    values: dict = field(default_factory=dict)  # set, instead of the default
    shown: dict = field(default_factory=dict)  # shown commented out, with this example value
    gains: dict | None = None  # a controller's gains by joint: {joint: (K_p, K_v)}


GAINS_HEADER = """
Gains by joint name, as ros2_controllers write them: gains.<joint>.p is K_p, gains.<joint>.d is K_v (each finite and
> 0; 0 = unset). The positional kp and kv (in the controller's joint order) are deprecated, read as those with a
notice. `ddarm tune` and `ddarm omega` write this form, with the urdf and motion the gains were tuned for."""

SCHEDULING_EXAMPLES = {'realtime_priority': 50, 'cpu_affinity': [1]}

FILES = (
    ConfigFile('plant.yaml', 'plant', 'plant', """
ros2 run ddarm_sim plant --ros-args --params-file config/plant.yaml
Every value is the schema's default (docs/model-specification.md's), but T = 1 s, the paper's; per-joint options left
out mean "none".""", values={'duration': 1.0},
        shown={'torque_limit': [563.21, 509.08, 110.67], 'viscous_friction': [0.0, 0.0, 0.0],
               'coulomb_friction': [0.0, 0.0, 0.0], 'external_torque': [0.0, 0.0, 0.0],
               'mass_scale': [1.0, 1.0, 1.0], 'initial_position': [0.0, 0.0, 0.0],
               'initial_velocity': [0.0, 0.0, 0.0], **SCHEDULING_EXAMPLES}),
    ConfigFile('robot.yaml', 'robot', 'robot', """
ros2 run ddarm_sim robot --ros-args --params-file config/robot.yaml
A MuJoCo robot behind ros2_control's topics (needs pip install 'ddarm[mujoco]'): /joint_states out, efforts in on
command_topic as a Float64MultiArray in the order of joints. A lifecycle node: autostart configures and activates it
at launch; otherwise drive it with its lifecycle services (ros2 lifecycle set /robot configure, activate, ...).""",
        values={'mjcf': 'config/robots/panda/panda.xml'},
        shown={'joints': [], 'initial_position': [], 'initial_velocity': []}),
    ConfigFile('pd_gravity.yaml', 'pd_gravity', 'controller', """
ros2 run ddarm_control pd_gravity --ros-args --params-file config/pd_gravity.yaml
The ω = 10 rule of (2.3) with m_ii at trajectory 1's final position: k_p = m_ii ω², k_v = 2 m_ii ω.""" + GAINS_HEADER,
        gains={'joint1': (2800.0, 560.0), 'joint2': (2700.0, 540.0), 'joint3': (350.0, 70.0)},
        shown={'joints': [], 'kp': [], 'kv': [], 'viscous_friction': [], 'coulomb_friction': [],
               'effort_limits': [], **SCHEDULING_EXAMPLES}),
    ConfigFile('computed_torque.yaml', 'computed_torque', 'controller', """
ros2 run ddarm_control computed_torque --ros-args --params-file config/computed_torque.yaml
The ω = 15 rule of section 2.2 (k_p = ω², k_v = 2ω) with the user's one-cycle compute delay.""" + GAINS_HEADER,
        gains={'joint1': (225.0, 30.0), 'joint2': (225.0, 30.0), 'joint3': (225.0, 30.0)},
        shown={'joints': [], 'kp': [], 'kv': [], 'viscous_friction': [], 'coulomb_friction': [],
               'effort_limits': [], **SCHEDULING_EXAMPLES}),
    ConfigFile('tuner.yaml', 'tuner', 'tuner', """
ros2 run ddarm_tuner tuner --ros-args --params-file config/tuner.yaml
With the plant and the controller running (ros2 run ddarm_sim plant, ros2 run ddarm_control computed_torque), runs
one episode per τ under each torque limit, records each as a bag and scores it from the bag. The plant and the
controller must run the tuner's urdf, model_urdf and motion, or it refuses the episode naming the difference.""",
        gains={'joint1': (225.0, 30.0), 'joint2': (225.0, 30.0), 'joint3': (225.0, 30.0)},
        values={'duration': 1.0, 'taus': [0.0, 0.05, 0.1], 'torque_limits': ['none', 'paper']}),
)


def _value(value) -> str:
    # A scalar is dumped as a document with its end marker, `value\n...`: the marker is not the value's.
    return yaml.safe_dump(value, default_flow_style=True, width=10_000, allow_unicode=True).strip().removesuffix(
        '\n...')


def _note(parameter: NodeParameter) -> str:
    """The comment beside a parameter: its description, and its unit, range and read-only flag, as the schema gives
    them."""
    extras = [f'unit {parameter.unit}'] if parameter.unit else []
    if parameter.range is not None:
        extras.append(' to '.join(str(end) if isinstance(end, int) else f'{end:g}' for end in parameter.range))
    if parameter.read_only:
        extras.append('read-only')
    return parameter.description + (f' [{"; ".join(extras)}]' if extras else '')


def _line(indent: str, assignment: str, note: str, commented: bool = False) -> list[str]:
    """`assignment` (commented out, or not) with `note` as its comment, wrapped within WIDTH."""
    start = f'{indent}{"# " if commented else ""}{assignment}'
    column = max(VALUE_COLUMN, len(start) + 2)
    if column > WIDTH - 40:  # a long value: its comment on the lines below
        return [start, *textwrap.wrap(note, WIDTH, initial_indent=f'{indent}#   ', subsequent_indent=f'{indent}#   ',
                                      break_on_hyphens=False)]
    return textwrap.wrap(note, WIDTH, initial_indent=f'{start.ljust(column)}# ', break_on_hyphens=False,
                         subsequent_indent=f'{indent}#{" " * (column - len(indent) - 1)}#   ')


def render(config: ConfigFile) -> str:
    """The text of a parameter file from the schema and the file's examples."""
    lines = [f'# {line}' if line else '#' for line in config.header.strip('\n').splitlines()]
    lines += [f'{config.node}:', '  ros__parameters:']
    indent = '    '
    for parameter in parameters_of(config.kind):
        if parameter.alias_of:
            continue  # a deprecated name: the parameter it names is in the file
        name = parameter.name
        if name == 'kp' and config.gains:  # the gains by joint, before the deprecated positional form
            low, high = JOINT_GAINS[0].range
            lines += _line(indent, 'gains:', f'by joint name: p is K_p, d is K_v, each {low:g} to {high:g} (the '
                                             'parameters gains.<joint>.p and .d)')
            lines += [f'{indent}  {joint}: {{p: {p!r}, d: {d!r}}}' for joint, (p, d) in config.gains.items()]
        if name in config.values:
            lines += _line(indent, f'{name}: {_value(config.values[name])}', _note(parameter))
        elif name in config.shown or parameter.default is None or parameter.read_only and parameter.default == '':
            example = config.shown.get(name, parameter.default if parameter.default is not None else [])
            lines += _line(indent, f'{name}: {_value(example)}', _note(parameter), commented=True)
        else:
            lines += _line(indent, f'{name}: {_value(parameter.default)}', _note(parameter))
    return '\n'.join(lines) + '\n'


def write_all(folder: Path = CONFIG) -> list[Path]:
    written = []
    for config in FILES:
        path = folder / config.name
        path.write_text(render(config))
        written.append(path)
    return written
