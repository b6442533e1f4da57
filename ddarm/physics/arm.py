"""The arm's rigid-body model: a Pinocchio model built from the URDF, reduced to the controlled joints.

A URDF's movable joints are revolute, continuous or prismatic; its fixed joints are folded into
their parent link (Pinocchio's URDF parser makes them frames). The joints an episode controls
are named by its motion; every other movable joint is locked at a given position, which makes a
reduced model (pin.buildReducedModel) used alike by the plant and the controller. Joint
positions are angles (rad) or lengths (m) everywhere in ddarm: a continuous joint, which
Pinocchio represents by (cos θ, sin θ), is given to Pinocchio through `configuration`.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import sys
import xml.etree.ElementTree as ElementTree
import xml.parsers.expat as expat
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache, partial
from pathlib import Path

import numpy as np
import pinocchio as pin

from ddarm.datafiles import MAX_FILE_BYTES, DataFileError, is_missing, read_data_bytes, unreachable
from ddarm.errors import DdarmError

URDF_NAME = 'ddarm.urdf'
MOVABLE = ('revolute', 'continuous', 'prismatic')
# Pinocchio's joint models of URDF's movable joints: 1-DOF revolute (bounded or not) and prismatic.
PINOCCHIO_JOINTS = ('JointModelRX', 'JointModelRY', 'JointModelRZ', 'JointModelRevoluteUnaligned',
                    'JointModelRUBX', 'JointModelRUBY', 'JointModelRUBZ', 'JointModelRevoluteUnboundedUnaligned',
                    'JointModelPX', 'JointModelPY', 'JointModelPZ', 'JointModelPrismaticUnaligned')


def is_prismatic(joint_model: str) -> bool:
    """Whether a Pinocchio joint model (its shortname) is prismatic: its position a length, its effort a force."""
    return joint_model.startswith('JointModelP')


class ModelError(DdarmError, ValueError):
    """A URDF or model option that cannot describe the arm."""


def config_file(*parts: str) -> Path:
    """A file of ddarm's config/ folder (e.g. 'arms', 'panda', 'panda.urdf'): from the source tree, else from the
    share folder of the prefix this module is installed in."""
    package = Path(__file__).resolve().parents[1]
    candidates = [package.parent / 'config']
    if len(package.parents) > 3:  # <prefix>/lib/pythonX.Y/site-packages/ddarm (colcon or pip)
        candidates.append(package.parents[3] / 'share' / 'ddarm' / 'config')
    candidates.append(Path(sys.prefix) / 'share' / 'ddarm' / 'config')
    for candidate in candidates:
        if candidate.joinpath(*parts).is_file():
            return candidate.joinpath(*parts)
    raise ModelError(f'{"/".join(parts)} not found in {[str(c) for c in candidates]}')


def default_urdf_path() -> Path:
    """The arm's URDF (config/ddarm.urdf)."""
    return config_file(URDF_NAME)


def same_urdf(first: str | Path | None, second: str | Path | None) -> bool:
    """Whether two URDF arguments (None: the ddarm arm) name the same file."""
    def resolved(urdf):
        return (Path(urdf) if urdf else default_urdf_path()).resolve()
    return resolved(first) == resolved(second)


@dataclass(frozen=True)
class UrdfJoint:
    """A URDF joint as its <joint> element says, as urdfdom reads it: type, links, <origin>, unit <axis> (None for a
    fixed joint), <limit> (lower and upper 0 where absent, ±inf for a continuous joint; effort and velocity inf
    without a <limit>) and <mimic>."""

    name: str
    kind: str
    parent: str
    child: str
    origin: pin.SE3  # the child link's frame in the parent link's
    axis: np.ndarray | None
    lower: float
    upper: float
    velocity: float
    effort: float
    mimic: tuple[str, float, float] | None  # (mimicked joint, multiplier, offset)
    damping: float = 0.0  # <dynamics damping>: viscous friction, N m s/rad (N s/m)
    friction: float = 0.0  # <dynamics friction>: Coulomb friction, N m (N)
    armature: float = 0.0  # <ddarm:armature value>: reflected rotor inertia, kg m² (kg)


@dataclass(frozen=True)
class UrdfDescription:
    """A URDF as ddarm reads it: its text (which Pinocchio is given, so that both read the same characters), the
    links' <inertial> (in the link's frame; None without one) and the joints, by name in file order."""

    text: str
    inertias: dict[str, pin.Inertia | None]
    joints: dict[str, UrdfJoint]


# A number as urdfdom reads one (std::istringstream in the classic locale, the whole text consumed): decimal, leading
# blanks allowed; not nan, inf, hexadecimal, digit separators, other digits than 0-9, a decimal comma, a trailing blank.
_NUMBER = re.compile(r'[ \t\n\r\f\v]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?')
# Principal moments may miss positive semi-definiteness and the triangle inequality by this fraction of their sum:
# URDF files give inertias to a few significant digits.
_MOMENT_TOLERANCE = 1e-5
# Numbers of a joint urdfdom reads, refusing the whole file over one it cannot (with lines of its own on stderr),
# that ddarm does not use: (element, attributes, the ones urdfdom requires).
_UNUSED_JOINT_NUMBERS = (('safety_controller', ('soft_lower_limit', 'soft_upper_limit', 'k_position', 'k_velocity'),
                          ('k_velocity',)),
                         ('calibration', ('rising', 'falling'), ()))
# A joint's armature (the rotor's inertia reflected through its gear, added to M(q)'s diagonal), which URDF has no
# element for: <ddarm:armature value="0.1"/> inside the <joint>, in kg m² (kg for a prismatic joint), with
# xmlns:ddarm="https://github.com/ddarm/ddarm" on <robot>. urdfdom, MuJoCo's URDF compiler and other readers ignore it.
ARMATURE_ELEMENT = 'ddarm:armature'
ARMATURE_NAMESPACE = 'https://github.com/ddarm/ddarm'


