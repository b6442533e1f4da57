"""Motion files: a programmed motion and the joints it drives, as YAML.

Two forms. The bang-bang motion of spec §4:

```yaml
joint_names: [joint1, joint2, joint3]  # the controlled joints, in the order of start and goal
duration: 1.0                          # T, s
profile: bang_bang                     # s(t/T) of spec §4
start: [0.0, 1.0471975511965976, -2.0943951023931953]  # q(0), rad
goal: [1.5707963267948966, 0.0, 0.0]                    # q(T), rad
```

Or waypoints, in the shape of a trajectory_msgs/JointTrajectory, splined as ros2_controllers' joint trajectory
controller does (ddarm.motion.waypoints):

```yaml
joint_names: [joint1, joint2, joint3]
start: [0.0, 0.0, 0.0]                 # optional: q(0), at rest; required when points[0] is later than t = 0
points:
  - positions: [0.1, 0.2, 0.3]
    velocities: [0.0, 0.5, 0.0]        # optional
    accelerations: [0.0, 0.0, 0.0]     # optional, only with velocities
    time_from_start: 0.5               # s, or {sec: 0, nanosec: 500000000} as the message writes it
  - positions: [0.2, 0.4, 0.6]
    time_from_start: 1.0               # the last point: the goal, held after it (its velocities, if any, zero)
```

Either form may add `locked: {joint4: 0.0}`: positions of the arm's other movable joints, which the motion
does not drive and the arm holds there.

Every refusal is a MotionError naming the file and the field: a motion file is edited by hand, and a
wrong one must never become a different motion silently. A file from someone else is bounded, each bound
refused before the work it bounds: MAX_FILE_BYTES, MAX_NODES YAML values (aliases expanded), MAX_DEPTH levels,
MAX_JOINTS joints, MAX_POINTS points; below them, reading costs time and memory linear in the file.
"""

from __future__ import annotations

import math
import re
import reprlib
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ddarm.datafiles import MAX_DEPTH, MAX_FILE_BYTES, DataFileError, read_data_file
from ddarm.samples import MAX_JOINTS
from ddarm.motion.programmed import MotionError, ProgrammedMotion
from ddarm.motion.waypoints import MAX_POINTS, WaypointMotion

PROFILES = ('bang_bang',)
FIELDS = ('joint_names', 'duration', 'profile', 'start', 'goal')  # the bang-bang form's, each required
WAYPOINT_FIELDS = ('joint_names', 'points')  # the waypoint form's required fields
WAYPOINT_OPTIONAL = ('start',)
OPTIONAL = ('locked',)  # either form's
POINT_FIELDS = ('positions', 'velocities', 'accelerations', 'time_from_start')
# builtin_interfaces/Duration: sec is an int32, nanosec a uint32 below one second.
_SEC_MAX = 2**31 - 1
_NANOSEC_PER_SEC = 1_000_000_000


@dataclass(frozen=True)
class MotionFile:
    """A motion file's content: the joints, by name, their motion, in that order, and the locked joints' positions
    (name, q) in the file's order."""

    joint_names: tuple[str, ...]
    motion: ProgrammedMotion | WaypointMotion
    locked: tuple[tuple[str, float], ...] = ()


