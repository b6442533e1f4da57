"""`ros2 run` works after `colcon build`: ament index markers and lib/<package>/<executable>, resolved as ros2run does."""

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from std_srvs.srv import Trigger

ROOT = Path(__file__).resolve().parent.parent
EXECUTABLES = [('ddarm_sim', 'plant', 'plant.yaml', '/plant/reset'),
               ('ddarm_sim', 'robot', 'robot.yaml', '/robot/status'),
               ('ddarm_control', 'pd_gravity', 'pd_gravity.yaml', '/pd_gravity/reset'),
               ('ddarm_control', 'computed_torque', 'computed_torque.yaml', '/computed_torque/reset')]


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    """This repository built by colcon into a temporary folder, as on a full ROS install."""
    colcon = shutil.which('colcon') or str(Path(sys.executable).with_name('colcon'))
    workspace = tmp_path_factory.mktemp('workspace')
    subprocess.run([colcon, '--log-base', str(workspace / 'log'), 'build', '--base-paths', str(ROOT),
                    '--build-base', str(workspace / 'build'), '--install-base', str(workspace / 'install')],
                   cwd=workspace, check=True, capture_output=True, timeout=300)
    install = workspace / 'install' / 'ddarm'
    site_packages = next(install.glob('lib/python*/site-packages'))
    environment = {**os.environ, 'AMENT_PREFIX_PATH': str(install),
                   'PYTHONPATH': str(site_packages),
                   'PATH': f'{Path(sys.executable).parent}{os.pathsep}{os.environ["PATH"]}'}
    return install, environment


def resolve(package, executable, environment):
    """What ros2run does: get_package_prefix(package) / lib / package / executable."""
    code = ('from ament_index_python.packages import get_package_prefix; import sys; '
            'print(get_package_prefix(sys.argv[1]))')
    prefix = subprocess.run([sys.executable, '-c', code, package], env=environment, capture_output=True,
                            text=True, check=True).stdout.strip()
    return Path(prefix) / 'lib' / package / executable


# A node of a fresh colcon install compiles its loop before it comes up (its numba cache is its own): about
# 30 s for the plant on the 2-core machine, more when it is busy.
def wait_for_service(name, timeout=120.0):
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('layout_probe', context=context)
    try:
        client = node.create_client(Trigger, name)
        assert client.wait_for_service(timeout_sec=timeout), f'{name} never appeared'
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize('package, executable, parameters, service', EXECUTABLES)
def test_ros2_run_resolves_and_starts_each_node(colcon_install, package, executable, parameters, service):
    install, environment = colcon_install
    path = resolve(package, executable, environment)
    assert path == install / 'lib' / package / executable
    assert os.access(path, os.X_OK)
    process = subprocess.Popen([str(path), '--ros-args', '--params-file', str(ROOT / 'config' / parameters)],
                               env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               cwd=ROOT)  # the files the parameter files name are relative to the checkout
    try:
        wait_for_service(service)
        assert process.poll() is None
    finally:
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=20)
    assert process.returncode == 0, output
    # Outside the source tree, the environment imports the colcon install, not this checkout.
    assert str(install) in subprocess.run(
        [sys.executable, '-c', 'import ddarm_sim; print(ddarm_sim.__file__)'], env=environment, cwd=install,
        capture_output=True, text=True).stdout


def test_the_package_and_its_config_are_installed_under_share(colcon_install):
    install, _ = colcon_install
    for name in ('ddarm', 'ddarm_sim', 'ddarm_control', 'ddarm_tuner'):
        assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' / name).is_file()
    for name in ('ddarm.urdf', 'plant.yaml', 'robot.yaml', 'pd_gravity.yaml', 'computed_torque.yaml', 'tuner.yaml'):
        assert (install / 'share' / 'ddarm' / 'config' / name).is_file()


@pytest.mark.parametrize('arguments, service', [(['plant'], '/plant/reset'),
                                                (['controller', 'computed_torque'], '/computed_torque/reset')])
def test_the_pip_install_starts_the_same_nodes(arguments, service):
    ddarm = Path(sys.executable).with_name('ddarm')
    parameters = ROOT / 'config' / ('plant.yaml' if arguments == ['plant'] else 'computed_torque.yaml')
    process = subprocess.Popen([str(ddarm), *arguments, '--ros-args', '--params-file', str(parameters)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_service(service)
    finally:
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=20)
    assert process.returncode == 0, output


def test_ros2_run_resolves_and_starts_the_tuner(colcon_install, tmp_path):
    install, environment = colcon_install
    path = resolve('ddarm_tuner', 'tuner', environment)
    assert path == install / 'lib' / 'ddarm_tuner' / 'tuner' and os.access(path, os.X_OK)
    # Started with config/tuner.yaml plus a mistyped parameter, it reads both and refuses by name.
    done = subprocess.run([str(path), '--ros-args', '--params-file', str(ROOT / 'config' / 'tuner.yaml'),
                           '-p', 'output_root:=' + str(tmp_path), '-p', 'tauz:=0.1'],
                          env=environment, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "unknown parameters ['tauz']" in done.stdout + done.stderr