# A start tag as well-formed XML writes it, and one of its attributes (name, value in double or in single quotes).
_START_TAG = re.compile(rb'<[^\s/>]+(?:\s+[^\s="\'>]+\s*=\s*(?:"[^"]*"|\'[^\']*\'))*\s*/?>')
_ATTRIBUTE = re.compile(rb'\s([^\s="\'>]+)\s*=\s*(?:"([^"]*)"|\'([^\']*)\')')
_REFERENCE = re.compile(r'&(?:#x([0-9a-fA-F]+)|#([0-9]+)|(lt|gt|amp|quot|apos));')
_PREDEFINED = {'lt': '<', 'gt': '>', 'amp': '&', 'quot': '"', 'apos': "'"}


def _expanded(match: re.Match) -> str:
    hexadecimal, decimal, name = match.groups()
    return chr(int(hexadecimal, 16)) if hexadecimal else chr(int(decimal)) if decimal else _PREDEFINED[name]


def _attributes_as_tinyxml2_reads_them(data: bytes, start: int, attributes: dict[str, str]) -> dict[str, str]:
    """The attributes of the start tag at byte `start`, as TinyXML2 (urdfdom's XML reader) reads them.

    XML makes each tab and line break written in an attribute value a blank, and expat does; TinyXML2 keeps them
    (a line break as LF), so that urdfdom reads "0.2<tab>0 0" as two numbers, not three, and "j<tab>2" as its name.
    """
    tag = _START_TAG.match(data, start)
    if tag is None or not any(blank in tag.group() for blank in (b'\t', b'\n', b'\r')):
        return attributes
    kept = dict(attributes)
    for attribute in _ATTRIBUTE.finditer(tag.group()):
        raw = (attribute.group(2) if attribute.group(2) is not None else attribute.group(3)).decode('utf-8')
        if any(blank in raw for blank in '\t\n\r'):
            kept[attribute.group(1).decode('utf-8')] = _REFERENCE.sub(
                _expanded, raw.replace('\r\n', '\n').replace('\r', '\n'))
    return kept


def _refuse_doctype(path: Path, name, *_) -> None:
    raise ModelError(f'URDF {path} has a document type declaration (<!DOCTYPE {name}>), which a URDF has no use '
                     f'for: its entities would be expanded by ddarm\'s XML reader and not by urdfdom\'s, which '
                     f'Pinocchio reads the file with')


# A URDF's bounds. Arms have tens of links, a humanoid with hands a few hundred; urdfdom and Pinocchio walk the
# kinematic tree recursively, and a chain of 5,000 links overflowed their stack (a segfault, not an error).
MAX_URDF_BYTES = MAX_FILE_BYTES
MAX_URDF_LINKS = 1000
# XML nesting: a URDF nests about 5 levels (robot, link, inertial, origin); each level is a frame of TinyXML2's.
MAX_URDF_LEVELS = 100
# The largest mass (kg) and moment or product of inertia (kg m²) read: Pinocchio's M(q) of an arm whose links weigh
# 1e160 kg is NaN (it multiplies two of them somewhere, which overflows past the square root of the largest double,
# 1.3e154); a single link of 1e300 kg was refused as "two coaxial joints".
MAX_URDF_INERTIA = 1e150


def _start_element(path: Path, data: bytes, parser, builder, levels: list[int], tag: str, attributes) -> None:
    levels[0] += 1
    if levels[0] > MAX_URDF_LEVELS:
        raise ModelError(f'URDF {path} nests elements deeper than {MAX_URDF_LEVELS} levels (line '
                         f'{parser.CurrentLineNumber}): a URDF nests about 5')
    builder.start(tag, _attributes_as_tinyxml2_reads_them(data, parser.CurrentByteIndex, attributes))


def _end_element(builder, levels: list[int], tag: str) -> None:
    levels[0] -= 1
    builder.end(tag)


def _read_xml(path: Path) -> tuple[str, ElementTree.Element]:
    """The file's text and its root element, read as urdfdom's TinyXML2 reads them: UTF-8, no DTD; at most
    MAX_URDF_BYTES and MAX_URDF_LEVELS deep."""
    try:
        data = read_data_bytes(path, MAX_URDF_BYTES)
    except OSError as error:
        raise ModelError(f'URDF {path} cannot be read: {error.strerror}') from error
    except DataFileError as error:
        raise ModelError(f'URDF {error}') from None
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise ModelError(f'URDF {path} is not UTF-8 text (byte {error.start}), the only encoding urdfdom reads') \
            from None
    builder = ElementTree.TreeBuilder()
    parser = expat.ParserCreate()  # no namespace processing: element names as TinyXML2 sees them, prefix and all
    parser.StartDoctypeDeclHandler = partial(_refuse_doctype, path)  # before any entity is declared
    levels = [0]
    parser.StartElementHandler = partial(_start_element, path, data, parser, builder, levels)
    parser.EndElementHandler = partial(_end_element, builder, levels)
    try:
        parser.Parse(text, True)  # text, not bytes: UTF-8 whatever the XML declaration says, as TinyXML2 reads it
    except expat.ExpatError as error:
        raise ModelError(f'URDF {path} is not readable XML: {error}') from None
    return text, builder.close()


def _child(path: Path, where: str, element, tag: str, required: bool = False):
    """The one <tag> child of `element` (None if there is none and none is required)."""
    found = element.findall(tag)
    if len(found) > 1:
        raise ModelError(f'URDF {path}: {where} has {len(found)} <{tag}> elements: URDF gives one (urdfdom reads '
                         f'the first, silently)')
    if not found and required:
        raise ModelError(f'URDF {path}: {where} has no <{tag}>, which urdfdom requires')
    return found[0] if found else None


