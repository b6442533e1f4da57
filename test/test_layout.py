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


# The layers, upstream first: a module may import its own layer and the ones before it, never a later one.
LAYERS = (
    # ddarm.reporting.text, how text from files is shown, imports nothing of ddarm: recording's refusals show names.
    ('ddarm.errors', 'ddarm.deprecation', 'ddarm.arrays', 'ddarm.samples', 'ddarm.datafiles', 'ddarm.strict_json',
     'ddarm.interrupts', 'ddarm.realtime', 'ddarm.reporting.text'),
    ('ddarm.physics',),
    ('ddarm.motion',),
    ('ddarm.control',),
    ('ddarm.episodes',),
    ('ddarm.recording',),
    ('ddarm.reporting',),
    ('ddarm.tuning',),
    ('ddarm.paper',),
    ('ddarm.ros',),
    ('ddarm.cli', 'ddarm_sim', 'ddarm_control', 'ddarm_tuner'),
)


def layer(module: str) -> int:
    for number, prefixes in enumerate(LAYERS):
        if any(module == prefix or module.startswith(prefix + '.') for prefix in prefixes):
            return number
    raise AssertionError(f'{module} belongs to no layer of test_layout.LAYERS')


def imported_modules(module: str) -> set[str]:
    """Every ddarm module `module` imports, at the top or inside a function."""
    import ast

    path = ROOT / Path(*module.split('.')).with_suffix('.py')
    if not path.exists():
        path = ROOT / Path(*module.split('.')) / '__init__.py'
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return {name for name in names if name.split('.')[0] in ('ddarm', 'ddarm_sim', 'ddarm_control', 'ddarm_tuner')}


@pytest.mark.parametrize('module', [module for module in MODULES if not module.endswith('__init__')])
def test_nothing_downstream_is_imported_upstream(module):
    later = sorted(name for name in imported_modules(module) if layer(name) > layer(module))
    assert not later, f'{module} (layer {layer(module)}) imports the later {later}'
