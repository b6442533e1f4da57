"""URDFs from someone else (issue 23): what ddarm reads is what Pinocchio (urdfdom) builds, or the file is refused.

Each case is refused naming the link or joint and the attribute, on one line, before urdfdom prints its own
lines; what both readers accept is checked against Pinocchio's model built here from the same file.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from ddarm.cli.main import main
from ddarm.physics.arm import Arm, ModelError, _check_readers_agree, default_urdf_path, read_urdf, urdf_joints
from test_arms import inertial, joint, robot

LINK_ORIGINS = {'l1': '0 0 0.1', 'l2': '0.2 0 0', 'l3': '0.15 0 0'}
MOTION = {'joint_names': ['j1', 'j2', 'j3'], 'duration': 0.3, 'profile': 'bang_bang', 'start': [0.0, 0.0, 0.0],
          'goal': [0.3, 0.4, 0.5]}


def arm_urdf(l2_inertial: str | None = None, j2: str | None = None, extra: str = '', l2: str = 'l2',
             prolog: str = '<?xml version="1.0"?>') -> str:
    """Three revolute joints (a yaw, then two pitches); `l2_inertial` replaces link l2's <inertial>, `j2` joint j2."""
    links = {'base': '', 'l1': inertial(2.0, LINK_ORIGINS['l1'], ixx=0.02, iyy=0.02, izz=0.01),
             l2: inertial(1.5, LINK_ORIGINS['l2'], ixx=0.002, iyy=0.02, izz=0.02) if l2_inertial is None
             else l2_inertial,
             'l3': inertial(1.0, LINK_ORIGINS['l3'], ixx=0.001, iyy=0.01, izz=0.01)}
    text = robot(joint('j1', 'revolute', 'base', 'l1', '0 0 0.1', effort=100),
                 j2 if j2 is not None else joint('j2', 'revolute', 'l1', l2, '0 0 0.2', axis='0 1 0', effort=100),
                 joint('j3', 'revolute', l2, 'l3', '0.4 0 0', axis='0 1 0', effort=100), extra, links=links)
    return text.replace('<?xml version="1.0"?>', prolog, 1)


def l2_inertial(mass='1.5', xyz='0.2 0 0', rpy='0 0 0', ixx='0.002', iyy='0.02', izz='0.02', ixy='0', ixz='0',
                iyz='0') -> str:
    return inertial(mass, xyz, rpy, ixx, iyy, izz, ixy, ixz, iyz)


def write(tmp_path: Path, text: str | bytes) -> Path:
    path = tmp_path / 'arm.urdf'
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def episode(capfd, tmp_path, monkeypatch, urdf_text, *extra, motion=None) -> tuple[int, str, str]:
    """`ddarm episode --json` on the URDF text (and the motion) in tmp_path: (exit code, stdout, stderr)."""
    monkeypatch.chdir(tmp_path)
    urdf = write(tmp_path, urdf_text)
    motion_path = tmp_path / 'motion.yaml'
    motion_path.write_text(yaml.safe_dump(motion or MOTION, sort_keys=False))
    capfd.readouterr()
    code = main(['episode', '--controller', 'computed_torque', '--omega', '15', '--urdf', str(urdf), '--motion',
                 str(motion_path), '--json', *extra])
    out, err = capfd.readouterr()
    return code, out, err


def assert_refused(capfd, tmp_path, monkeypatch, urdf_text, named, *extra, motion=None) -> str:
    """Exit 2, nothing on stdout, one line on stderr (none of urdfdom's) holding every text of `named`."""
    code, out, err = episode(capfd, tmp_path, monkeypatch, urdf_text, *extra, motion=motion)
    assert code == 2, (out, err)
    assert out == '' and 'Traceback' not in err, err
    assert len(err.strip().splitlines()) == 1, err
    for text in named:
        assert text in err, (text, err)
    return err


def pinocchio_model(path: Path) -> pin.Model:
    return pin.buildModelFromUrdf(str(path))


# ---------------------------------------------------------------------------------------------------------------
# Inertials