def _number(path: Path, where: str, element, name: str, default: float | None = None,
            largest: float = math.inf) -> float:
    """Attribute `name` of `element` as a finite number urdfdom reads alike (`default` if absent; None: required),
    of magnitude at most `largest`."""
    text = element.get(name) if element is not None else None
    if text is None:
        if default is None:
            raise ModelError(f'URDF {path}: {where} has no {name}="…", which urdfdom requires')
        return default
    value = float(text) if _NUMBER.fullmatch(text) else math.nan
    if not math.isfinite(value):
        raise ModelError(f'URDF {path}: {where}: {name}={text!r} is not a finite decimal number (urdfdom, which '
                         f'Pinocchio reads the URDF with, reads no other)')
    if abs(value) > largest:
        raise ModelError(f'URDF {path}: {where}: {name}={text!r} is too large for floating point (ddarm reads up to '
                         f'{largest:g})')
    return value


def _vector(path: Path, where: str, element, name: str, default: tuple[float, float, float]) -> np.ndarray:
    """Attribute `name` of `element` as three numbers separated by blanks, as urdfdom splits and reads them."""
    text = element.get(name) if element is not None else None
    if text is None:
        return np.array(default, dtype=float)
    pieces = [piece for piece in text.split(' ') if piece]
    values = [float(piece) if _NUMBER.fullmatch(piece) else math.nan for piece in pieces]
    if len(values) != 3 or not all(math.isfinite(value) for value in values):
        raise ModelError(f'URDF {path}: {where}: {name}={text!r} is not three finite decimal numbers separated by '
                         f'blanks (urdfdom, which Pinocchio reads the URDF with, reads no other)')
    return np.array(values)


def _origin(path: Path, where: str, element) -> pin.SE3:
    origin = _child(path, where, element, 'origin')
    xyz = _vector(path, f'{where} <origin>', origin, 'xyz', (0.0, 0.0, 0.0))
    rpy = _vector(path, f'{where} <origin>', origin, 'rpy', (0.0, 0.0, 0.0))
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _moments_problem(mass: float, moments: np.ndarray) -> str | None:
    """Why no body has this mass and inertia tensor (about its centre of mass), or None if one can."""
    if mass < 0:
        return f'mass {mass!r} is negative: no body\'s is'
    largest = np.max(np.abs(moments))
    if largest == 0:
        return None  # a point mass, or no body at all (mass 0, as urdfdom reads a link without <inertial>)
    if mass == 0:
        return 'mass 0 with nonzero moments of inertia: a body without mass has none'
    smallest, middle, greatest = relative = np.linalg.eigvalsh(moments / largest)  # normalised: sums must not overflow
    tolerance = _MOMENT_TOLERANCE * np.sum(np.abs(relative))
    principal = [float(f'{value * largest:.6g}') for value in relative]
    if smallest < -tolerance:
        return (f'the inertia tensor has a negative principal moment ({principal}): it is not positive '
                f'semi-definite, as every body\'s is')
    if greatest > smallest + middle + tolerance:
        return (f'principal moments {principal} break the triangle inequality (the largest exceeds the sum of the '
                f'other two), which every body\'s meet')
    return None


