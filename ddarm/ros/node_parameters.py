"""How an episode maps to node parameters: the `ros__parameters` that make the plant and a controller
run an EpisodeSpec, the subset set through their parameter services, and the record a bag carries."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rclpy.parameter import Parameter

from ddarm.episodes.spec import EpisodePlan, EpisodeSpec, arm_joints
from ddarm.physics.arm import same_urdf
from ddarm.ros.interface import flat_parameters
from ddarm.ros.parameter_schema import read_only

# Lockstep waits this long (wall clock) for a command before the plant ends the episode.
COMMAND_TIMEOUT = 10.0
# The plant starts an episode once this many nodes listen to it: the controller and the driver.
GRAPH_SUBSCRIBERS = 2
# What the plant and a controller are built from when they start (the arm and the joints controlled), which the
# driver checks before each episode. '' is the default: the paper's arm, and its joints (or every movable joint).
READ_ONLY = ('urdf', 'motion')


@dataclass(frozen=True)
class SchedulingOptions:
    """What the node processes are asked for in real time (`ddarm episode --realtime-priority …`); None: not set,
    each node keeps what it has. Priority and cores go to the plant and the controller, the spin margin to the plant.
    """

    priority: int | None = None
    affinity: tuple[int, ...] | None = None
    spin_margin: float | None = None

    def parameters(self, node: str) -> dict:
        values = {'realtime_priority': self.priority,
                  'cpu_affinity': None if self.affinity is None else [int(core) for core in self.affinity]}
        if node == 'plant':
            values['spin_margin'] = self.spin_margin
        return {name: value for name, value in values.items() if value is not None}


def gains_parameters(spec: EpisodeSpec) -> dict:
    """The episode's gains as a controller node holds them: by joint name, `gains: {<joint>: {p: K_p, d: K_v}}`."""
    joints = arm_joints(spec)[0]
    return {'gains': {joint: {'p': float(p), 'd': float(d)} for joint, p, d in zip(joints, spec.kp, spec.kv)}}


def arm_parameters(spec: EpisodeSpec) -> dict[str, dict[str, str]]:
    """The read-only parameters the plant and the `spec` law's controller must have been started with.

    The plant integrates `urdf`; the controller's model is `model_urdf` (or the plant's URDF); both
    reduce their URDF to the joints of the one `motion` file, the others locked where it says.
    """
    motion = spec.motion or ''
    return {'plant': {'urdf': spec.urdf or '', 'motion': motion, 'mjcf': spec.mjcf or '',
                      'mjcf_joints': list(spec.mjcf_joints or [])},
            spec.controller: {'urdf': spec.model_urdf or spec.urdf or '', 'motion': motion}}


def same_read_only(name: str, given, wanted: str) -> bool:
    """Whether a node's `urdf`, `motion` or `mjcf` (a path; '' the default) names the same file as `wanted`, or its
    `mjcf_joints` are the same names."""
    if name == 'mjcf_joints':  # a string array; unset (None, or '' from a node without it) is none
        return (given in (None, '') or isinstance(given, list)) and list(given or []) == list(wanted)
    if not isinstance(given, str):
        return False
    if name == 'urdf':
        return same_urdf(given or None, wanted or None)
    if not given or not wanted:
        return given == wanted
    return Path(given).resolve() == Path(wanted).resolve()


def node_parameters(spec: EpisodeSpec, plan: EpisodePlan, mode: str = 'lockstep',
                    scheduling: SchedulingOptions | None = None) -> dict:
    """The parameters (as a node: ros__parameters: mapping) that make the plant and controller run `spec`.

    Per-joint options left out mean "none"; set through the parameter services, they are empty arrays.
    Read-only parameters left at their default ('') are left out; so is the scheduling not asked for.
    """
    plant = {
        'mode': mode, 'period': spec.period, 'substeps': spec.substeps, 'command_timeout': COMMAND_TIMEOUT,
        'required_subscribers': GRAPH_SUBSCRIBERS, 'required_clock_subscribers': 1, 'max_samples': plan.k_max + 1,
        'autostart': False,
        'trajectory': spec.trajectory, 'duration': spec.duration, 'tau': spec.tau,
    }
    optional = {'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
                'viscous_friction': spec.viscous_friction, 'coulomb_friction': spec.coulomb_friction,
                'external_torque': spec.external_torque, 'mass_scale': spec.mass_scale}
    plant.update({name: [float(x) for x in value] for name, value in optional.items() if value is not None})
    controller = {**gains_parameters(spec), 'omega': 0.0, 'delay': spec.delay, 'period': spec.period}
    # The in-process runner gives computed torque the plant's friction as its model F̂; so does this.
    controller.update({name: list(getattr(spec, name)) for name in ('viscous_friction', 'coulomb_friction')
                       if getattr(spec, name) is not None})
    arms = arm_parameters(spec)
    plant.update({name: value for name, value in arms['plant'].items() if value})
    controller.update({name: value for name, value in arms[spec.controller].items() if value})
    if scheduling is not None:
        plant.update(scheduling.parameters('plant'))
        controller.update(scheduling.parameters(spec.controller))
    return {'plant': {'ros__parameters': plant}, spec.controller: {'ros__parameters': controller}}


def service_parameters(values: dict, clear: tuple[str, ...], node: str) -> list[Parameter]:
    """Parameters to set at run time on a `node` ('plant' or 'controller'), from its `ros__parameters` (nested
    mappings as dotted names): its read-only ones (the schema's) left out, unset per-joint options cleared."""
    fixed = read_only(node)
    parameters = [Parameter(name, value=value) for name, value in flat_parameters(values).items() if name not in fixed]
    parameters += [Parameter(name, Parameter.Type.DOUBLE_ARRAY, []) for name in clear if name not in values]
    return parameters


PLANT_OPTIONAL = ('torque_limit', 'viscous_friction', 'coulomb_friction', 'external_torque', 'mass_scale')
CONTROLLER_OPTIONAL = ('viscous_friction', 'coulomb_friction')


def episode_record(spec: EpisodeSpec, plan: EpisodePlan, transport: str, command: str | None,
                   scheduling: SchedulingOptions | None = None) -> dict:
    """The configuration a bag carries, so that the bag alone says what was run."""
    return {'spec': spec.to_dict(), 'joints': list(plan.joint_names), 'prismatic': list(plan.prismatic),
            'k_max': plan.k_max,
            'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
            'transport': transport, 'command': command,
            'node_parameters': node_parameters(spec, plan, transport.removeprefix('ros-'), scheduling)}
