"""The generated pages of docs/: cli.md from `ddarm`'s argument parser (every command, its options, their
defaults and help), ros-interface.md from the nodes themselves (topics, QoS, services, parameters), the episode
options' table of model-specification.md (§14) from the episode's defaults; and the parameter files config/*.yaml
from the parameter schema (ddarm.ros.config_files).

    .venv/bin/python -m ddarm.cli.docs        # rewrites them all (make docs)

Each page is read from what the code declares, never written by hand, so that it cannot drift from it;
test_docs.py (test_parameter_schema.py for config/) fails when a committed one differs from this output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddarm.cli.main import build_parser
from ddarm.control.laws import CONTROLLERS
from ddarm.ros.config_files import write_all

PAGE = Path(__file__).resolve().parents[2] / 'docs' / 'cli.md'


def _cell(text: str) -> str:
    """Text inside a Markdown table cell: one line, its pipes escaped."""
    return ' '.join(str(text).split()).replace('|', '\\|')


def _names(action: argparse.Action) -> str:
    if not action.option_strings:
        return f'`{action.metavar or action.dest}`'
    value = ''
    if action.nargs != 0:
        if action.choices is not None:
            value = ' {' + ','.join(map(str, action.choices)) + '}'
        else:
            value = f' {action.metavar or action.dest.upper()}'
        if action.nargs in ('+', '*'):
            value += ' …'
    return ', '.join(f'`{name}{value}`' for name in action.option_strings)


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS):
        return ''
    if isinstance(action.default, (list, tuple)):
        return ' '.join(map(str, action.default))
    return str(action.default)


def _commands(parser: argparse.ArgumentParser) -> dict[str, tuple[str, argparse.ArgumentParser]]:
    """Each subcommand's help line and parser, in the order `ddarm --help` lists them."""
    (subparsers,) = [action for action in parser._actions if isinstance(action, argparse._SubParsersAction)]
    helps = {choice.dest: choice.help for choice in subparsers._choices_actions}
    return {name: (helps.get(name, ''), command) for name, command in subparsers.choices.items()}


def cli_reference() -> str:
    """The page's text."""
    parser = build_parser()
    commands = _commands(parser)
    lines = ['# `ddarm` command line', '',
             'Generated from the argument parser by `make docs` (`python -m ddarm.cli.docs`); do not edit by hand. '
             'Every command also takes `--help`.', '',
             *(f'- [`ddarm {name}`](#ddarm-{name}): {_cell(help_line)}' for name, (help_line, _) in commands.items())]
    for name, (help_line, command) in commands.items():
        lines += ['', f'## ddarm {name}', '', _cell(help_line), '', '| option | default | meaning |', '|---|---|---|']
        for action in command._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            required = ' (required)' if action.required and action.option_strings else ''
            lines.append(f'| {_names(action)} | {_cell(_default(action))} | {_cell(action.help or "")}{required} |')
    return '\n'.join(lines) + '\n'


ROS_PAGE = PAGE.with_name('ros-interface.md')
# The parameter types of rcl_interfaces/ParameterType, by number.
PARAMETER_TYPES = {1: 'bool', 2: 'integer', 3: 'double', 4: 'string', 5: 'byte[]', 6: 'bool[]', 7: 'integer[]',
                   8: 'double[]', 9: 'string[]'}
# What each node needs to start at all; documented as required, not as a default.
GAINS = {f'gains.joint{i}.{key}': 1.0 for i in (1, 2, 3) for key in ('p', 'd')}  # the ddarm arm's joints
REQUIRED = {'pd_gravity': GAINS, 'computed_torque': GAINS, 'tuner': GAINS,
            'robot': {'mjcf': str(PAGE.parent.parent / 'config' / 'robots' / 'panda' / 'panda.xml')}}


def _qos(profile) -> str:
    return (f'{profile.reliability.name.lower()}, {profile.durability.name.lower()}, '
            f'{profile.history.name.lower().replace("keep_", "keep ")} {profile.depth}')


def _range(descriptor) -> str:
    for ranges in (descriptor.floating_point_range, descriptor.integer_range):
        if ranges:
            return f'[{ranges[0].from_value:g}, {ranges[0].to_value:g}]'
    return ''


def _value(value) -> str:
    if value is None:
        return 'unset'
    if isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
        return '[' + ', '.join(map(str, list(value))) + ']'
    return repr(value) if isinstance(value, str) else str(value)