def _inertia(path: Path, link: str, element) -> pin.Inertia | None:
    """The link's <inertial> in the link's frame; refused unless urdfdom reads it alike and a body can have it."""
    inertial = _child(path, f'link {link!r}', element, 'inertial')
    if inertial is None:
        return None
    where = f'link {link!r} <inertial>'
    origin = _origin(path, where, inertial)
    mass = _number(path, f'{where} <mass>', _child(path, where, inertial, 'mass', required=True), 'value',
                   largest=MAX_URDF_INERTIA)
    tensor = _child(path, where, inertial, 'inertia', required=True)
    i = {name: _number(path, f'{where} <inertia>', tensor, name, largest=MAX_URDF_INERTIA)
         for name in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')}
    moments = np.array([[i['ixx'], i['ixy'], i['ixz']], [i['ixy'], i['iyy'], i['iyz']], [i['ixz'], i['iyz'], i['izz']]])
    problem = _moments_problem(mass, moments)
    if problem is not None:
        raise ModelError(f'URDF {path}: {where}: {problem}')
    return pin.Inertia(mass, origin.translation, origin.rotation @ moments @ origin.rotation.T)


def _link_name(path: Path, where: str, element, tag: str, links) -> str:
    name = _child(path, where, element, tag, required=True).get('link')
    if name is None:
        raise ModelError(f'URDF {path}: {where} <{tag}> has no link="…"')
    if name not in links:
        raise ModelError(f'URDF {path}: {where}: {tag} link {name!r} is not a link of the URDF')
    return name


def _joint(path: Path, element, links) -> UrdfJoint:
    name, kind = element.get('name'), element.get('type')
    if not name:
        raise ModelError(f'URDF {path}: a <joint> has no name')
    where = f'joint {name!r}'
    if kind is None:
        raise ModelError(f'URDF {path}: {where} has no type')
    if kind in ('floating', 'planar'):
        raise ModelError(f'URDF {path}: {where} is {kind}: ddarm models fixed-base arms '
                         f'(revolute, continuous, prismatic and fixed joints)')
    if kind not in (*MOVABLE, 'fixed'):
        raise ModelError(f'URDF {path}: {where} has type {kind!r}, which URDF does not define')
    parent, child = (_link_name(path, where, element, tag, links) for tag in ('parent', 'child'))
    if parent == child:
        raise ModelError(f'URDF {path}: {where} has link {parent!r} as both its parent and its child: a joint '
                         f'joins two links')
    origin = _origin(path, where, element)
    axis = None
    if kind != 'fixed':  # urdfdom reads no <axis> of a fixed joint
        axis_element = _child(path, where, element, 'axis')
        axis = _vector(path, f'{where} <axis>', axis_element, 'xyz', (1.0, 0.0, 0.0))
        if not np.any(axis):
            raise ModelError(f'URDF {path}: {where} <axis> xyz={axis_element.get("xyz")!r} has no direction')
        axis = axis / np.max(np.abs(axis))  # first: the norm of a long axis must not overflow
        axis = axis / np.linalg.norm(axis)
    limit = _child(path, where, element, 'limit', required=kind in ('revolute', 'prismatic'))
    lower, upper, velocity, effort = -math.inf, math.inf, math.inf, math.inf
    if limit is not None:  # read for every type, as urdfdom does
        at = f'{where} <limit>'
        lower, upper = _number(path, at, limit, 'lower', 0.0), _number(path, at, limit, 'upper', 0.0)
        effort, velocity = _number(path, at, limit, 'effort'), _number(path, at, limit, 'velocity')
        for attribute, value in (('effort', effort), ('velocity', velocity)):
            if value < 0:
                raise ModelError(f'URDF {path}: {at}: {attribute}={limit.get(attribute)!r} is negative')
        if kind in ('revolute', 'prismatic') and lower > upper:
            raise ModelError(f'URDF {path}: {at}: lower={limit.get("lower", "0")!r} is above '
                             f'upper={limit.get("upper", "0")!r}')
    if kind == 'continuous':
        lower, upper = -math.inf, math.inf
    mimic = _child(path, where, element, 'mimic')
    if mimic is not None:
        if not mimic.get('joint'):
            raise ModelError(f'URDF {path}: {where} <mimic> names no joint')
        mimic = (mimic.get('joint'), _number(path, f'{where} <mimic>', mimic, 'multiplier', 1.0),
                 _number(path, f'{where} <mimic>', mimic, 'offset', 0.0))
    for tag, attributes, required in _UNUSED_JOINT_NUMBERS:
        unused = _child(path, where, element, tag)
        if unused is not None:
            for attribute in attributes:
                _number(path, f'{where} <{tag}>', unused, attribute, None if attribute in required else 0.0)
    dynamics, armature = _child(path, where, element, 'dynamics'), _child(path, where, element, ARMATURE_ELEMENT)
    # Negative friction or inertia would feed the arm energy: no joint has it.
    damping, friction = (_non_negative(path, f'{where} <dynamics>', dynamics, attribute, MAX_URDF_INERTIA)
                         for attribute in ('damping', 'friction'))
    if armature is not None:
        armature = _non_negative(path, f'{where} <{ARMATURE_ELEMENT}>', armature, 'value', MAX_URDF_INERTIA,
                                 required=True)
    return UrdfJoint(name, kind, parent, child, origin, axis, lower, upper, velocity, effort, mimic, damping,
                     friction, armature or 0.0)


def _non_negative(path: Path, where: str, element, name: str, largest: float, required: bool = False) -> float:
    value = _number(path, where, element, name, None if required else 0.0, largest)
    if value < 0:
        raise ModelError(f'URDF {path}: {where}: {name}={element.get(name)!r} is negative: a joint\'s friction and '
                         f'inertia are not')
    return value


def _check_tree(path: Path, links: list[str], joints: dict[str, UrdfJoint]) -> None:
    """Refuse joints that do not join the links into one tree: a cycle, a link with two parent joints, two root
    links. urdfdom and Pinocchio's builder walk the tree from its root: a cycle crashed Pinocchio (a segfault, not an
    error) and a second parent gave a model of other joints than the file's. Iterative: up to MAX_URDF_LINKS deep."""
    children = {}
    for joint in joints.values():
        children.setdefault(joint.parent, []).append(joint)
    # Depth first from each link not reached yet, parent to child: a joint to a link of the current descent closes a
    # cycle. A link reached again otherwise has two parents, refused below.
    done, depth = set(), {}  # depth: each link of the current descent, at its index in `descent`
    for start in links:
        if start in done:
            continue
        descent, through = [(start, iter(children.get(start, ())))], []  # through[k]: descent[k] to descent[k + 1]
        depth[start] = 0
        while descent:
            link, pending = descent[-1]
            joint = next(pending, None)
            if joint is None:
                descent.pop()
                del depth[link]
                done.add(link)
                if through:
                    through.pop()
            elif joint.child in depth:
                names = [repr(step.name) for step in [*through[depth[joint.child]:], joint]]
                if len(names) > 6:  # a cycle may run through a thousand joints: the line stays readable
                    names[3:-2] = [f'… ({len(names) - 5} more)']
                raise ModelError(f'URDF {path}: joints {" → ".join(names)} form a cycle through link '
                                 f'{joint.child!r}: a URDF is a tree')
            elif joint.child not in done:
                depth[joint.child] = len(descent)
                descent.append((joint.child, iter(children.get(joint.child, ()))))
                through.append(joint)
    parents = {}
    for joint in joints.values():
        if joint.child in parents:
            raise ModelError(f'URDF {path}: link {joint.child!r} is the child of two joints '
                             f'({parents[joint.child]!r}, {joint.name!r}): a URDF is a tree')
        parents[joint.child] = joint.name
    roots = [link for link in links if link not in parents]
    if len(roots) > 1:
        raise ModelError(f'URDF {path}: links {roots[0]!r} and {roots[1]!r} are both the child of no joint: a URDF '
                         f'is one tree, with one root link')


def read_urdf(path: Path) -> UrdfDescription:
    """The URDF as urdfdom reads it: <robot>'s own <link> and <joint> elements (not those inside <gazebo>, xacro
    or any other element), every number read by urdfdom's rule; refuses joint types no fixed-base arm model takes,
    inertials no body has and joints that do not make the links one tree.

    Read from the XML: Pinocchio's parser turns a floating or planar joint into a base of 6 or 3 DOF and a mimic
    joint into an independent one without a word, and gives a link whose <inertial> urdfdom cannot read mass 0.
    """
    text, root = _read_xml(path)
    if root.tag != 'robot':
        raise ModelError(f'URDF {path}: the root element is <{root.tag}>, not <robot>')
    links = root.findall('link')
    if not links:
        raise ModelError(f'URDF {path} has no <link>, which urdfdom requires')
    if len(links) > MAX_URDF_LINKS:
        raise ModelError(f'URDF {path} has {len(links)} links, more than the {MAX_URDF_LINKS} ddarm reads (an arm '
                         f'has tens)')
    joint_elements = root.findall('joint')
    if len(joint_elements) >= MAX_URDF_LINKS:
        raise ModelError(f'URDF {path} has {len(joint_elements)} joints, more than a tree of at most '
                         f'{MAX_URDF_LINKS} links has')
    inertias = {}
    for element in links:
        name = element.get('name')
        if not name:
            raise ModelError(f'URDF {path}: a <link> has no name')
        if name in inertias:
            raise ModelError(f'URDF {path}: link {name!r} is defined twice')
        inertias[name] = _inertia(path, name, element)
    joints = {}
    for element in joint_elements:
        joint = _joint(path, element, inertias)
        if joint.name in joints:
            raise ModelError(f'URDF {path}: joint {joint.name!r} is defined twice')
        joints[joint.name] = joint
    _check_tree(path, list(inertias), joints)
    return UrdfDescription(text, inertias, joints)


def urdf_joints(path: Path) -> dict[str, UrdfJoint]:
    """The URDF's joints by name, in file order (read_urdf)."""
    return read_urdf(path).joints


def _locked_positions(path: Path, joints: dict[str, UrdfJoint], movable: list[str], controlled: tuple[str, ...],
                      locked: tuple[tuple[str, float], ...]) -> dict[str, float]:
    """The position of every movable joint not controlled: given, a mimic's from its joint, else 0."""
    given = dict(locked)
    for name in given:
        if name not in joints:
            raise ModelError(f'URDF {path}: locked joint {name!r} is not a joint of the URDF')
        if joints[name].kind == 'fixed':
            raise ModelError(f'URDF {path}: locked joint {name!r} is fixed: only movable joints are locked')
        if name in controlled:
            raise ModelError(f'URDF {path}: joint {name!r} is both controlled and locked')
    for name in controlled:
        joint = joints[name]
        if joint.mimic is not None:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {joint.mimic[0]!r}: a mimic joint cannot be '
                             f'controlled (lock it and the joint it mimics, or remove its <mimic>)')
    positions = {}
    for name in movable:
        if name in controlled:
            continue
        joint = joints[name]
        if joint.mimic is None:
            positions[name] = float(given.get(name, 0.0))
    for name in movable:
        joint = joints[name]
        if name in controlled or joint.mimic is None:
            continue
        source, multiplier, offset = joint.mimic
        if name in given:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {source!r}: give the position of {source!r} '
                             f'under locked, not its own')
        if source not in positions:
            raise ModelError(f'URDF {path}: joint {name!r} mimics {source!r}, which is '
                             f'{"controlled" if source in controlled else "no locked joint"}: mimic joints are '
                             f'supported only locked, with the joint they follow')
        positions[name] = multiplier * positions[source] + offset
    for name, value in positions.items():
        joint = joints[name]
        if not (math.isfinite(value) and joint.lower <= value <= joint.upper):
            raise ModelError(f'URDF {path}: locked joint {name!r} at {value!r} is outside its limits '
                             f'[{joint.lower}, {joint.upper}]')
    return positions