class Unusable:
    """A YAML value that no field of a data file takes, kept only to be refused by the field's name: a complex
    key (`? [a, b]`: a key must be a name) or an integer too long for Python to convert from text."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text

    __str__ = __repr__


# YAML values, an alias counted as every value it repeats: a few hundred bytes of nested aliases repeat a list
# 10^9 times, which no field could take in and no message could show.
MAX_NODES = 4_000_000

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
_TAG = 'tag:yaml.org,2002:'


def _error(problem: str, mark) -> yaml.constructor.ConstructorError:
    return yaml.constructor.ConstructorError(None, None, problem, mark)


def _core_int(text: str, mark):
    if not _INT.fullmatch(text):
        raise _error(f'{text!r} is not a YAML 1.2 decimal integer', mark)
    digits = len(text.lstrip('+-'))
    if digits > (sys.get_int_max_str_digits() or digits):
        return Unusable(f'an integer of {digits} digits')
    return int(text)


def _core_float(text: str, mark) -> float:
    if not (_FLOAT.fullmatch(text) or _INT.fullmatch(text)):
        raise _error(f'{text!r} is not a YAML 1.2 float', mark)
    bare = text.lstrip('+-').lower()
    if bare in ('.inf', '.nan'):
        return (-1.0 if text.startswith('-') else 1.0) * float(bare[1:])
    return float(text)


def _core_bool(text: str, mark) -> bool:
    if not _BOOL.fullmatch(text):
        raise _error(f'{text!r} is not a YAML 1.2 boolean', mark)
    return text.lower() == 'true'


# A plain scalar's tag: the first of these it matches, else a string (one match per scalar: a motion has millions).
_IMPLICIT = re.compile('|'.join(f'(?P<{name}>{pattern.pattern})' for name, pattern in (
    ('bool', _BOOL), ('int', _INT), ('float', _FLOAT), ('null', _NULL))))
_IMPLICIT_VALUE = {'bool': _core_bool, 'int': _core_int, 'float': _core_float, 'null': lambda text, mark: None}
_EXPLICIT = {f'{_TAG}str': lambda text, mark: text, f'{_TAG}null': lambda text, mark: None,
             f'{_TAG}bool': _core_bool, f'{_TAG}int': _core_int, f'{_TAG}float': _core_float}
_UNSET = object()

try:  # libyaml's parser, where PyYAML was built with it: its events come ten times faster than PyYAML's own
    from yaml.cyaml import CParser as _Parser
except ImportError:
    _Parser = yaml.SafeLoader


class DataLoader(_Parser):
    """The YAML of ddarm's data files (motions, campaigns, the paper's settings): plain data, YAML 1.2's core
    schema, bounded; for yaml.load(text, Loader=DataLoader).

    Built from the parser's events straight into dicts, lists and scalars, in one pass: the cost is linear in the
    file, and each bound (MAX_NODES values, aliases counted as what they repeat; MAX_DEPTH levels) is refused
    at the event that passes it, before anything is expanded. Numbers, booleans and null resolve as YAML 1.2's
    core schema has them (above), explicit `!!int`, `!!float`, `!!bool`, `!!str`, `!!null` included; any other
    tag is refused; anything else is a string. Two equal keys are refused (PyYAML keeps the last: a file with two
    `goal`s), and so is an alias inside the value it names (a value that contains itself). A key that is not a
    scalar (a complex key, `? [a, b]`) and an integer of more digits than Python converts become an Unusable
    value, which every field refuses by its name. An alias is the value it names, not a copy.
    """

    def get_single_data(self):
        self.get_event()  # the stream's start
        if self.check_event(yaml.StreamEndEvent):
            return None
        document = self.get_event()
        value = _Document().read(self)
        if not self.check_event(yaml.StreamEndEvent):
            raise yaml.composer.ComposerError('expected a single document in the stream', document.start_mark,
                                              'but found another document', self.get_event().start_mark)
        return value


class _Collection:
    __slots__ = ('value', 'key', 'anchor', 'first', 'mark')

    def __init__(self, value, anchor, first: int, mark) -> None:
        self.value, self.key, self.anchor, self.first, self.mark = value, _UNSET, anchor, first, mark


class _Document:
    """One document's value, from its events (after DocumentStartEvent, up to and with DocumentEndEvent)."""

    def __init__(self) -> None:
        self.nodes = 0  # the values so far, each alias counted as every value it repeats
        self.anchors: dict = {}  # anchor -> (value, its count of values)
        self.open: list[_Collection] = []
        self.root = _UNSET

    def read(self, parser):
        scalar, start, end, alias = yaml.ScalarEvent, (yaml.SequenceStartEvent, yaml.MappingStartEvent), \
            (yaml.SequenceEndEvent, yaml.MappingEndEvent), yaml.AliasEvent
        while True:
            event = parser.get_event()
            kind = type(event)
            if kind is scalar:
                self.count(1, event.start_mark)
                value = self.scalar(event)
                if event.anchor is not None:
                    self.anchors[event.anchor] = (value, 1)
                self.add(value, event.start_mark)
            elif kind in start:
                self.count(1, event.start_mark)
                self.begin(event, kind is yaml.SequenceStartEvent)
            elif kind in end:
                collection = self.open.pop()
                if collection.anchor is not None:
                    self.anchors[collection.anchor] = (collection.value, self.nodes - collection.first)
                self.add(collection.value, collection.mark)
            elif kind is alias:
                self.add(self.aliased(event), event.start_mark)
            else:  # DocumentEndEvent: a document is one value
                return self.root

    def count(self, nodes: int, mark) -> None:
        self.nodes += nodes
        if self.nodes > MAX_NODES:
            raise _error(f'more than {MAX_NODES} values (an alias counted as every value it repeats), the most a '
                         'data file may hold', mark)

    def scalar(self, event):
        tag, text = event.tag, event.value
        if tag is None or tag == '!':
            if event.implicit[0] and (match := _IMPLICIT.fullmatch(text)):
                return _IMPLICIT_VALUE[match.lastgroup](text, event.start_mark)
            return text
        if tag not in _EXPLICIT:
            raise _error(f'the tag {shown(tag)} is not one of plain data (str, int, float, bool, null)',
                         event.start_mark)
        return _EXPLICIT[tag](text, event.start_mark)

    def begin(self, event, sequence: bool) -> None:
        if len(self.open) >= MAX_DEPTH:
            raise _error(f'nested more than {MAX_DEPTH} levels deep', event.start_mark)
        if event.tag not in (None, '!', f'{_TAG}seq' if sequence else f'{_TAG}map'):
            raise _error(f'the tag {shown(event.tag)} is not one of plain data (a list or a mapping)',
                         event.start_mark)
        # The collection counted itself already.
        self.open.append(_Collection([] if sequence else {}, event.anchor, self.nodes - 1, event.start_mark))

    def aliased(self, event):
        if any(collection.anchor == event.anchor for collection in self.open):
            raise _error(f'the alias {shown(event.anchor)} is inside the value it names', event.start_mark)
        if event.anchor not in self.anchors:
            raise _error(f'found undefined alias {shown(event.anchor)}', event.start_mark)
        value, nodes = self.anchors[event.anchor]
        self.count(nodes, event.start_mark)
        return value

    def add(self, value, mark) -> None:
        if not self.open:
            self.root = value
            return
        parent = self.open[-1]
        if type(parent.value) is list:
            parent.value.append(value)
        elif parent.key is _UNSET:
            key = Unusable(f'? {shown(value)}') if isinstance(value, (list, dict)) else value
            if key in parent.value:
                raise _error(f'duplicate key {shown(key)}', mark)
            parent.key = key
        else:
            parent.value[parent.key] = value
            parent.key = _UNSET


