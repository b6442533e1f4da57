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
import sys
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


class Unusable:
    """A YAML value that no field of a data file takes, kept only to be refused by the field's name: a complex
    key (`? [a, b]`: a key must be a name) or an integer too long for Python to convert from text."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text

    __str__ = __repr__


# YAML 1.2's core schema, in decimal (https://yaml.org/spec/1.2.2/#1032-tag-resolution). What YAML 1.1 (PyYAML's
# default) reads as a number in other ways is text here, and so refused wherever a number is due: a file edited by
# hand must never mean another number than it says (1.1 reads `1:00` as 60, `017` as 15, `0b11` as 3, `1_0` as
# 10). An integer has no leading zero (017 is 17 to YAML 1.2 and 15 to YAML 1.1: refused, not guessed); a float
# has a dot or an exponent (`1e-05`, as repr writes some doubles); `.inf` and `.nan` read as such.
_INT = re.compile(r'[-+]?(0|[1-9][0-9]*)')
_FLOAT = re.compile(r'[-+]?(\.[0-9]+|[0-9]+\.[0-9]*|[0-9]+(?=[eE]))([eE][-+]?[0-9]+)?'
                    r'|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)')
_BOOL = re.compile(r'true|True|TRUE|false|False|FALSE')
_NULL = re.compile(r'~|null|Null|NULL|')


class DataLoader(yaml.SafeLoader):
    """The YAML of ddarm's data files (motions, the paper's settings): safe, and YAML 1.2's core schema.

    Numbers, booleans and null resolve as YAML 1.2's core schema has them (above), explicit `!!int`,
    `!!float` and `!!bool` included; anything else is a string. Two equal keys are refused (PyYAML keeps the
    last: a file with two `goal`s). A key that is not a scalar (a complex key, `? [a, b]`) and an integer of
    more digits than Python converts become an Unusable value, which every field refuses by its name.
    """

    yaml_implicit_resolvers: dict = {}

    def construct_mapping(self, node, deep=False):
        if not isinstance(node, yaml.MappingNode):
            raise yaml.constructor.ConstructorError(None, None, f'expected a mapping, found a {node.id}',
                                                    node.start_mark)
        mapping = {}
        for key_node, value_node in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                key = Unusable(f'? {_shown(key)}')
            if key in mapping:
                raise yaml.constructor.ConstructorError(None, None, f'duplicate key {key!r}', key_node.start_mark)
            mapping[key] = self.construct_object(value_node, deep=deep)
        return mapping

    def construct_core_int(self, node):
        text = self.construct_scalar(node)
        if not _INT.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f'{text!r} is not a YAML 1.2 decimal integer',
                                                    node.start_mark)
        digits = len(text.lstrip('+-'))
        if digits > (sys.get_int_max_str_digits() or digits):
            return Unusable(f'an integer of {digits} digits')
        return int(text)

    def construct_core_float(self, node):
        text = self.construct_scalar(node)
        if not (_FLOAT.fullmatch(text) or _INT.fullmatch(text)):
            raise yaml.constructor.ConstructorError(None, None, f'{text!r} is not a YAML 1.2 float', node.start_mark)
        bare = text.lstrip('+-').lower()
        if bare in ('.inf', '.nan'):
            return (-1.0 if text.startswith('-') else 1.0) * float(bare[1:])
        return float(text)

    def construct_core_bool(self, node):
        text = self.construct_scalar(node)
        if not _BOOL.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f'{text!r} is not a YAML 1.2 boolean',
                                                    node.start_mark)
        return text.lower() == 'true'


for _tag, _pattern, _first in (('bool', _BOOL, 'tTfF'), ('int', _INT, '-+0123456789'),
                               ('float', _FLOAT, '-+.0123456789'), ('null', _NULL, ['~', 'n', 'N', ''])):
    DataLoader.add_implicit_resolver(f'tag:yaml.org,2002:{_tag}', re.compile(f'^(?:{_pattern.pattern})$'),
                                     list(_first))
DataLoader.add_constructor('tag:yaml.org,2002:int', DataLoader.construct_core_int)
DataLoader.add_constructor('tag:yaml.org,2002:float', DataLoader.construct_core_float)
DataLoader.add_constructor('tag:yaml.org,2002:bool', DataLoader.construct_core_bool)


def _shown(value) -> str:
    """`value` for a message: its repr, cut short."""
    text = repr(value)
    return text if len(text) <= 200 else text[:200] + '…'


def load_motion(path: Path | str) -> MotionFile:
    """The motion file at `path`; MotionError names the file and the field of anything it cannot use."""
    path = Path(path)
    try:
        document = yaml.load(path.read_text(), Loader=DataLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError) as error:
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
        raise MotionError(f'{path}: joint_names must be a non-empty list of names, got {_shown(names)}')
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise MotionError(f'{path}: joint_names names {repeated} more than once')
    duration = _number(path, 'duration', document['duration'])
    if not duration > 0:
        raise MotionError(f'{path}: duration must be positive, got {duration!r}')
    if document['profile'] not in PROFILES:
        raise MotionError(f'{path}: profile must be one of {list(PROFILES)}, got {_shown(document["profile"])}')
    start, goal = (_positions(path, field, document[field], len(names)) for field in ('start', 'goal'))
    return MotionFile(tuple(names), ProgrammedMotion(start, goal, duration))


def _number(path: Path, field: str, value) -> float:
    # bool is an int to Python, never a number to a motion file
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            value = float(value)
        except OverflowError:
            raise MotionError(f'{path}: {field} must be a finite number, got an integer beyond the range of a float') \
                from None
    if not isinstance(value, float) or not math.isfinite(value):
        hint = ''
        if isinstance(value, str) and re.match(r'[-+]?\.?[0-9]', value):
            hint = (' (text, not a number: numbers are read as YAML 1.2 writes them, e.g. 10, -0.5, 1e-05; never '
                    "as YAML 1.1's 1:00, 017, 0b11 or 1_0)")
        raise MotionError(f'{path}: {field} must be a finite number, got {_shown(value)}{hint}')
    return value


def _positions(path: Path, field: str, values, joints: int) -> np.ndarray:
    if not isinstance(values, list) or len(values) != joints:
        raise MotionError(f'{path}: {field} must list one position per joint of joint_names ({joints}), '
                          f'got {_shown(values)}')
    return np.array([_number(path, f'{field}[{i}]', value) for i, value in enumerate(values)])
