"""`ddarm identify BAG... --urdf FILE --out FILE.urdf`: the robot's dynamic parameters from its recorded episodes."""

from __future__ import annotations

import argparse
import math
import shlex
from pathlib import Path

from ddarm.cli.arguments import finite, new_output_path, whole_number
from ddarm.cli.output import print_json
from ddarm.episodes.spec import read_motion_file
from ddarm.motion.programmed import MotionError
from ddarm.physics.arm import ModelError, load_arm, movable_joints
from ddarm.physics.identification import (REST_VELOCITY, Identification, IdentificationError, PeriodSamples,
                                          identified_urdf, identify, identify_payload, joined, joint_parameters,
                                          link_inertia, parameter_samples, period_samples, relative_residual)
from ddarm.physics.regressor import JOINT_PARAMETERS
from ddarm.recording.bags import BagEpisode, checked_output_path, read_episode_bag
from ddarm.recording.runs import write_new_text


def add_identify_parser(commands) -> None:
    identify_parser = commands.add_parser('identify', help="the robot's dynamic parameters (inertias, armature, "
                                                           'friction) from its recorded episodes, as a URDF')
    identify_parser.add_argument('bags', nargs='+', metavar='BAG', help='episode bags to fit on (ddarm episode --ros '
                                                                        '--bag, e.g. of a ddarm motion --excite)')
    identify_parser.add_argument('--urdf', required=True, metavar='FILE',
                                 help="the arm's URDF: its joints, kinematics and the values held where the data "
                                      'is silent')
    identify_parser.add_argument('--out', required=True, type=new_output_path, metavar='FILE.urdf',
                                 help='the identified URDF (new file)')
    identify_parser.add_argument('--validate', nargs='+', default=[], metavar='BAG',
                                 help='bags not fitted on, on which the torque residuals are reported')
    identify_parser.add_argument('--cutoff', type=finite, metavar='HZ',
                                 help='a zero-phase low-pass of q, q̇ and the torques first (for measured noise; '
                                      'default none)')
    identify_parser.add_argument('--payload', type=payload_point, metavar='LINK=X,Y,Z',
                                 help="take the URDF's links as they are and identify a payload's mass at this point "
                                      "of LINK's frame (m), with each joint's armature, damping and friction")
    identify_parser.add_argument('--samples', type=whole_number(0, 100), default=0, metavar='K',
                                 help="also write K URDFs of parameters drawn within the estimate's standard "
                                      'deviations, <out>-sample-<k>.urdf, for ddarm tune --robust-urdf (0)')
    identify_parser.add_argument('--json', action='store_true', help='print one JSON object')
    identify_parser.set_defaults(handler=command_identify)


def payload_point(text: str) -> tuple[str, tuple[float, float, float]]:
    """An argparse type: LINK=X,Y,Z, a point of the link's frame in m."""
    link, equals, point = text.rpartition('=')
    try:
        values = tuple(float(value) for value in point.split(','))
    except ValueError:
        values = ()
    if not (equals and link and len(values) == 3 and all(map(math.isfinite, values))):
        raise argparse.ArgumentTypeError(f'{text!r} is not LINK=X,Y,Z (a link and three finite numbers, m)')
    return link, values


def bag_periods(bag: BagEpisode, cutoff: float | None) -> tuple[PeriodSamples, float]:
    """The bag's periods: the states of samples 0 … K (to the last one before a divergence) and the torque held
    over each (the effort of the next state)."""
    period = bag.episode.get('spec', {}).get('period')
    if not isinstance(period, (int, float)) or isinstance(period, bool) or not period > 0:
        raise IdentificationError(f'{bag.path}: its episode configuration has no sampling period')
    q, v, torque = [], [], []
    n = 0
    while n + 1 in bag.states and all(x is not None for x in (*bag.states[n][:2], bag.states[n + 1][0],
                                                              bag.states[n + 1][2])):
        q.append(bag.states[n][0])
        v.append(bag.states[n][1])
        torque.append(bag.states[n + 1][2])
        n += 1
    if n < 2:
        raise IdentificationError(f'{bag.path}: it holds {n} periods with states and efforts: nothing to identify '
                                  'from (a bag without efforts, or an episode that diverged at once)')
    q.append(bag.states[n][0])
    v.append(bag.states[n][1])
    torque.append(torque[-1])  # the last state's own period is not in the bag: period_samples drops it
    return period_samples(q, v, torque, float(period), str(bag.path), cutoff), float(period)