_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxstring, _SHORT.maxlong, _SHORT.maxother = 3, 80, 40, 80
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = _SHORT.maxset = 8


def shown(value) -> str:
    """`value` for a message: its repr, cut short, in time and memory bounded whatever its size (a value repeated
    by aliases is never written out whole)."""
    text = _SHORT.repr(value)
    return text if len(text) <= 200 else text[:200] + '…'


def load_motion(path: Path | str) -> MotionFile:
    """The motion file at `path`; MotionError names the file and the field of anything it cannot use."""
    path = Path(path)
    try:
        text = read_data_file(path)
    except DataFileError as error:
        raise MotionError(f'{path}: cannot read the motion file: {error}') from None
    except OSError as error:
        raise MotionError(f'{path}: cannot read the motion file: {error}') from error
    return parse_motion(text, str(path))


def parse_motion(text: str, source: str) -> MotionFile:
    """The motion file whose text is `text`; `source` names it (its path) first in every MotionError."""
    if (size := len(text.encode('utf-8'))) > MAX_FILE_BYTES:
        raise MotionError(f'{source}: {size} bytes, more than the {MAX_FILE_BYTES} a motion file may hold')
    try:
        document = yaml.load(text, Loader=DataLoader)
    except yaml.YAMLError as error:
        raise MotionError(f'{source}: cannot read the motion file: {error}') from error
    if not isinstance(document, dict):
        raise MotionError(f'{source}: a motion file is a mapping of {", ".join(FIELDS)} (or of '
                          f'{", ".join(WAYPOINT_FIELDS)}), got {type(document).__name__}')
    if 'profile' in document and 'points' in document:
        raise MotionError(f'{source}: both profile (a bang-bang motion: duration, start, goal) and points (a '
                          'waypoint motion): a motion file is one or the other')
    waypoints = 'points' in document
    required, optional = (WAYPOINT_FIELDS, WAYPOINT_OPTIONAL + OPTIONAL) if waypoints else (FIELDS, OPTIONAL)
    unknown = [key for key in document if key not in required + optional]
    if unknown:
        form = 'a waypoint motion file (points)' if waypoints else 'a bang-bang motion file (profile)'
        raise MotionError(f'{source}: unknown key {unknown[0]!r} ({form} has {", ".join(required)}, and optionally '
                          f'{", ".join(optional)})')
    missing = [key for key in required if key not in document]
    if missing:
        hint = ' (or points, for a waypoint motion)' if missing[0] == 'profile' else ''
        raise MotionError(f'{source}: missing key {missing[0]!r}{hint}')
    names = document['joint_names']
    if (not isinstance(names, list) or not names
            or not all(isinstance(name, str) and name for name in names)):
        raise MotionError(f'{source}: joint_names must be a non-empty list of names, got {shown(names)}')
    if len(names) > MAX_JOINTS:
        raise MotionError(f'{source}: joint_names names {len(names)} joints, more than the {MAX_JOINTS} a motion may '
                          'drive')
    repeated = sorted(name for name, count in Counter(names).items() if count > 1)
    if repeated:
        raise MotionError(f'{source}: joint_names names {repeated} more than once')
    motion = _waypoint_motion(source, document, len(names)) if waypoints else _bang_bang(source, document, len(names))
    return MotionFile(tuple(names), motion, _locked(source, document.get('locked', {}), names))