def _check_readable(path: Path) -> None:
    failure = unreachable(path)  # a symlink loop, a folder it may not search: the OS's reason, not 'does not exist'
    if is_missing(failure):
        raise ModelError(f'URDF {path} does not exist')
    if failure is not None:
        raise ModelError(f'URDF {path} cannot be read: {failure.strerror or failure}')
    if path.is_dir():
        raise ModelError(f'URDF {path} is a directory, not a URDF file')
    if not path.is_file():  # a FIFO or a device would block the read, or never end it
        raise ModelError(f'URDF {path} cannot be read: it is not a regular file (a FIFO, a socket or a device)')


def _read_model(path: Path, description: UrdfDescription) -> pin.Model:
    """Pinocchio's model of the URDF, with each joint's armature, which urdfdom does not read."""
    try:
        model = pin.buildModelFromXML(description.text)
    except (RuntimeError, ValueError) as error:
        raise ModelError(f'URDF {path} is not a URDF the arm can be built from: {error}') from error
    _check_readers_agree(path, description, model)
    armature = np.array(model.armature)
    for joint_id, name in enumerate(list(model.names)[1:], start=1):
        armature[model.joints[joint_id].idx_v] = description.joints[name].armature
    model.armature = armature
    return model


def _same(ours: float, theirs: float) -> bool:
    return ours == theirs or (math.isfinite(ours) and math.isfinite(theirs)
                              and abs(ours - theirs) <= 1e-12 * max(abs(ours), abs(theirs)))


def _close(ours: np.ndarray, theirs: np.ndarray, floor: float = 0.0) -> bool:
    """Equal to rounding: within 1e-9 of the larger entry's magnitude (or of `floor`)."""
    scale = max(float(np.max(np.abs(ours))), float(np.max(np.abs(theirs))), floor)
    return bool(np.all(np.abs(ours - theirs) <= 1e-9 * scale))


def _links_at_zero(description: UrdfDescription) -> tuple[dict, dict]:
    """Each link's frame in the root link's at q = 0, and the movable joint that carries it ('' for none); the
    joints make the links one tree (read_urdf refuses any other)."""
    children = {}
    for joint in description.joints.values():
        children.setdefault(joint.parent, []).append(joint)
    parented = {joint.child for joint in description.joints.values()}
    root = next(link for link in description.inertias if link not in parented)
    placements, carriers, pending = {root: pin.SE3.Identity()}, {root: ''}, [root]
    while pending:
        link = pending.pop()
        for joint in children.get(link, ()):
            placements[joint.child] = placements[link] * joint.origin
            carriers[joint.child] = joint.name if joint.kind in MOVABLE else carriers[link]
            pending.append(joint.child)
    return placements, carriers