UNREADABLE_INERTIALS = [
    ('mass nan', l2_inertial(mass='nan'), ['value', 'nan']),
    ('mass inf', l2_inertial(mass='inf'), ['value', 'inf']),
    ('mass overflowing', l2_inertial(mass='1e999'), ['value', '1e999']),
    ('mass with a decimal comma', l2_inertial(mass='1,5'), ['value', '1,5']),
    ('mass a word', l2_inertial(mass='heavy'), ['value', 'heavy']),
    ('mass with a trailing blank', l2_inertial(mass='1.5 '), ['value']),
    ('mass with a digit separator', l2_inertial(mass='1_5'), ['value', '1_5']),
    ('mass in hexadecimal', l2_inertial(mass='0x2'), ['value', '0x2']),
    ('mass in Arabic-Indic digits', l2_inertial(mass='\u0663'), ['value']),
    ('ixx nan', l2_inertial(ixx='nan'), ['ixx', 'nan']),
    ('iyz infinite', l2_inertial(iyz='-inf'), ['iyz', '-inf']),
    ('origin nan', l2_inertial(xyz='0.2 nan 0'), ['xyz', 'nan']),
    ('origin rpy infinite', l2_inertial(rpy='0 0 inf'), ['rpy', 'inf']),
    ('origin of two numbers', l2_inertial(xyz='0.2 0'), ['xyz', '0.2 0']),
    ('origin with commas', l2_inertial(xyz='0.2,0,0'), ['xyz', '0.2,0,0']),
    ('no mass', '<inertial><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>', ['<mass>']),
    ('mass without value', '<inertial><mass/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>',
     ['<mass>', 'value']),
    ('no inertia', '<inertial><mass value="1.5"/></inertial>', ['<inertia>']),
    ('inertia without ixy', '<inertial><mass value="1.5"/><inertia ixx="1" ixz="0" iyy="1" iyz="0" izz="1"/>'
     '</inertial>', ['ixy']),
    ('two masses', '<inertial><mass value="1.5"/><mass value="9"/><inertia ixx="0.002" ixy="0" ixz="0" iyy="0.02" '
     'iyz="0" izz="0.02"/></inertial>', ['<mass>']),
    ('two inertials', l2_inertial() + l2_inertial(mass='9'), ['<inertial>']),
]
NON_PHYSICAL_INERTIALS = [
    ('a negative moment', l2_inertial(ixx='-0.1'), ['negative']),
    ('a negative principal moment', l2_inertial(ixx='0.01', iyy='0.01', izz='0.02', ixy='0.02'), ['negative']),
    ('moments breaking the triangle inequality', l2_inertial(ixx='0.01', iyy='0.01', izz='0.05'), ['triangle']),
    ('a negative mass', l2_inertial(mass='-1.5'), ['mass', '-1.5']),
    ('no mass but moments', l2_inertial(mass='0'), ['mass 0']),
]


@pytest.mark.parametrize('case, text, named', UNREADABLE_INERTIALS + NON_PHYSICAL_INERTIALS,
                         ids=[case[0] for case in UNREADABLE_INERTIALS + NON_PHYSICAL_INERTIALS])
def test_an_inertial_urdfdom_cannot_read_or_no_body_has_is_refused_naming_the_link(capfd, tmp_path, monkeypatch, case,
                                                                                    text, named):
    """urdfdom drops such an <inertial> with lines on stderr and Pinocchio gives the link mass 0: an episode on an
    arm without link l2's mass would have run with exit 0."""
    assert_refused(capfd, tmp_path, monkeypatch, arm_urdf(text), ["link 'l2'", *named])


@pytest.mark.parametrize('text', [l2_inertial(mass='0', ixx='0', iyy='0', izz='0'), ''],
                         ids=['mass 0 and no moments', 'no inertial'])
def test_a_massless_link_is_a_link_without_inertial(tmp_path, text):
    """mass 0 with zero moments is accepted (urdfdom's reading, and the shipped Panda's and UR5's end links)."""
    arm = Arm.from_urdf(write(tmp_path, arm_urdf(text)))
    model = pinocchio_model(tmp_path / 'arm.urdf')
    assert model.inertias[2].mass == 0.0
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(arm.mass_matrix(q), pin.crba(model, model.createData(), q), rtol=1e-12, atol=1e-15)