def _bang_bang(source: str, document: dict, joints: int) -> ProgrammedMotion:
    duration = _number(source, 'duration', document['duration'])
    if not duration > 0:
        raise MotionError(f'{source}: duration must be positive, got {duration!r}')
    if document['profile'] not in PROFILES:
        raise MotionError(f'{source}: profile must be one of {list(PROFILES)}, got {shown(document["profile"])}')
    start, goal = (_positions(source, field, document[field], joints) for field in ('start', 'goal'))
    return ProgrammedMotion(start, goal, duration)


def _waypoint_motion(source: str, document: dict, joints: int) -> WaypointMotion:
    points = document['points']
    if not isinstance(points, list) or not points:
        raise MotionError(f'{source}: points must be a non-empty list of points (mappings of '
                          f'{", ".join(POINT_FIELDS)}), got {shown(points)}')
    if len(points) > MAX_POINTS:
        raise MotionError(f'{source}: points holds {len(points)} points, more than the {MAX_POINTS} a motion may have')
    times, positions, velocities, accelerations = [], [], [], []
    for i, point in enumerate(points):
        where = f'points[{i}]'
        if not isinstance(point, dict):
            raise MotionError(f'{source}: {where} must be a mapping of {", ".join(POINT_FIELDS)}, got {shown(point)}')
        unknown = [key for key in point if key not in POINT_FIELDS]
        if unknown:
            raise MotionError(f'{source}: {where}: unknown key {unknown[0]!r} (a point has positions, '
                              'time_from_start, and optionally velocities, accelerations)')
        for key in ('positions', 'time_from_start'):
            if key not in point:
                raise MotionError(f'{source}: {where}: missing key {key!r}')
        times.append(_time_from_start(source, f'{where}.time_from_start', point['time_from_start']))
        positions.append(_positions(source, f'{where}.positions', point['positions'], joints))
        for key, given in (('velocities', velocities), ('accelerations', accelerations)):
            given.append(_positions(source, f'{where}.{key}', point[key], joints, 'number') if key in point else None)
    start = _positions(source, 'start', document['start'], joints) if 'start' in document else None
    try:
        return WaypointMotion(np.array(times), np.array(positions), tuple(velocities), tuple(accelerations), start)
    except MotionError as error:  # the points' order and ends: the message names the point and the field
        raise MotionError(f'{source}: {error}') from None