def _check_readers_agree(path: Path, description: UrdfDescription, model: pin.Model) -> None:
    """Refuse a URDF Pinocchio (urdfdom) built otherwise than ddarm read it: joints, their types, limits, axes and
    frames, links and the inertia each joint moves. What ddarm checks and reports must be what it simulates."""
    def disagree(element, ours, theirs):
        return ModelError(f'URDF {path}: {element}: {ours} as ddarm reads the file and {theirs} as Pinocchio '
                          f'(urdfdom) builds it: refused, since what ddarm checks and reports would not be what it '
                          f'simulates')
    movable = [name for name, joint in description.joints.items() if joint.kind in MOVABLE]
    built = list(model.names)[1:]
    if sorted(movable) != sorted(built):
        raise disagree('the movable joints', sorted(movable), sorted(built))
    bodies = {frame.name: index for index, frame in enumerate(model.frames) if frame.type == pin.FrameType.BODY}
    if sorted(bodies) != sorted(description.inertias):
        raise disagree('the links', sorted(description.inertias), sorted(bodies))
    placements, carriers = _links_at_zero(description)
    data = model.createData()
    zero = pin.neutral(model)
    pin.framesForwardKinematics(model, data, zero)
    pin.computeJointJacobians(model, data, zero)
    for link, frame_id in bodies.items():
        carrier = model.names[model.frames[frame_id].parentJoint] if model.frames[frame_id].parentJoint else ''
        if carrier != carriers[link]:
            raise disagree(f'the joint that moves link {link!r}', repr(carriers[link]), repr(carrier))
        ours, theirs = placements[link], data.oMf[frame_id]
        if not (_close(ours.translation, theirs.translation, 1.0) and _close(ours.rotation, theirs.rotation, 1.0)):
            raise disagree(f'the position of link {link!r} at q = 0 (the <origin> of the joints down to it)',
                           ours.translation.tolist(), theirs.translation.tolist())
    for joint_id, name in enumerate(built, start=1):
        joint, built_joint = description.joints[name], model.joints[joint_id]
        kind = ('prismatic' if is_prismatic(built_joint.shortname()) else
                'continuous' if built_joint.nq == 2 else 'revolute')
        if kind != joint.kind:
            raise disagree(f'joint {name!r}', joint.kind, kind)
        limits = [('effort', joint.effort, model.effortLimit[built_joint.idx_v]),
                  ('velocity', joint.velocity, model.velocityLimit[built_joint.idx_v])]
        if kind != 'continuous':
            limits += [('lower', joint.lower, model.lowerPositionLimit[built_joint.idx_q]),
                       ('upper', joint.upper, model.upperPositionLimit[built_joint.idx_q])]
        for attribute, ours, theirs in limits:
            if not _same(ours, float(theirs)):
                raise disagree(f'joint {name!r} <limit {attribute}>', ours, float(theirs))
        for attribute, ours, theirs in (('damping', joint.damping, model.damping[built_joint.idx_v]),
                                        ('friction', joint.friction, model.friction[built_joint.idx_v])):
            if not _same(ours, float(theirs)):
                raise disagree(f'joint {name!r} <dynamics {attribute}>', ours, float(theirs))
        # Pinocchio returns a one-column Jacobian of a one-dof model as a vector.
        jacobian = np.reshape(pin.getJointJacobian(model, data, joint_id, pin.LOCAL_WORLD_ALIGNED), (6, model.nv))
        motion = jacobian[:, built_joint.idx_v]
        ours, theirs = placements[joint.child].rotation @ joint.axis, motion[:3] if kind == 'prismatic' else motion[3:]
        if not _close(ours, theirs, 1.0):
            raise disagree(f'joint {name!r} <axis> (at q = 0, in the root link\'s frame)', ours.tolist(),
                           theirs.tolist())
        carried = [link for link, carrier in carriers.items() if carrier == name]
        inertias = [placements[joint.child].actInv(placements[link]).act(description.inertias[link])
                    for link in carried if description.inertias[link] is not None]
        mass = sum(inertia.mass for inertia in inertias)
        if 0 < mass < np.finfo(float).eps:  # pin.Inertia's sum divides by max(mass, eps): its centre of mass is off
            raise ModelError(f'URDF {path}: links {carried}, which joint {name!r} moves, weigh {mass!r} kg in all, '
                             f'less than Pinocchio resolves (2.2e-16 kg): give them mass 0 or a real one')
        with np.errstate(over='ignore', invalid='ignore'):
            ours = sum((inertia.matrix() for inertia in inertias), np.zeros((6, 6)))
        if not np.all(np.isfinite(ours)):
            raise ModelError(f'URDF {path}: the inertia of links {carried}, which joint {name!r} moves, is too '
                             f'large for floating point (their mass, moments or lever arms)')
        theirs = model.inertias[joint_id]
        if not (abs(mass - theirs.mass) <= 1e-9 * max(mass, theirs.mass) and _close(ours, theirs.matrix())):
            lever = sum(inertia.mass * inertia.lever for inertia in inertias) / mass if mass > 0 else np.zeros(3)
            raise disagree(f'the <inertial> of links {carried}, which joint {name!r} moves',
                           f'mass {mass!r} at {lever.tolist()}', f'mass {theirs.mass!r} at {theirs.lever.tolist()}')


def _reduced_model(full: pin.Model, locked: list[int], reference: np.ndarray) -> pin.Model:
    """pin.buildReducedModel, also for a URDF that names a link or a fixed joint like a joint.

    buildReducedModel looks frames up by name alone and fails on two of one name: the other frames take a
    unique name for it, and their own again in the reduced model.
    """
    model = pin.Model(full)
    names = [frame.name for frame in model.frames]
    counts, taken, originals = Counter(names), set(names), {}
    for index, name in enumerate(names):
        if counts[name] > 1 and model.frames[index].type != pin.FrameType.JOINT:
            stand_in = next(candidate for candidate in (f'{name}#{number}' for number in itertools.count())
                            if candidate not in taken)
            taken.add(stand_in)
            originals[stand_in] = name
            model.frames[index].name = stand_in
    reduced = pin.buildReducedModel(model, locked, reference)
    for frame in reduced.frames:
        if frame.name in originals:
            frame.name = originals[frame.name]
    return reduced


def _mass_matrix(model: pin.Model, data: pin.Data, configuration: np.ndarray) -> np.ndarray:
    upper = pin.crba(model, data, configuration)  # its upper triangle only
    return np.triu(upper) + np.triu(upper, 1).T