def locked_joints(bag: BagEpisode, urdf: str) -> tuple[tuple[str, float], ...]:
    """The URDF's movable joints the bag's episode held still, where its motion file said (none: every movable
    joint was controlled)."""
    others = [name for name in movable_joints(urdf) if name not in bag.joints]
    if not others:
        return ()
    motion = bag.episode.get('spec', {}).get('motion')
    try:
        locked = read_motion_file(motion).locked if isinstance(motion, str) else None
    except MotionError as error:
        raise IdentificationError(f'{bag.path}: the URDF {urdf} has joints {others} the episode did not control, '
                                  f'held where its motion file says, which cannot be read: {error}') from error
    if locked is None:
        raise IdentificationError(f'{bag.path}: the URDF {urdf} has joints {others} the episode did not control, and '
                                  'its configuration names no motion file that says where they were held')
    return tuple(locked)


def command_identify(args: argparse.Namespace) -> int:
    out = checked_output_path(args.out)
    if not out.absolute().parent.is_dir():
        raise IdentificationError(f'{out}: no folder {out.parent} to write it in')
    fitted = [read_episode_bag(path) for path in args.bags]
    held_out = [read_episode_bag(path) for path in args.validate]
    report = identify_bags(args.urdf, fitted, held_out, out, shlex.join(['ddarm', *args.argv]), args.cutoff,
                           args.payload, args.samples)
    if args.json:
        print_json(report)
    else:
        print_identification(report)
    return 0


def identify_bags(urdf: str, fitted: list[BagEpisode], held_out: list[BagEpisode], out: Path, command: str,
                  cutoff: float | None = None, payload=None, samples: int = 0) -> dict:
    """Identify the URDF's arm from the `fitted` bags (with `payload`, LINK and point, its mass instead of the
    links'), report the residuals on `held_out`, write the identified URDF at `out` and `samples` URDFs drawn within
    its standard deviations beside it: `ddarm identify`'s work, its report."""
    first = fitted[0]
    for bag in fitted + held_out:
        if list(bag.joints) != list(first.joints):
            raise IdentificationError(f'{bag.path} records joints {list(bag.joints)}, {first.path} '
                                      f'{list(first.joints)}: bags of one arm only')
    locked = locked_joints(first, urdf)
    try:
        arm = load_arm(str(Path(urdf).absolute()), None, tuple(first.joints), locked)
    except ModelError as error:
        raise IdentificationError(f'{error} (the joints of {first.path})') from error
    fit_data = joined([bag_periods(bag, cutoff)[0] for bag in fitted])
    result = identify(arm, fit_data) if payload is None else identify_payload(arm, fit_data, *payload)
    validation = []
    for bag in held_out:
        data = bag_periods(bag, cutoff)[0]
        validation.append((str(bag.path), relative_residual(arm, result.estimate, data),
                           relative_residual(arm, result.estimate, data, moving_only=False)))
    report = identification_report(arm, result, validation, str(out), command)
    write_new_text(out, identified_urdf(arm, result.estimate, urdf_header(report)))
    report['samples_written'] = []
    for k, phi in enumerate(parameter_samples(arm, result, samples), start=1):
        sample = out.with_name(f'{out.stem}-sample-{k}{out.suffix}')
        write_new_text(sample, identified_urdf(arm, phi, urdf_header(report) + f'\nSample {k} of {samples}: '
                                               'base parameters drawn within their standard deviations.'))
        report['samples_written'].append(str(sample))
    return report


