"""How an episode maps to node parameters: the `ros__parameters` that make the plant and a controller
run an EpisodeSpec, the subset set through their parameter services, and the record a bag carries."""

from __future__ import annotations

from rclpy.parameter import Parameter

from ddarm.episodes.spec import EpisodePlan, EpisodeSpec
from ddarm.physics.arm import load_arm

# Lockstep waits this long (wall clock) for a command before the plant ends the episode.
COMMAND_TIMEOUT = 10.0
# The plant starts an episode once this many nodes listen to it: the controller and the driver.
GRAPH_SUBSCRIBERS = 2


def node_parameters(spec: EpisodeSpec, plan: EpisodePlan, mode: str = 'lockstep') -> dict:
    """The parameters (as a node: ros__parameters: mapping) that make the plant and controller run `spec`.

    Per-joint options left out mean "none"; set through the parameter services, they are empty arrays.
    """
    plant = {
        'mode': mode, 'period': spec.period, 'substeps': spec.substeps, 'command_timeout': COMMAND_TIMEOUT,
        'required_subscribers': GRAPH_SUBSCRIBERS, 'max_samples': plan.k_max + 1, 'autostart': False,
        'trajectory': spec.trajectory, 'duration': spec.duration, 'tau': spec.tau,
    }
    optional = {'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
                'viscous_friction': spec.viscous_friction, 'coulomb_friction': spec.coulomb_friction,
                'external_torque': spec.external_torque, 'mass_scale': spec.mass_scale}
    plant.update({name: [float(x) for x in value] for name, value in optional.items() if value is not None})
    controller = {'kp': list(spec.kp), 'kv': list(spec.kv), 'omega': 0.0, 'compute_delay_steps': spec.delay,
                  'period': spec.period}
    # The in-process runner gives computed torque the plant's friction as its model F̂; so does this.
    controller.update({name: list(getattr(spec, name)) for name in ('viscous_friction', 'coulomb_friction')
                       if getattr(spec, name) is not None})
    if spec.urdf:
        plant['urdf'] = controller['urdf'] = spec.urdf
    return {'plant': {'ros__parameters': plant}, spec.controller: {'ros__parameters': controller}}


def service_parameters(values: dict, clear: tuple[str, ...]) -> list[Parameter]:
    """Parameters to set at run time: read-only ones left out, unset per-joint options cleared."""
    parameters = [Parameter(name, value=value) for name, value in values.items() if name != 'urdf']
    parameters += [Parameter(name, Parameter.Type.DOUBLE_ARRAY, []) for name in clear if name not in values]
    return parameters


PLANT_OPTIONAL = ('torque_limit', 'viscous_friction', 'coulomb_friction', 'external_torque', 'mass_scale')
CONTROLLER_OPTIONAL = ('viscous_friction', 'coulomb_friction')

def episode_record(spec: EpisodeSpec, plan: EpisodePlan, transport: str, command: str | None) -> dict:
    """The configuration a bag carries, so that the bag alone says what was run."""
    return {'spec': spec.to_dict(), 'joints': load_arm(spec.urdf).joint_names, 'k_max': plan.k_max,
            'torque_limit': None if plan.torque_limit is None else plan.torque_limit.tolist(),
            'transport': transport, 'command': command,
            'node_parameters': node_parameters(spec, plan, transport.removeprefix('ros-'))}