def test_a_thin_rod_and_a_point_mass_are_bodies(tmp_path):
    """A zero principal moment (the paper's links, config/ddarm.urdf) meets the triangle inequality: accepted."""
    rod = l2_inertial(ixx='0.0', iyy='0.02', izz='0.02')
    Arm.from_urdf(write(tmp_path, arm_urdf(rod)))
    Arm.from_urdf(write(tmp_path, arm_urdf(l2_inertial(ixx='0', iyy='0', izz='0'))))
    Arm.from_urdf()


def test_numbers_as_urdfdom_reads_them_are_read_alike(tmp_path):
    """Signs, exponents, a leading blank and a bare decimal point: urdfdom's std::istringstream reads them."""
    text = arm_urdf(l2_inertial(mass=' +1.5e0', xyz='  .2 0  0. ', ixx='2E-3'))
    arm = Arm.from_urdf(write(tmp_path, text))
    model = pinocchio_model(tmp_path / 'arm.urdf')
    assert model.inertias[2].mass == 1.5
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(arm.mass_matrix(q), pin.crba(model, model.createData(), q), rtol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# Joints


def j2_with(**changes) -> str:
    arguments = dict(name='j2', kind='revolute', parent='l1', child='l2', xyz='0 0 0.2', axis='0 1 0', effort=100)
    arguments.update(changes)
    return joint(**arguments)


UNREADABLE_JOINTS = [
    ('origin nan', j2_with(xyz='0 0 nan'), ['xyz', 'nan']),
    ('rpy of four numbers', j2_with(rpy='0 0 0 1'), ['rpy']),
    ('axis infinite', j2_with(axis='0 inf 0'), ['<axis>', 'inf']),
    ('the zero axis', j2_with(axis='0 0 0'), ['<axis>']),
    ('effort overflowing', j2_with(effort='1e999'), ['effort', '1e999']),
    ('effort negative', j2_with(effort='-5'), ['effort', '-5']),
    ('its own parent', joint('j2', 'revolute', 'l2', 'l2', '0 0 0.2', axis='0 1 0', effort=100),
     ['both its parent and its child']),
    ('velocity a word', j2_with(velocity='fast'), ['velocity', 'fast']),
    ('lower above upper', j2_with(lower=1.0, upper=-1.0), ['lower', 'upper']),
    ('no limit', '<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><axis xyz="0 1 0"/></joint>',
     ['<limit>']),
    ('limit without effort', '<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>'
     '<limit lower="-1" upper="1" velocity="1"/></joint>', ['effort']),
    ('two limits', j2_with(mimic='<limit lower="-1" upper="1" effort="0.5" velocity="1"/>'), ['<limit>']),
    ('damping nan', j2_with(mimic='<dynamics damping="nan"/>'), ['damping', 'nan']),
    ('no type', '<joint name="j2"><parent link="l1"/><child link="l2"/></joint>', ['type']),
    ('an unknown child', j2_with(child='l9'), ['l9']),
    ('defined twice', j2_with() + j2_with(effort=5), ['twice']),
]


@pytest.mark.parametrize('case, text, named', UNREADABLE_JOINTS, ids=[case[0] for case in UNREADABLE_JOINTS])
def test_a_joint_urdfdom_cannot_read_is_refused_naming_the_joint(capfd, tmp_path, monkeypatch, case, text, named):
    assert_refused(capfd, tmp_path, monkeypatch, arm_urdf(j2=text), ["'j2'", *named])


NOT_TREES = [
    ('a cycle back to the root link', arm_urdf(extra=joint('j4', 'revolute', 'l3', 'base', '0.3 0 0', axis='0 1 0')),
     ["joints 'j1' → 'j2' → 'j3' → 'j4' form a cycle through link 'base'"]),
    ('a cycle among inner links', arm_urdf(j2=j2_with(parent='l3')),
     ["joints 'j3' → 'j2' form a cycle through link 'l2'"]),
    ('a joint back to an inner link', arm_urdf(extra=joint('j4', 'revolute', 'l3', 'l1', '0.3 0 0', axis='0 1 0')),
     ["joints 'j2' → 'j3' → 'j4' form a cycle through link 'l1'"]),
    ('a link with two parents', arm_urdf(extra=joint('j4', 'revolute', 'l1', 'l3', '0.3 0 0', axis='0 1 0')),
     ["link 'l3' is the child of two joints ('j3', 'j4')"]),
    ('two root links', arm_urdf().replace('</robot>', '<link name="stray"/></robot>'), ["links 'base' and 'stray'"]),
]


@pytest.mark.parametrize('case, text, named', NOT_TREES, ids=[case[0] for case in NOT_TREES])
def test_joints_that_do_not_make_the_links_one_tree_are_refused_naming_the_link(capfd, tmp_path, monkeypatch, case,
                                                                                text, named):
    """urdfdom and Pinocchio walk a tree from its root: each of these gave a model of other joints than the file's, or
    urdfdom's own lines on stderr and Pinocchio's "no body named …", or a segfault (below)."""
    assert 'a URDF is' in assert_refused(capfd, tmp_path, monkeypatch, text, named)


@pytest.mark.parametrize('command', [['episode', '--controller', 'computed_torque', '--omega', '15'],
                                     ['stability', '--controller', 'pd_gravity']], ids=['episode', 'stability'])
def test_a_cycle_the_motions_joints_run_through_is_refused_not_a_segfault(tmp_path, command):
    """The paper's arm with a joint from link3 back to link1, every joint in the motion: Pinocchio's URDF builder
    segfaulted (exit 139). Run in a child process, so that a crash fails this test, not the test session."""
    back = joint('back', 'revolute', 'link3', 'link1', '1.0 0 0', axis='0 -1 0')
    urdf = write(tmp_path, default_urdf_path().read_text().replace('</robot>', back + '</robot>'))
    motion = tmp_path / 'motion.yaml'
    motion.write_text(yaml.safe_dump({'joint_names': ['joint1', 'joint2', 'joint3', 'back'], 'duration': 0.3,
                                      'profile': 'bang_bang', 'start': [0.0] * 4, 'goal': [0.3] * 4}))
    arguments = [*command, '--urdf', str(urdf), '--motion', str(motion), '--json']
    script = f'import sys\nfrom ddarm.cli.main import main\nsys.exit(main({arguments!r}))\n'
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and done.stdout == '' and 'Traceback' not in done.stderr, done
    assert "joints 'joint2' → 'joint3' → 'back' form a cycle through link 'link1'" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_a_cycle_of_a_thousand_joints_is_refused_in_one_readable_line(tmp_path):
    """A chain of 999 links (the most whose cycle stays within the 999 joints read) closed back to the root: found
    without recursion, named without listing every joint."""
    from ddarm.physics.arm import MAX_URDF_LINKS

    links = MAX_URDF_LINKS - 1
    closing = joint('back', 'fixed', f'c{links - 5}', 'base')
    with pytest.raises(ModelError, match=f"joints 'j1' → 'j2' → 'j3' → … \\({links - 5} more\\) → 'f{links - 5}' → "
                                         f"'back' form a cycle through link 'base'"):
        read_urdf(write(tmp_path, fixed_chain(links).replace('</robot>', closing + '</robot>')))


def test_a_revolute_limit_without_lower_and_upper_is_zero_as_urdfdom_reads_it(tmp_path):
    text = arm_urdf(j2='<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>'
                       '<origin xyz="0 0 0.2"/><axis xyz="0 1 0"/><limit effort="7" velocity="2"/></joint>')
    arm = Arm.from_urdf(write(tmp_path, text), joints=['j1', 'j3'])
    model = pinocchio_model(tmp_path / 'arm.urdf')
    assert urdf_joints(tmp_path / 'arm.urdf')['j2'].lower == model.lowerPositionLimit[1] == 0.0
    assert urdf_joints(tmp_path / 'arm.urdf')['j2'].upper == model.upperPositionLimit[1] == 0.0
    assert arm.joint_names == ['j1', 'j3']


def test_a_joint_inside_gazebo_is_not_the_urdfs_joint(capfd, tmp_path, monkeypatch):
    """urdfdom reads <robot>'s own <joint> and <link> elements; a <gazebo> (or any other) element's are not the
    URDF's. The nested limit of 0.5 N m made --urdf-limits saturate j2 with exit 0."""
    nested = ('<gazebo reference="j2"><joint name="j2" type="revolute"><limit lower="-1" upper="1" effort="0.5" '
              'velocity="1"/></joint><link name="l2"><inertial><mass value="50"/>'
              '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link></gazebo>')
    path = write(tmp_path, arm_urdf(extra=nested))
    arm = Arm.from_urdf(path)
    np.testing.assert_array_equal(arm.effort_limit, [100.0, 100.0, 100.0])
    reference = pinocchio_model(path)
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(arm.mass_matrix(q), pin.crba(reference, reference.createData(), q), rtol=1e-12)
    code, out, err = episode(capfd, tmp_path, monkeypatch, arm_urdf(extra=nested), '--urdf-limits')
    assert code == 0, err
    assert yaml.safe_load(out)['saturated_joints'] == []


# ---------------------------------------------------------------------------------------------------------------
# XML


DOCTYPES = [
    ('an entity in a joint name', '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY two "j2">]>',
     lambda text: text.replace('name="j2"', 'name="&two;"')),
    ('billion laughs', '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa">'
     + ''.join(f'<!ENTITY {chr(98 + i)} "{("&" + chr(97 + i) + ";") * 10}">' for i in range(9))
     + ']>', lambda text: text.replace('name="test"', 'name="&j;"')),
    ('an external entity', '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY secret SYSTEM "file:///etc/hostname">]>',
     lambda text: text.replace('name="test"', 'name="&secret;"')),
    ('an external DTD', '<?xml version="1.0"?><!DOCTYPE robot SYSTEM "http://localhost:9/robot.dtd">',
     lambda text: text),
]


@pytest.mark.parametrize('case, prolog, change', DOCTYPES, ids=[case[0] for case in DOCTYPES])
def test_a_document_type_declaration_is_refused(capfd, tmp_path, monkeypatch, case, prolog, change):
    """urdfdom (TinyXML2) expands no entity; the two readers would read different names or numbers."""
    assert_refused(capfd, tmp_path, monkeypatch, change(arm_urdf(prolog=prolog)), ['DOCTYPE'])


def test_a_urdf_is_read_as_utf8_whatever_its_declaration_says(tmp_path):
    """TinyXML2 reads UTF-8 alone; an ISO-8859-1 declaration made ddarm's reader see 'jÃ©' for Pinocchio's 'jé'."""
    text = arm_urdf(prolog='<?xml version="1.0" encoding="ISO-8859-1"?>').replace('"j2"', '"jé"')
    path = write(tmp_path, text.encode('utf-8'))
    arm = Arm.from_urdf(path)
    assert arm.joint_names == list(pinocchio_model(path).names)[1:] == ['j1', 'jé', 'j3']


def test_a_urdf_that_is_not_utf8_is_refused(tmp_path):
    path = write(tmp_path, arm_urdf().replace('"j2"', '"jé"').encode('latin-1'))
    with pytest.raises(ModelError, match='UTF-8'):
        Arm.from_urdf(path)


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    fifo = tmp_path / 'arm.urdf'
    os.mkfifo(fifo)
    script = ('from ddarm.physics.arm import Arm, ModelError\n'
              f'try:\n    Arm.from_urdf({str(fifo)!r})\nexcept ModelError as error:\n    print(error)\n')
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=120)
    assert 'not a regular file' in done.stdout, done