def _mass_matrix_problem(mass: np.ndarray, joint_names: list[str], where: str) -> tuple[str, str] | None:
    """What is wrong with M(q) at `where` and its cause in a URDF, or None for a finite positive definite M."""
    if not np.all(np.isfinite(mass)):
        involved = [name for name, row in zip(joint_names, mass) if not np.all(np.isfinite(row))]
        return (f'M(q) at {where} is not finite (joints {involved})',
                'their links\' masses, moments or lever arms are too large for floating point')
    for name, value in zip(joint_names, np.diag(mass)):
        if not value > 0:
            return (f'joint {name!r} moves no mass or inertia (M_ii = {float(value)!r} at {where})',
                    'lock it, or give its link an <inertial>')
    values = np.linalg.eigvalsh(mass / np.max(np.abs(mass)))  # normalised: eigh must not overflow
    if values[0] > 1e-12 * values[-1]:
        return None
    diagonal = np.sqrt(np.diag(mass))
    values, vectors = np.linalg.eigh(mass / np.outer(diagonal, diagonal))  # blind to each joint's scale
    if not values[0] > 1e-12 * values[-1]:
        involved = [name for name, part in zip(joint_names, vectors[:, 0]) if abs(part) > 0.1]
        return (f'M(q) is singular at {where} (joints {involved})',
                'they move the same inertia, e.g. two coaxial joints with no mass between them: lock one of them')
    heaviest, lightest = int(np.argmax(diagonal)), int(np.argmin(diagonal))
    return (f'M(q) is ill-conditioned at {where}: joint {joint_names[heaviest]!r} moves '
            f'{float(diagonal[heaviest] ** 2):.3g} (M_ii) and joint {joint_names[lightest]!r} '
            f'{float(diagonal[lightest] ** 2):.3g}',
            'floating point cannot integrate inertias this far apart: check their links\' <inertial>')