def identification_report(arm, result: Identification, validation, out: str, command: str) -> dict:
    estimate, prior = (joint_parameters(phi, arm.dof) for phi in (result.estimate, result.prior))
    joints = []
    for i, name in enumerate(arm.joint_names):
        entry = {'joint': name, 'mass': float(link_inertia(result.estimate, i).mass),
                 'mass_urdf': float(link_inertia(result.prior, i).mass)}
        for parameter in JOINT_PARAMETERS:
            entry[parameter] = float(estimate[parameter][i])
            entry[f'{parameter}_urdf'] = float(prior[parameter][i])
        joints.append(entry)
    return {
        'urdf': str(arm.urdf_path), 'out': out, 'command': command, 'joint_names': list(arm.joint_names),
        'samples': result.samples, 'condition_number': result.condition_number,
        'base_parameters': [{'pivot': result.names[column], 'value': float(value), 'std': float(std)}
                            for column, value, std in zip(result.base, result.base_estimate, result.base_std)],
        'joints': joints,
        'fit_residual': dict(zip(arm.joint_names, result.fit_residual.tolist())),
        'least_squares_residual': dict(zip(arm.joint_names, result.base_residual.tolist())),
        'rest_velocity': REST_VELOCITY,
        'validation_residual': [{'bag': bag, **dict(zip(arm.joint_names, residual.tolist()))}
                                for bag, residual, _ in validation],
        'validation_residual_all_samples': [{'bag': bag, **dict(zip(arm.joint_names, residual.tolist()))}
                                            for bag, _, residual in validation],
        'constrained': list(result.least_squares_problems),
        'payload': None if result.payload is None else {
            'link': result.payload.link, 'point': list(result.payload.point), 'mass': result.payload.mass,
            'std': result.payload.std},
    }


def urdf_header(report: dict) -> str:
    return '\n'.join([
        f"Identified by: {report['command']}",
        f"From {report['samples']} sampling periods; {len(report['base_parameters'])} base parameters; condition "
        f"number {report['condition_number']:.4g}.",
        'Each controlled joint\'s composite body (every link it moves, fixed to it or beyond a locked joint) is its '
        'child link\'s <inertial>; the other links it moves have none. Where the data cannot tell parameters apart, '
        'they are held near the URDF\'s.'])


def _joints(entry: dict) -> dict:
    return {key: value for key, value in entry.items() if key != 'bag'}


def _residuals(values: dict) -> str:
    return '  '.join(f'{value:.3%}' for value in values.values())


def print_identification(report: dict) -> None:
    print(f"identified {report['out']} from {report['samples']} periods: {len(report['base_parameters'])} base "
          f"parameters, condition number {report['condition_number']:.4g}")
    header = ['joint', 'mass kg', '(URDF)', 'armature', '(URDF)', 'damping', '(URDF)', 'friction', '(URDF)']
    rows = [[entry['joint'], *(f'{entry[key]:.4g}' for key in (
        'mass', 'mass_urdf', 'armature', 'armature_urdf', 'damping', 'damping_urdf', 'friction', 'friction_urdf'))]
        for entry in report['joints']]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print('  ' + '  '.join(cell.rjust(width) if i else cell.ljust(width)
                               for i, (cell, width) in enumerate(zip(row, widths))))
    print(f"  torque residual (RMS / RMS torque) per joint where it moves (|q̇| >= {report['rest_velocity']:g}), "
          f"fit: {_residuals(report['fit_residual'])}")
    for moving, every in zip(report['validation_residual'], report['validation_residual_all_samples']):
        print(f"  on {moving['bag']} (not fitted): {_residuals(_joints(moving))}; with the samples at rest, where "
              f"friction holds the joint: {_residuals(_joints(every))}")
    for sample in report.get('samples_written', []):
        print(f'  sample {sample}')
    if not report['validation_residual']:
        print('  no --validate bag: the residuals above are on the fitted data only')
    if report['constrained']:
        print('  the least-squares solution was not physically consistent ('
              + '; '.join(report['constrained']) + '): the parameters written are the consistent ones nearest it in '
              'fit')
    payload = report['payload']
    if payload is None:
        print('  masses of links the data cannot weigh alone stay near the URDF\'s: see base_parameters (--json)')
    else:
        print(f"  payload on {payload['link']} at {payload['point']} m: {payload['mass']:.4g} ± {payload['std']:.2g} kg "
              "(the URDF's links taken as they are)")
