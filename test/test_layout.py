"""The layout's one hard rule: only modules that face ROS (node, ros, driver, session, graph or cli in
their path) load rclpy; the core (physics, laws, indices, recording, tuning, the paper) runs without it."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ROS_FACING = ('node', 'ros', 'driver', 'session', 'graph', 'cli')
MODULES = sorted('.'.join(path.relative_to(ROOT).with_suffix('').parts)
                 for package in ('ddarm', 'ddarm_sim', 'ddarm_control', 'ddarm_tuner')
                 for path in (ROOT / package).rglob('*.py'))
CORE = [module for module in MODULES
        if not any(word in ROS_FACING for part in module.split('.') for word in part.split('_'))]


def test_the_core_is_found():
    assert 'ddarm.physics.plant' in CORE and 'ddarm.paper.experiments' in CORE and 'ddarm_sim.node' not in CORE


@pytest.mark.parametrize('module', CORE)
def test_no_core_module_loads_rclpy(module):
    done = subprocess.run([sys.executable, '-c', f'import sys, {module}; print(sorted(name for name in sys.modules '
                           f"if name.split('.')[0] in ('rclpy', 'rosidl_runtime_py')))"],
                          capture_output=True, text=True, cwd=ROOT, check=True)
    assert done.stdout.strip() == '[]', f'{module} loads {done.stdout.strip()}'