@pytest.mark.parametrize('blank', ['\t', '\n', '\r\n'], ids=['tab', 'LF', 'CR LF'])
def test_a_tab_or_line_break_inside_a_vector_is_read_as_urdfdom_reads_it(capfd, tmp_path, monkeypatch, blank):
    """XML makes a tab or line break in an attribute a blank (ddarm read "0.2 0 0"); TinyXML2 keeps it, urdfdom,
    splitting at blanks only, drops the <inertial> and Pinocchio gives l2 mass 0."""
    text = arm_urdf(l2_inertial(xyz=f'0.2{blank}0 0'))
    path = write(tmp_path, text.encode('utf-8'))
    assert pinocchio_model(path).inertias[2].mass == 0.0
    assert_refused(capfd, tmp_path, monkeypatch, text.encode('utf-8'), ["link 'l2'", 'xyz'])


def test_a_tab_inside_a_name_is_kept_as_urdfdom_keeps_it(tmp_path):
    path = write(tmp_path, arm_urdf().replace('name="j2"', 'name="j\t2"'))
    assert list(urdf_joints(path)) == list(pinocchio_model(path).names)[1:] == ['j1', 'j\t2', 'j3']


def built_otherwise(**changes) -> pin.Model:
    """Pinocchio's model of arm_urdf with j2 or l2 changed, as if urdfdom had read the file otherwise than ddarm."""
    j2 = {key: value for key, value in changes.items() if key != 'l2'}
    text = arm_urdf(changes.get('l2'), j2_with(**j2))
    return pin.buildModelFromXML(text)


