"""The tuner node: drives episodes on the running plant and controller, records each as a bag, scores it from the bag."""

from __future__ import annotations

import sys
import time

import rclpy
import yaml
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter

from ddarm_control.laws import CONTROLLERS
from ddarm_sim.ros_interface import descriptor, proposed_values, undeclared_overrides
from ddarm_tuner.bags import BagError, EpisodeBagWriter, score_bag
from ddarm_tuner.episodes import EpisodeError, EpisodeSpec, plan_episode
from ddarm_tuner.ros_episode import GraphDriver, episode_record
from ddarm_tuner.runs import DEFAULT_ROOT, RunFolder


class TunerNode(GraphDriver):
    """A sweep of episodes (every τ of `taus` under every limit of `torque_limits`) for one law and gains.

    Gains come from `kp`/`kv`, or from `gains_file` (a controller parameter YAML such as
    `ddarm tune` writes). Results land in <output_root>/<run_name>/: a bag per episode,
    summary.json with the indices scored from each bag, and run.log.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('tuner', **kwargs)
        double_array = Parameter.Type.DOUBLE_ARRAY
        declared = [
            ('controller', 'computed_torque', descriptor(f'the law to drive: one of {CONTROLLERS}')),
            ('kp', double_array, descriptor('K_p diagonal (unless gains_file)')),
            ('kv', double_array, descriptor('K_v diagonal (unless gains_file)')),
            ('gains_file', '', descriptor('controller parameter YAML with kp, kv, compute_delay_steps')),
            ('trajectory', 1, descriptor('programmed motion 1 or 2', integer=(1, 2))),
            ('duration', 1.0, descriptor('T in s', floating=(1e-3, 3600.0))),
            ('period', 0.01, descriptor('Δ in s', floating=(1e-4, 1.0))),
            ('delay', 1, descriptor('compute delay d in samples (unless gains_file)', integer=(0, 100))),
            ('substeps', 8, descriptor('plant RK4 steps per period', integer=(1, 10_000))),
            ('taus', [0.0], descriptor('initial velocity disturbances τ (3.1), one episode each, s')),
            ('torque_limits', ['none'], descriptor("'none' and/or 'paper' (2 x max nominal), each with every τ")),
            ('output_root', str(DEFAULT_ROOT), descriptor('folder that holds the run folders')),
            ('run_name', '', descriptor('run folder name ("" = tuner-<date>-<time>); never reused')),
            ('storage', 'mcap', descriptor('bag storage: mcap or sqlite3')),
            ('episode_timeout', 120.0, descriptor('wall seconds one episode may take', floating=(1.0, 86400.0))),
        ]
        for name, default, described in declared:
            self.declare_parameter(name, default, described)
        unknown = undeclared_overrides(self)
        if unknown:
            raise EpisodeError(f'unknown parameters {unknown} (not tuner parameters: a typo?)')
        self.values = proposed_values(self, ())
        self.specs = self._episode_specs()

    def _gains(self) -> tuple[list, list, int]:
        values = self.values
        if values['gains_file']:
            try:
                document = yaml.safe_load(open(values['gains_file']))
                gains = document[values['controller']]['ros__parameters']
                return gains['kp'], gains['kv'], gains.get('compute_delay_steps', values['delay'])
            except (OSError, yaml.YAMLError, KeyError, TypeError) as error:
                raise EpisodeError(f"gains_file {values['gains_file']}: no {values['controller']} kp/kv "
                                   f'({type(error).__name__}: {error})') from error
        if values['kp'] is None or values['kv'] is None:
            raise EpisodeError('set kp and kv, or gains_file')
        return values['kp'], values['kv'], values['delay']

    def _episode_specs(self) -> list[tuple[str, EpisodeSpec]]:
        values = self.values
        kp, kv, delay = self._gains()
        specs = []
        for limit in values['torque_limits']:
            for tau in values['taus']:
                spec = EpisodeSpec(controller=values['controller'], kp=kp, kv=kv, trajectory=values['trajectory'],
                                   duration=values['duration'], period=values['period'], delay=delay, tau=tau,
                                   torque_limit=limit, substeps=values['substeps'])
                specs.append((f'{len(specs):03d}-tau{tau:g}-{limit}', spec))
        return specs

    def run_sweep(self, executor, run: RunFolder) -> None:
        for name, spec in self.specs:
            plan = plan_episode(spec)
            path = run.bag_path(name)
            with EpisodeBagWriter(path, episode_record(spec, plan, 'ros-lockstep', run.summary['command']),
                                  self.values['storage']) as bag:
                result = self.run_episode(executor, spec, plan, bag, timeout=self.values['episode_timeout'])
                bag.close(complete=True)
            # The episode is on disk and closed: scoring it needs no ROS.
            scored = score_bag(path)
            run.add_episode({'name': name, 'bag': str(path), **{key: scored[key] for key in (
                'I1', 'I2', 'I', 'diverged', 'diverged_at_sample', 'max_abs_error_deg', 'max_abs_torque',
                'spec')}, 'graph_indices': result.indices})
            self.get_logger().info(f"{name}: I1 {scored['I1']:.6g}  I2 {scored['I2']:.6g}  I {scored['I']:.6g}"
                                   f'  (scored from {path})')


def main(args=None) -> int:
    args = sys.argv if args is None else args
    rclpy.init(args=args)
    node, run = None, None
    status = 'failed'
    try:
        node = TunerNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        name = node.values['run_name'] or time.strftime('tuner-%Y%m%d-%H%M%S')
        run = RunFolder(name, node.values['output_root'], command=' '.join(args))
        node.run_sweep(executor, run)
        status = 'complete'
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 'interrupted'
    except (EpisodeError, BagError, ParameterException, RuntimeError) as error:
        if not rclpy.ok():  # a ROS call raced the shutdown of a SIGINT/SIGTERM
            status = 'interrupted'
        else:
            print(f'tuner: {error}', flush=True)
            if run is not None:
                run.log.error('%s', error)
    finally:
        if run is not None:
            run.finish(status)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0 if status in ('complete', 'interrupted') else 2


if __name__ == '__main__':
    raise SystemExit(main())
