"""Motion files: a programmed motion and the joints it drives, as YAML.

```yaml
joint_names: [joint1, joint2, joint3]  # the controlled joints, in the order of start and goal
duration: 1.0                          # T, s
profile: bang_bang                     # s(t/T) of spec §4
start: [0.0, 1.0471975511965976, -2.0943951023931953]  # q(0), rad
goal: [1.5707963267948966, 0.0, 0.0]                    # q(T), rad
```

Every refusal is a MotionError naming the file and the field: a motion file is edited by hand, and a
wrong one must never become a different motion silently.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ddarm.motion.programmed import MotionError, ProgrammedMotion

PROFILES = ('bang_bang',)
FIELDS = ('joint_names', 'duration', 'profile', 'start', 'goal')


@dataclass(frozen=True)
class MotionFile:
    """A motion file's content: the joints, by name, and their motion, in that order."""

    joint_names: tuple[str, ...]
    motion: ProgrammedMotion


class DataLoader(yaml.SafeLoader):
    """The YAML of ddarm's data files (motions, the paper's settings): safe, with two fixes to YAML 1.1.

    PyYAML keeps the last of two equal keys; a file with two `goal`s is refused instead. And YAML 1.1
    reads a float without a dot (`1e-05`, repr's own spelling of some doubles) as a string; it reads
    as the number here, as YAML 1.2 has it.
    """

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f'duplicate key {key!r}', key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


DataLoader.add_implicit_resolver('tag:yaml.org,2002:float', re.compile(r'^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$'),
                                 list('-+0123456789'))


def load_motion(path: Path | str) -> MotionFile:
    """The motion file at `path`; MotionError names the file and the field of anything it cannot use."""
    path = Path(path)
    try:
        document = yaml.load(path.read_text(), Loader=DataLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise MotionError(f'{path}: cannot read the motion file: {error}') from error
    if not isinstance(document, dict):
        raise MotionError(f'{path}: a motion file is a mapping of {", ".join(FIELDS)}, got {type(document).__name__}')
    unknown = [key for key in document if key not in FIELDS]
    if unknown:
        raise MotionError(f'{path}: unknown key {unknown[0]!r} (a motion file has {", ".join(FIELDS)})')
    missing = [key for key in FIELDS if key not in document]
    if missing:
        raise MotionError(f'{path}: missing key {missing[0]!r}')
    names = document['joint_names']
    if (not isinstance(names, list) or not names
            or not all(isinstance(name, str) and name for name in names)):
        raise MotionError(f'{path}: joint_names must be a non-empty list of names, got {names!r}')
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise MotionError(f'{path}: joint_names names {repeated} more than once')
    duration = _number(path, 'duration', document['duration'])
    if not duration > 0:
        raise MotionError(f'{path}: duration must be positive, got {duration!r}')
    if document['profile'] not in PROFILES:
        raise MotionError(f'{path}: profile must be one of {list(PROFILES)}, got {document["profile"]!r}')
    start, goal = (_positions(path, field, document[field], len(names)) for field in ('start', 'goal'))
    return MotionFile(tuple(names), ProgrammedMotion(start, goal, duration))


def _number(path: Path, field: str, value) -> float:
    # bool is an int to Python, never a number to a motion file
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MotionError(f'{path}: {field} must be a finite number, got {value!r}')
    return float(value)


def _positions(path: Path, field: str, values, joints: int) -> np.ndarray:
    if not isinstance(values, list) or len(values) != joints:
        raise MotionError(f'{path}: {field} must list one position per joint of joint_names ({joints}), '
                          f'got {values!r}')
    return np.array([_number(path, f'{field}[{i}]', value) for i, value in enumerate(values)])