DISAGREEMENTS = [
    ('an effort limit', built_otherwise(effort=0.5), ["'j2'", '<limit effort>', '100.0', '0.5']),
    ('a position limit', built_otherwise(lower=-1.0), ["'j2'", '<limit lower>']),
    ('a mass', built_otherwise(l2=l2_inertial(mass='0')), ["'l2'", "'j2'", 'mass 1.5', 'mass 0.0']),
    ('a centre of mass', built_otherwise(l2=l2_inertial(xyz='0.3 0 0')), ["'l2'", "'j2'"]),
    ('an origin', built_otherwise(xyz='0 0 0.25'), ["link 'l2'"]),
    ('an axis', built_otherwise(axis='0 0 1'), ["'j2'", '<axis>']),
    ('a joint type', built_otherwise(kind='continuous'), ["'j2'", 'revolute', 'continuous']),
    ('a joint name', built_otherwise(name='j2b'), ['movable joints', 'j2b']),
]


@pytest.mark.parametrize('case, model, named', DISAGREEMENTS, ids=[case[0] for case in DISAGREEMENTS])
def test_a_model_pinocchio_built_otherwise_than_ddarm_read_the_file_is_refused(tmp_path, case, model, named):
    """The last line of defence: whatever the two XML readers still read differently, what ddarm checked (limits,
    links, inertials) must be what Pinocchio simulates, element by element."""
    path = write(tmp_path, arm_urdf())
    _check_readers_agree(path, read_urdf(path), pin.buildModelFromXML(path.read_text()))
    with pytest.raises(ModelError, match='Pinocchio') as refusal:
        _check_readers_agree(path, read_urdf(path), model)
    for text in named:
        assert text in str(refusal.value), (text, refusal.value)