def _node_section(title: str, run: str, node, required: dict, kind: str) -> list[str]:
    """A node's page section from the node itself: what it publishes, subscribes to, serves and declares (with each
    parameter's unit from the schema, `kind`'s rows: a ParameterDescriptor has no field for it)."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from ddarm.ros.parameter_schema import parameters_of

    units = {parameter.name: parameter.unit for parameter in parameters_of(kind)}

    own = f'{node.get_name()}/'
    lines = ['', f'## {title}', '', f'`{run}`', '', '| topic | direction | type | QoS |', '|---|---|---|---|']
    # Node's own properties: the tuner is a GraphDriver, whose `publishers` is a method of its own.
    endpoints = [(publisher.topic_name, 'publishes', publisher.msg_type, publisher.qos_profile)
                 for publisher in Node.publishers.fget(node) if publisher.topic_name != '/parameter_events']
    endpoints += [(subscription.topic_name, 'subscribes', subscription.msg_type, subscription.qos_profile)
                  for subscription in Node.subscriptions.fget(node) if subscription.topic_name != '/parameter_events']
    for topic, direction, msg_type, profile in sorted(endpoints, key=lambda e: (e[1], e[0])):
        kind = f'{msg_type.__module__.split(".")[0]}/{msg_type.__name__}'
        lines.append(f'| `{topic}` | {direction} | `{kind}` | {_qos(profile)} |')
    services = sorted((service.srv_name, f'{service.srv_type.__module__.split(".")[0]}/{service.srv_type.__name__}')
                      for service in Node.services.fget(node) if not service.srv_name.startswith(own))
    lines += ['', 'Services: ' + (', '.join(f'`{name}` (`{kind}`)' for name, kind in services) or 'none')
              + '; and the standard parameter services.']
    lines += ['', '| parameter | type | default | range | unit | read-only | description |',
              '|---|---|---|---|---|---|---|']
    names = sorted(node._parameters)
    for name, descriptor in zip(names, node.describe_parameters(names)):
        unset = Parameter(name, Parameter.Type.NOT_SET)
        default = 'required' if name in required else _value(node.get_parameter_or(name, unset).value)
        read_only = 'yes' if descriptor.read_only else ''
        lines.append(f'| `{name}` | {PARAMETER_TYPES.get(descriptor.type, "")} | {_cell(default)} | '
                     f'{_range(descriptor)} | {_cell(units.get(name, ""))} | {read_only} | '
                     f'{_cell(descriptor.description)} |')
    return lines


def ros_interface() -> str:
    """The nodes' page: each node started with its defaults (and what it requires), in a context of its own."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from ddarm_control.node import ControllerNode
    from ddarm_sim.node import PlantNode
    from ddarm_sim.robot_node import RobotNode
    from ddarm_tuner.node import TunerNode

    context = Context()
    rclpy.init(context=context, args=[])
    nodes = []
    try:
        def overrides(name):
            return [Parameter(key, value=value) for key, value in REQUIRED.get(name, {}).items()]

        nodes = [('plant', 'ros2 run ddarm_sim plant',
                  PlantNode(context=context, parameter_overrides=overrides('plant'))),
                 # A lifecycle node: its topics are made at configure, which autostart does at launch.
                 ('robot', 'ros2 run ddarm_sim robot --ros-args -p mjcf:=FILE',
                  RobotNode(context=context, parameter_overrides=overrides('robot')))]
        nodes += [(law, f'ros2 run ddarm_control {law}',
                   ControllerNode(law, context=context, parameter_overrides=overrides(law)))
                  for law in ('pd_gravity', 'computed_torque')]
        nodes.append(('tuner', 'ros2 run ddarm_tuner tuner',
                      TunerNode(context=context, parameter_overrides=overrides('tuner'))))
        lines = ['# The ROS 2 interface of ddarm\'s nodes', '',
                 'Generated from the nodes themselves by `make docs` (`python -m ddarm.cli.docs`): each node started '
                 'with its defaults, its topics, services and declared parameters read back. Do not edit by hand: '
                 'every parameter is defined in `ddarm/ros/parameter_schema.py`, which the nodes declare theirs from. '
                 'A default `required` must be given (the gains by joint).']
        for title, run, node in nodes:
            kind = 'controller' if title in CONTROLLERS else title
            lines += _node_section(title, run, node, REQUIRED.get(title, {}), kind)
        return '\n'.join(lines) + '\n'
    finally:
        for _, _, node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