@dataclass(frozen=True)
class Arm:
    """A fixed-base arm of revolute, continuous and prismatic joints (the controlled ones), and a Pinocchio
    workspace for its dynamics.

    Like Pinocchio's own Model/Data pair, `model` is what the robot is and
    `data` is scratch space: an Arm is not to be shared between threads.
    """

    model: pin.Model
    data: pin.Data
    urdf_path: Path
    lower: np.ndarray  # the URDF's <limit> per controlled joint (±inf for a continuous joint)
    upper: np.ndarray
    velocity_limit: np.ndarray
    effort_limit: np.ndarray
    unbounded: np.ndarray  # continuous joints: (cos θ, sin θ) to Pinocchio
    locked: tuple[tuple[str, float], ...] = ()  # every movable joint not controlled, at its position
    mass_scale: tuple[float, ...] | None = None  # the factors each controlled joint's link inertia is scaled by
    unscaled: pin.Model | None = field(default=None, compare=False, repr=False)  # the model before mass_scale

    @classmethod
    def from_urdf(cls, urdf_path: Path | str | None = None, mass_scale: np.ndarray | list[float] | None = None,
                  joints: tuple[str, ...] | list[str] | None = None,
                  locked: tuple[tuple[str, float], ...] | dict = ()) -> Arm:
        """Load the URDF reduced to `joints` (default: every movable joint), the others at `locked` (default 0).

        `mass_scale` multiplies each controlled joint's link inertia (mass and moments, locked
        links folded in): a heavier link of the same shape and uniform density scales its whole
        spatial inertia, which is how the plant is made to differ from the model.
        """
        path = Path(urdf_path) if urdf_path is not None else default_urdf_path()
        _check_readable(path)
        description = read_urdf(path)  # first: Pinocchio's parser prints its own lines for what it cannot read
        described = description.joints
        full = _read_model(path, description)
        movable = list(full.names)[1:]
        controlled = tuple(movable if joints is None else joints)
        if not controlled:
            raise ModelError(f'URDF {path}: no joint to control (its movable joints: {movable})')
        for name in controlled:
            if name not in movable:
                kind = described[name].kind if name in described else None
                raise ModelError(f'URDF {path}: joint {name!r} is '
                                 f'{"a " + kind + " joint" if kind else "not a joint of the URDF"}; its movable '
                                 f'joints: {movable}')
        repeated = sorted({name for name in controlled if controlled.count(name) > 1})
        if repeated:
            raise ModelError(f'URDF {path}: joints {repeated} named more than once')
        in_model_order = [name for name in movable if name in controlled]
        if list(controlled) != in_model_order:
            raise ModelError(f'URDF {path}: list the controlled joints in the URDF\'s order (parent before child, '
                             f'as Pinocchio numbers them): {in_model_order}, not {list(controlled)}')
        locked = tuple(locked.items()) if isinstance(locked, dict) else tuple(locked)
        positions = _locked_positions(path, described, movable, controlled, locked)
        model = full
        if positions:
            reference = pin.neutral(full)
            for name, value in positions.items():
                joint = full.joints[full.getJointId(name)]
                if joint.nq == 2:
                    reference[joint.idx_q:joint.idx_q + 2] = (math.cos(value), math.sin(value))
                else:
                    reference[joint.idx_q] = value
            model = _reduced_model(full, [full.getJointId(name) for name in positions], reference)
        for joint_id in range(1, model.njoints):
            kind = model.joints[joint_id].shortname()
            if kind not in PINOCCHIO_JOINTS:
                raise ModelError(f'URDF {path}: joint {model.names[joint_id]!r} is a {kind}; ddarm supports '
                                 f'revolute, continuous and prismatic joints')
        unscaled, scale = None, None
        if mass_scale is not None:
            scale = np.asarray(mass_scale, dtype=float)
            if scale.shape != (model.nv,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
                raise ModelError(f'mass_scale must be {model.nv} finite positive numbers, got {mass_scale!r}')
            unscaled, model = model, pin.Model(model)
            for joint_id, factor in enumerate(scale.tolist(), start=1):
                inertia = model.inertias[joint_id]
                with np.errstate(over='ignore', invalid='ignore'):
                    mass, moments = factor * inertia.mass, factor * inertia.inertia
                if not (math.isfinite(mass) and np.all(np.isfinite(moments))):
                    raise ModelError(f'mass_scale {factor!r} for joint {model.names[joint_id]!r} makes the mass '
                                     f'({inertia.mass!r} kg) and moments its links have in URDF {path} overflow '
                                     f'floating point')
                model.inertias[joint_id] = pin.Inertia(mass, inertia.lever, moments)
        limits = [described[name] for name in controlled]
        arm = cls(model=model, data=model.createData(), urdf_path=path,
                  lower=np.array([joint.lower for joint in limits]), upper=np.array([joint.upper for joint in limits]),
                  velocity_limit=np.array([joint.velocity for joint in limits]),
                  effort_limit=np.array([joint.effort for joint in limits]),
                  unbounded=np.array([model.joints[i].nq == 2 for i in range(1, model.njoints)]),
                  locked=tuple(positions.items()), mass_scale=None if scale is None else tuple(scale.tolist()),
                  unscaled=unscaled)
        arm.check_inertia(np.zeros(arm.dof), 'q = 0')
        return arm

    def check_inertia(self, q: np.ndarray, where: str) -> None:
        """Refuse an M(q) that is not finite and positive definite: the plant could not be integrated, nor M̂
        inverted. Blames mass_scale where the unscaled links give a good M(q)."""
        problem = _mass_matrix_problem(self.mass_matrix(q), self.joint_names, where)
        if problem is None:
            return
        summary, cause = problem
        if self.unscaled is not None:
            mass = _mass_matrix(self.unscaled, self.unscaled.createData(), self.configuration(q))
            if _mass_matrix_problem(mass, self.joint_names, where) is None:
                raise ModelError(f'mass_scale {list(self.mass_scale)}: {summary} with the links of URDF '
                                 f'{self.urdf_path} scaled by it, not without: floating point cannot hold factors '
                                 f'this far from 1 (or from each other)')
        raise ModelError(f'URDF {self.urdf_path}: {summary}: {cause}')

    @property
    def dof(self) -> int:
        return self.model.nv

    @property
    def joint_names(self) -> list[str]:
        return list(self.model.names)[1:]

    @property
    def prismatic(self) -> np.ndarray:
        """Which controlled joints are prismatic (positions in m, efforts in N); the others are angles."""
        return np.array([is_prismatic(self.model.joints[i].shortname()) for i in range(1, self.model.njoints)])

    def configuration(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio's configuration of joint positions q: (cos θ, sin θ) for each continuous joint."""
        if not self.unbounded.any():
            return q
        q = np.asarray(q, dtype=float)
        parts = [(math.cos(value), math.sin(value)) if unbounded else (value,)
                 for value, unbounded in zip(q, self.unbounded)]
        return np.array([x for part in parts for x in part])

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q) of (1.1), symmetric."""
        return _mass_matrix(self.model, self.data, self.configuration(q))

    def bias(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """V(q, q̇) + G(q) of (1.1)."""
        return pin.nonLinearEffects(self.model, self.data, self.configuration(q), v).copy()

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G(q) of (1.1)."""
        return pin.computeGeneralizedGravity(self.model, self.data, self.configuration(q)).copy()

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque (articulated-body algorithm)."""
        return pin.aba(self.model, self.data, self.configuration(q), v, torque).copy()

    def inverse_dynamics(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """M(q) a + V(q, q̇) + G(q) (recursive Newton-Euler)."""
        return pin.rnea(self.model, self.data, self.configuration(q), v, a).copy()

    def energy(self, q: np.ndarray, v: np.ndarray) -> float:
        """Kinetic plus potential energy, for conservation checks."""
        configuration = self.configuration(q)
        kinetic = pin.computeKineticEnergy(self.model, self.data, configuration, v)
        potential = pin.computePotentialEnergy(self.model, self.data, configuration)
        return float(kinetic + potential)

    def frame_position(self, q: np.ndarray, frame: str) -> np.ndarray:
        """Position of a URDF link frame (or, for a name no link has, a joint frame) in the fixed frame."""
        # A URDF may name a link and a joint alike: the link is meant.
        kind = pin.FrameType.BODY if self.model.existFrame(frame, pin.FrameType.BODY) else None
        if kind is None and not self.model.existFrame(frame):
            raise ModelError(f'no frame {frame!r} in {self.urdf_path}')
        pin.framesForwardKinematics(self.model, self.data, self.configuration(q))
        frame_id = self.model.getFrameId(frame) if kind is None else self.model.getFrameId(frame, kind)
        return self.data.oMf[frame_id].translation.copy()


def urdf_stamp(urdf: str | None) -> tuple:
    """What a cached model of `urdf` is valid for: the file's modification time and size (a file edited between
    two commands of one process is read again)."""
    try:
        status = os.stat(urdf if urdf is not None else default_urdf_path())
    except OSError:
        return ()  # from_urdf refuses it, naming why
    return status.st_mtime_ns, status.st_size


def movable_joints(urdf: str) -> tuple[str, ...]:
    """The URDF's movable joints, in file order, read once per version of the file."""
    return _movable_joints(urdf, urdf_stamp(urdf))


@lru_cache(maxsize=16)
def _movable_joints(urdf, stamp) -> tuple[str, ...]:
    _check_readable(Path(urdf))
    return tuple(joint.name for joint in urdf_joints(Path(urdf)).values() if joint.kind in MOVABLE)


def load_arm(urdf: str | None, mass_scale: tuple[float, ...] | None = None, joints: tuple[str, ...] | None = None,
             locked: tuple[tuple[str, float], ...] = ()) -> Arm:
    """The arm from a URDF, loaded once per process and version of the file (Arm holds scratch space: one thread
    only)."""
    return _load_arm(urdf, urdf_stamp(urdf), mass_scale, joints, locked)


@lru_cache(maxsize=16)
def _load_arm(urdf, stamp, mass_scale, joints, locked) -> Arm:
    return Arm.from_urdf(urdf, mass_scale, joints, locked)