# ---------------------------------------------------------------------------------------------------------------
# A link named like a joint (the SO-100 of a public robot collection)


def same_name_urdf() -> str:
    links = {'base': '', 'l1': inertial(2.0, '0 0 0.1', ixx=0.02, iyy=0.02, izz=0.01),
             'j2': inertial(1.5, '0.2 0 0', ixx=0.002, iyy=0.02, izz=0.02),
             'l3': inertial(1.0, '0.15 0 0', ixx=0.001, iyy=0.01, izz=0.01),
             'tool': inertial(0.2, '0.02 0 0', ixx=0.0001, iyy=0.0001, izz=0.0001)}
    return robot(joint('j1', 'revolute', 'base', 'l1', '0 0 0.1'),
                 joint('j2', 'revolute', 'l1', 'j2', '0 0 0.2', axis='0 1 0'),
                 joint('j3', 'revolute', 'j2', 'l3', '0.4 0 0', axis='0 1 0'),
                 joint('tool', 'fixed', 'l3', 'tool', '0.3 0 0'), links=links)


@pytest.mark.parametrize('locked', [{'j1': 0.4}, {'j2': -0.7}, {'j3': 0.5}], ids=['j1', 'j2', 'j3'])
def test_a_link_named_like_a_joint_reduces_as_the_full_arm_with_that_joint_held(tmp_path, locked):
    path = write(tmp_path, same_name_urdf())
    controlled = [name for name in ('j1', 'j2', 'j3') if name not in locked]
    arm = Arm.from_urdf(path, joints=controlled, locked=locked)
    full = pinocchio_model(path)
    data = full.createData()
    rng = np.random.default_rng(7)
    keep = [full.getJointId(name) - 1 for name in controlled]
    for _ in range(5):
        q_full = rng.uniform(-1, 1, 3)
        for name, value in locked.items():
            q_full[full.getJointId(name) - 1] = value
        q = q_full[keep]
        mass = pin.crba(full, data, q_full)
        mass = np.triu(mass) + np.triu(mass, 1).T
        np.testing.assert_allclose(arm.mass_matrix(q), mass[np.ix_(keep, keep)], rtol=1e-10, atol=1e-12)
        gravity = pin.computeGeneralizedGravity(full, data, q_full)[keep]
        np.testing.assert_allclose(arm.gravity(q), gravity, rtol=1e-10, atol=1e-12)
        pin.framesForwardKinematics(full, data, q_full)
        for link in ('j2', 'tool'):
            expected = data.oMf[full.getFrameId(link, pin.FrameType.BODY)].translation
            np.testing.assert_allclose(arm.frame_position(q, link), expected, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# Mass scale


@pytest.mark.parametrize('scale', [[1e308] * 3, [1.0, 1e300, 1.0], [1e-320] * 3, [1e150, 1.0, 1e-150]],
                         ids=['overflowing', 'one overflowing', 'underflowing', 'far apart'])
def test_a_mass_scale_floating_point_cannot_hold_is_blamed_not_the_urdf(capfd, tmp_path, monkeypatch, scale):
    """The URDF is fine unscaled: the message must name mass_scale, not a massless link or two coaxial joints."""
    with pytest.raises(ModelError, match='mass_scale') as refusal:
        Arm.from_urdf(mass_scale=scale)
    assert 'coaxial' not in str(refusal.value) and '<inertial>' not in str(refusal.value), refusal.value
    code, out, err = episode(capfd, tmp_path, monkeypatch, arm_urdf(), '--mass-scale', *map(str, scale))
    assert code == 2 and out == '' and len(err.strip().splitlines()) == 1, (out, err)
    assert 'mass_scale' in err and 'coaxial' not in err and 'Traceback' not in err, err


FLOATING_POINT_URDFS = [
    ('a mass of 1e300', l2_inertial(mass='1e300'), "<mass>: value='1e300' is too large for floating point"),
    ('a moment of 1e300', l2_inertial(ixx='1e300', iyy='1e300', izz='1e300'),
     "<inertia>: ixx='1e300' is too large for floating point"),
    ('a product of inertia of -1e300', l2_inertial(ixy='-1e300'), "<inertia>: ixy='-1e300' is too large for floating"),
    ('an inertia overflowing through its lever arm', l2_inertial(mass='1e100', xyz='1e110 0 0'),
     'too large for floating point'),
    ('masses 140 orders of magnitude apart', l2_inertial(mass='1e140', ixx='1e139', iyy='1e139', izz='1e139'),
     'far apart'),
    ('a mass Pinocchio cannot resolve', l2_inertial(mass='1e-300', ixx='1e-300', iyy='1e-300', izz='1e-300'),
     'Pinocchio resolves'),
]


@pytest.mark.parametrize('case, text, named', FLOATING_POINT_URDFS, ids=[case[0] for case in FLOATING_POINT_URDFS])
def test_masses_floating_point_cannot_hold_are_named_as_such(tmp_path, case, text, named):
    """Not "two coaxial joints": the URDF's own numbers are the cause."""
    with pytest.raises(ModelError, match=named) as refusal:
        Arm.from_urdf(write(tmp_path, arm_urdf(text)))
    assert 'coaxial' not in str(refusal.value)


def test_a_mass_of_1e300_at_the_end_of_the_papers_arm_is_too_large_not_two_coaxial_joints(capfd, tmp_path,
                                                                                         monkeypatch):
    """It dwarfs link 2 so that M(q) of joints 2 and 3 was singular, which was refused as "two coaxial joints"."""
    text = default_urdf_path().read_text()
    heavy = text[:text.index('<link name="link3">')] + text[text.index('<link name="link3">'):].replace(
        '<mass value="10.0"/>', '<mass value="1e300"/>', 1)
    err = assert_refused(capfd, tmp_path, monkeypatch, heavy, ["link 'link3'", 'too large for floating point'],
                         motion={'joint_names': ['joint1', 'joint2', 'joint3'], 'duration': 0.3,
                                 'profile': 'bang_bang', 'start': [0.0] * 3, 'goal': [0.3] * 3})
    assert 'coaxial' not in err


def test_masses_and_moments_at_the_bound_are_read(tmp_path):
    """The paper's arm with every mass and moment 1e149 times its own (link 2's and 3's masses 1e150 kg): its M(q)
    is the paper's M(q) scaled alike."""
    from ddarm.physics.arm import MAX_URDF_INERTIA

    text = re.sub(r'(value|i[xyz]{2})="([0-9.]+)"', lambda number: f'{number[1]}="{float(number[2]) * 1e149!r}"',
                  default_urdf_path().read_text())
    assert f'<mass value="{MAX_URDF_INERTIA!r}"/>' in text
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(Arm.from_urdf(write(tmp_path, text)).mass_matrix(q),
                               1e149 * Arm.from_urdf().mass_matrix(q), rtol=1e-12)


@pytest.mark.parametrize('kind, axis', [('revolute', '0 0 1'), ('prismatic', '1 0 0'), ('continuous', '0 0 1')])
def test_a_one_joint_arm_is_read_checked_and_run(capfd, tmp_path, monkeypatch, kind, axis):
    """Pinocchio gives a one-dof model's Jacobian as a vector: the readers' cross-check must still read its column."""
    limit = '' if kind == 'continuous' else ' lower="-1" upper="1"'
    text = robot(f'<joint name="j1" type="{kind}"><parent link="base"/><child link="l1"/><axis xyz="{axis}"/>'
                 f'<limit effort="50" velocity="5"{limit}/></joint>',
                 links={'base': '', 'l1': inertial(1.0, '0.2 0 0', ixx=0.01, iyy=0.01, izz=0.01)})
    code, out, err = episode(capfd, tmp_path, monkeypatch, text, motion={
        'joint_names': ['j1'], 'duration': 0.3, 'profile': 'bang_bang', 'start': [0.0], 'goal': [0.3]})
    assert code == 0 and 'Traceback' not in err, err
    assert not json.loads(out)['diverged']
    model = pinocchio_model(tmp_path / 'arm.urdf')
    arm = Arm.from_urdf(tmp_path / 'arm.urdf')
    q = np.full(model.nq, 0.2) if kind != 'continuous' else np.array([np.cos(0.2), np.sin(0.2)])
    assert arm.mass_matrix(np.array([0.2])) == pytest.approx(pin.crba(model, model.createData(), q), rel=1e-14)


def fixed_chain(links: int) -> str:
    """The arm with a chain of fixed links hanging from l3, `links` links in all."""
    chain = [f'c{index}' for index in range(links - 4)]
    parents = ['l3', *chain[:-1]]
    return arm_urdf(extra=''.join(joint(f'f{index}', 'fixed', parent, child, '0.001 0 0')
                                  for index, (parent, child) in enumerate(zip(parents, chain)))).replace(
        '</robot>', ''.join(f'<link name="{name}"/>' for name in chain) + '</robot>')


def test_a_urdf_of_more_links_than_the_bound_is_refused_before_urdfdom_walks_it(tmp_path):
    # 5,000 links in a chain overflowed urdfdom's and Pinocchio's recursion: a segfault, not an error.
    path = write(tmp_path, fixed_chain(5000))
    script = ('from ddarm.physics.arm import Arm, ModelError\n'
              f'try:\n    Arm.from_urdf({str(path)!r})\nexcept ModelError as error:\n    print(error)\n')
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and 'has 5000 links, more than the 1000' in done.stdout, done


def test_a_urdf_of_as_many_links_as_the_bound_is_read(tmp_path):
    from ddarm.physics.arm import MAX_URDF_LINKS

    arm = Arm.from_urdf(write(tmp_path, fixed_chain(MAX_URDF_LINKS)))
    assert arm.joint_names == ['j1', 'j2', 'j3']


def test_a_urdf_nested_deeper_than_the_bound_is_refused(tmp_path):
    path = write(tmp_path, arm_urdf(extra='<gazebo>' * 101 + '</gazebo>' * 101))
    with pytest.raises(ModelError, match='deeper than 100 levels'):
        Arm.from_urdf(path)


def test_a_urdf_larger_than_the_bound_is_refused_unread(tmp_path):
    path = tmp_path / 'arm.urdf'
    with path.open('wb') as file:
        file.truncate(32 * 2**20 + 1)
    with pytest.raises(ModelError, match=f'holds {32 * 2**20 + 1} bytes, more than the {32 * 2**20}'):
        Arm.from_urdf(path)