SPEC_PAGE = PAGE.with_name('model-specification.md')
# The episode's options in §14 of the model specification: (the field, its name on the page, its constraint); the
# default column is EPISODE_DEFAULTS' (ddarm.episodes.spec), written by `make docs` between the two markers.
EPISODE_OPTIONS = (
    ('controller', 'controller', '`pd_gravity` or `computed_torque`'),
    ('kp', 'kp, kv', 'n values each, finite and > 0; none: a template, which a search gives its gains'),
    ('trajectory', 'trajectory', '1 or 2'),
    ('duration', 'duration T', 'T/Δ a whole number; at most 10⁶ samples (`MAX_SAMPLES`)'),
    ('period', 'period Δ', '10⁻⁶ ≤ Δ ≤ 10 s in process (`ddarm/samples.py: PERIOD_RANGE`); 10⁻⁴ ≤ Δ ≤ 1 s on the '
     'nodes (`ddarm/physics/plant.py: NODE_PERIOD_RANGE`, their `period` parameter\'s range)'),
    ('delay', 'delay d', 'whole number in [0, 100]'),
    ('tau', 'tau τ', '0 ≤ τ ≤ T'),
    ('torque_limit', 'torque_limit', '`none`, `paper` (§7), `urdf` (every controlled joint\'s `<limit effort>` > 0, '
     '§16) or n values > 0'),
    ('external_torque', 'external_torque P^z', 'n finite values'),
    ('viscous_friction', 'viscous_friction, coulomb_friction', 'n values ≥ 0'),
    ('mass_scale', 'mass_scale', 'n values > 0, plant only'),
    ('substeps', 'substeps N', '1 … 10 000'),
    ('urdf', 'urdf', 'revolute, continuous, prismatic and fixed joints (§16)'),
    ('model_urdf', 'model_urdf', 'the same controlled joints as the plant\'s (§16)'),
    ('motion', 'motion', 'a motion file (§16); T defaults to its duration'),
    ('mjcf', 'mjcf, mjcf_joints', "a MuJoCo robot stepped instead of ddarm's plant ([robots.md](robots.md)), and its "
     'name of each controlled joint where it differs; without mass_scale, external_torque and friction'),
)
# What a default of None means, per field.
NONE_MEANS = {'controller': 'required', 'kp': 'none (a template)', 'duration': "the motion's (the paper's: 1 s)",
              'external_torque': 'none', 'viscous_friction': 'none', 'mass_scale': 'none (1)',
              'urdf': '`config/ddarm.urdf`', 'model_urdf': "the plant's URDF", 'motion': "the paper's `trajectory`",
              'mjcf': "none (ddarm's plant)"}
SPEC_MARKERS = ('<!-- episode options: generated by make docs from EPISODE_DEFAULTS; do not edit by hand -->',
                '<!-- end of the episode options -->')


def episode_options_table() -> str:
    """§14's table: each option of an episode, its default as EpisodeSpec gives it, its constraint."""
    from ddarm.episodes.spec import EPISODE_DEFAULTS

    lines = ['| option | default | constraint |', '|---|---|---|']
    for field, name, constraint in EPISODE_OPTIONS:
        default = EPISODE_DEFAULTS.get(field)
        shown = NONE_MEANS[field] if default is None else f'`{default}`' if isinstance(default, str) else f'{default}'
        unit = ' s' if field in ('period', 'tau') and default is not None else ''
        lines.append(f'| {name} | {shown}{unit} | {constraint} |')
    return '\n'.join(lines) + '\n'


def specification_page() -> str:
    """The model specification with its generated table in place."""
    text = SPEC_PAGE.read_text()
    start, end = (text.index(marker) for marker in SPEC_MARKERS)
    return text[:start + len(SPEC_MARKERS[0])] + '\n' + episode_options_table() + text[end:]


def main() -> int:
    PAGE.parent.mkdir(exist_ok=True)
    PAGE.write_text(cli_reference())
    ROS_PAGE.write_text(ros_interface())
    SPEC_PAGE.write_text(specification_page())
    configs = write_all()
    print(f'{PAGE}: {len(_commands(build_parser()))} commands; {ROS_PAGE}; {", ".join(map(str, configs))}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
