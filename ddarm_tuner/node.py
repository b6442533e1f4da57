"""The tuner node: drives episodes on the running plant and controller, records each as a bag, scores it from the bag."""

from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions

from ddarm.control.laws import CONTROLLERS, GainError
from ddarm.deprecation import renamed_keys
from ddarm.ros.executable import run_executable
from ddarm.ros.executors import node_executor
from ddarm.ros.parameter_files import parameter_document
from ddarm.ros.interface import (declare_from_schema, declare_joint_gains, flat_parameters, given_gains,
                                 keyed_gains_given, positional_gains, positional_gains_notice, proposed_values,
                                 refuse_undeclared_parameters, undeclared_overrides)
from ddarm.recording.bags import STORAGES, BagError, score_bag
from ddarm.recording.gains_file import CONTROLLER_RENAMED
from ddarm.episodes.indices import INDICES
from ddarm.episodes.spec import EpisodeError, EpisodeSpec, check_episode, read_motion_file
from ddarm.interrupts import Interrupted, stop_on_signals
from ddarm.motion.programmed import MotionError
from ddarm.ros.driver import GraphDriver, GraphEpisodeError
from ddarm.ros.node_parameters import READ_ONLY, episode_record, same_read_only
from ddarm.recording.runs import RunFolder


class TunerNode(GraphDriver):
    """A sweep of episodes (every τ of `taus` under every limit of `torque_limits`) for one law and gains.

    Gains come from `kp`/`kv`, or from `gains_file` (a controller parameter YAML such as
    `ddarm tune` writes). Results land in <output_root>/<run_name>/: a bag per episode,
    summary.json with the indices scored from each bag, and run.log. Every episode is checked
    before it starts (`ddarm.ros.driver.GraphDriver`): the plant and the controller on the
    graph once each, and nobody else publishing on the episode's topics.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('tuner', **kwargs)
        self._given_overrides = tuple(kwargs.get('parameter_overrides') or ())  # rclpy has no public view
        declare_from_schema(self, 'tuner', EpisodeError)
        refuse_undeclared_parameters(self, 'tuner')
        try:
            self.specs = self._checked_sweep()
        except BaseException:
            self.destroy_node()  # a refused tuner leaves no node on the graph behind it
            raise

    def _checked_sweep(self) -> list:
        values = proposed_values(self, ())
        try:
            self.joints = list(read_motion_file(values['motion'] or None, values['trajectory']).joint_names)
        except MotionError as error:
            raise EpisodeError(str(error)) from error
        for joint in self.joints:  # the gains by joint, as a controller takes them
            declare_joint_gains(self, joint)
        unknown = undeclared_overrides(self, self._given_overrides)
        if unknown:
            raise EpisodeError(f'unknown parameters {unknown} (not tuner parameters: a typo?)')
        self.values = proposed_values(self, ())
        if self.values['controller'] not in CONTROLLERS:
            raise EpisodeError(f"controller must be one of {CONTROLLERS}, got {self.values['controller']!r}")
        if self.values['storage'] not in STORAGES:
            raise EpisodeError(f"storage must be one of {sorted(STORAGES)}, got {self.values['storage']!r}")
        return self._episode_specs()

    def _gains(self) -> tuple[list, list, int]:
        values = self.values
        if values['gains_file']:
            try:
                document = parameter_document(values['gains_file'])
                gains = document[values['controller']]['ros__parameters']
                # Read by the controller node's own rule: gains.<joint>.p/.d or the positional kp/kv.
                kp, kv = given_gains({**flat_parameters(gains), 'omega': 0.0}, self.joints)
                gains = renamed_keys(gains, CONTROLLER_RENAMED, f"gains_file {values['gains_file']}", EpisodeError)
                delay, period = gains.get('delay', values['delay']), gains.get('period')
            except (ValueError, KeyError, TypeError, AttributeError) as error:
                # ValueError: a file beyond its bounds or not YAML (ParameterFileError), or gains the controller
                # would refuse (GainError, MotionError)
                raise EpisodeError(f"gains_file {values['gains_file']}: no {values['controller']} gains "
                                   f'({type(error).__name__}: {error})') from error
            if period is not None and period != values['period']:
                # Gains tuned for one sampling period are other gains at another: never swept silently.
                raise EpisodeError(f"gains_file {values['gains_file']} holds gains for period {period!r} s; the "
                                   f"sweep's period is {values['period']!r} s: set period to match")
            wanted = {'urdf': values['model_urdf'] or values['urdf'], 'motion': values['motion']}
            for name in READ_ONLY:  # gains for another arm or other joints: other gains too
                if name in gains and not same_read_only(name, gains[name], wanted[name]):
                    raise EpisodeError(f"gains_file {values['gains_file']} holds gains for the controller's {name} "
                                       f"{gains[name]!r}; the sweep's is {wanted[name]!r}: set urdf, model_urdf "
                                       'and motion to match')
            return kp, kv, delay
        positional = positional_gains(values)
        if not positional and not keyed_gains_given(values):
            raise EpisodeError(f'set the gains: gains.<joint>.p and .d for each joint of {self.joints}, or gains_file')
        try:
            kp, kv = given_gains({**values, 'omega': 0.0}, self.joints)
        except GainError as error:
            raise EpisodeError(str(error)) from error
        for name in positional:
            self.get_logger().warning(positional_gains_notice(name, 'tuner parameter'))
        return kp, kv, values['delay']

    def _episode_specs(self) -> list[tuple[str, EpisodeSpec]]:
        """Every episode of the sweep, checked as a run would check it: nothing reaches ROS to be refused there."""
        values = self.values
        kp, kv, delay = self._gains()
        if not values['taus'] or not values['torque_limits']:
            raise EpisodeError('taus and torque_limits need at least one value each')
        specs = []
        for limit in values['torque_limits']:
            for tau in values['taus']:
                if not np.isfinite(tau):
                    raise EpisodeError(f'taus: {tau!r} is not a finite number')
                try:
                    spec = EpisodeSpec(controller=values['controller'], kp=kp, kv=kv,
                                       trajectory=values['trajectory'], duration=values['duration'] or None,
                                       period=values['period'], delay=delay, tau=tau, torque_limit=limit,
                                       substeps=values['substeps'], urdf=values['urdf'] or None,
                                       model_urdf=values['model_urdf'] or None, motion=values['motion'] or None)
                    plan = check_episode(spec)
                except (EpisodeError, TypeError, ValueError) as error:
                    source = f"gains_file {values['gains_file']}" if values['gains_file'] else 'parameters'
                    raise EpisodeError(f'episode τ = {tau:g}, torque limit {limit!r} ({source}): {error}') from error
                specs.append((f'{len(specs):03d}-tau{tau:g}-{limit}', spec, plan))
        return specs

    def run_sweep(self, executor, run: RunFolder) -> None:
        for name, spec, plan in self.specs:
            path = run.bag_path(name)
            self.wait_for_peers(executor, spec.controller, self.values['peer_timeout'])
            with self.open_bag(path, episode_record(spec, plan, 'ros-lockstep', run.summary['command']),
                               self.values['storage']) as bag:
                result = self.run_episode(executor, spec, plan, bag, timeout=self.values['episode_timeout'],
                                          peer_timeout=self.values['peer_timeout'])
                bag.close(complete=True)
            # The episode is on disk and closed: scoring it needs no ROS.
            scored = score_bag(path)
            kept = (*INDICES, 'diverged', 'diverged_at', 'diverged_at_sample', 'max_abs_error_deg', 'max_abs_torque',
                    'spec')
            run.add_episode({'name': name, 'bag': str(path), **{key: scored[key] for key in kept},
                             'graph_indices': result.indices()})
            self.get_logger().info(f"{name}: I1 {scored['I1']:.6g}  I2 {scored['I2']:.6g}  I {scored['I']:.6g}"
                                   f'  (scored from {path})')


def main(args=None) -> int:
    """The tuner as an executable: 0 when the sweep completed, 2 when it failed or was refused,
    128 + the signal when SIGINT or SIGTERM stopped it (finished bags complete, the one under way
    marked incomplete, the summary `interrupted`)."""
    args = sys.argv if args is None else args
    try:
        # Our handlers, not rclpy's: a signal then stops the sweep at once, wherever it is.
        with stop_on_signals():
            return run_executable('tuner', TunerNode, (EpisodeError, BagError), args, lambda node: sweep(node, args),
                                  out=sys.stderr, signal_handler_options=SignalHandlerOptions.NO, follow=False)
    except Interrupted as stop:
        print(f'tuner: {stop}; the run is marked interrupted', file=sys.stderr, flush=True)
        return stop.exit_code


def sweep(node: TunerNode, args) -> int:
    """The started tuner's sweep into a new run folder: 0 when it completed, 2 when it failed."""
    executor = node_executor()
    try:
        executor.add_node(node)
        name = node.values['run_name'] or time.strftime('tuner-%Y%m%d-%H%M%S')
        try:
            run = RunFolder(name, node.values['output_root'], command=' '.join(args))
        except BagError as error:
            print(f'tuner: {error}', file=sys.stderr, flush=True)
            return 2
        with run:
            try:
                node.run_sweep(executor, run)
            except (GraphEpisodeError, BagError) as error:
                print(f'tuner: {error}', file=sys.stderr, flush=True)
                run.finish('failed', error=str(error))
                return 2
            run.finish('complete')
        return 0
    except ExternalShutdownException:
        print('tuner: ROS was shut down under the sweep; the run is marked failed', file=sys.stderr, flush=True)
        return 2
    finally:
        executor.shutdown()


if __name__ == '__main__':
    raise SystemExit(main())