def _time_from_start(source: str, field: str, value) -> float:
    """A point's time in s: a number, or builtin_interfaces/Duration's {sec, nanosec} as the message has it."""
    if isinstance(value, dict):
        if set(value) != {'sec', 'nanosec'}:
            raise MotionError(f'{source}: {field} must be a number of seconds or a mapping of exactly sec and '
                              f'nanosec, got {shown(value)}')
        sec, nanosec = value['sec'], value['nanosec']
        for key, number, largest in (('sec', sec, _SEC_MAX), ('nanosec', nanosec, _NANOSEC_PER_SEC - 1)):
            if not (isinstance(number, int) and not isinstance(number, bool) and 0 <= number <= largest):
                raise MotionError(f'{source}: {field}.{key} must be an integer in [0, {largest}], got {shown(number)}')
        # The nanoseconds counted exactly, rounded once.
        return (sec * _NANOSEC_PER_SEC + nanosec) / _NANOSEC_PER_SEC
    seconds = _number(source, field, value)
    if seconds < 0:
        raise MotionError(f'{source}: {field} must not be negative, got {seconds!r}')
    return seconds


def _locked(source: str, locked, names: list) -> tuple[tuple[str, float], ...]:
    if not isinstance(locked, dict):
        raise MotionError(f'{source}: locked must be a mapping of joint name to position, got {shown(locked)}')
    if len(locked) > MAX_JOINTS:
        raise MotionError(f'{source}: locked names {len(locked)} joints, more than the {MAX_JOINTS} an arm may have')
    driven = set(names)
    for name in locked:
        if not (isinstance(name, str) and name):
            raise MotionError(f'{source}: locked: {shown(name)} is not a joint name')
        if name in driven:
            raise MotionError(f'{source}: locked[{name!r}]: the motion drives {name!r} (it is in joint_names); '
                              'a joint is either driven or locked')
    return tuple((name, _number(source, f'locked[{name!r}]', value)) for name, value in locked.items())


def _number(source: str, field: str, value) -> float:
    # bool is an int to Python, never a number to a motion file
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            value = float(value)
        except OverflowError:
            raise MotionError(f'{source}: {field} must be a finite number, got an integer beyond the range of a '
                              'float') from None
    if not isinstance(value, float) or not math.isfinite(value):
        hint = ''
        if isinstance(value, str) and re.match(r'[-+]?\.?[0-9]', value):
            hint = (' (text, not a number: numbers are read as YAML 1.2 writes them, e.g. 10, -0.5, 1e-05; never '
                    "as YAML 1.1's 1:00, 017, 0b11 or 1_0)")
        raise MotionError(f'{source}: {field} must be a finite number, got {shown(value)}{hint}')
    return value


def _positions(source: str, field: str, values, joints: int, what: str = 'position') -> np.ndarray:
    if not isinstance(values, list) or len(values) != joints:
        raise MotionError(f'{source}: {field} must list one {what} per joint of joint_names ({joints}), '
                          f'got {shown(values)}')
    return np.array([_number(source, f'{field}[{i}]', value) for i, value in enumerate(values)])


def motion_of_duration(file: MotionFile, duration: float):
    """q^d over an episode of T = `duration`: a bang-bang motion stretched to T, waypoints as they are (held after
    their last point)."""
    motion = file.motion
    if isinstance(motion, ProgrammedMotion):
        # Fresh arrays: a caller may change its copy.
        return ProgrammedMotion(motion.q0.copy(), motion.qf.copy(), float(duration))
    return motion


# Written by ddarm (a motion from a bag, an excitation): text that reads back exactly.
_WORD = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')


def flow_numbers(values) -> str:
    """Numbers as a YAML flow sequence that reads back as the same doubles."""
    # repr: the shortest text that reads back as the same double (YAML 1.2 reads 1e-05 and -0.0 as floats)
    return '[' + ', '.join(repr(float(value)) for value in values) + ']'


def flow_names(names) -> str:
    """Names as a YAML flow sequence that reads back as the same texts."""
    return '[' + ', '.join(_flow_name(name) for name in names) + ']'


def _flow_name(name: str) -> str:
    """`name` as YAML that reads back as it: plain when it is a word the loader reads as that text (joint1, not
    true or 1e5), else double-quoted, with what YAML would not read as it stands (a quote, a backslash, a control
    character) escaped."""
    if _WORD.fullmatch(name) and yaml.load(name, Loader=DataLoader) == name:
        return name
    return '"' + ''.join(c if (' ' <= c <= '~' or (c >= '\xa0' and c.isprintable())) and c not in '"\\'
                         else f'\\U{ord(c):08x}' for c in name) + '"'
