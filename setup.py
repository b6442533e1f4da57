"""ddarm: one ament_python package holding the ddarm_sim, ddarm_control and ddarm_tuner Python packages."""

from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = 'ddarm'

setup(
    name=PACKAGE,
    version='0.1.0',
    description='Feedback-gain selection for a direct-drive arm on ROS 2 Jazzy (Kowalska, PD + gravity '
                'and computed torque)',
    license='Apache-2.0',
    python_requires='>=3.10',
    packages=find_packages(include=['ddarm', 'ddarm.*', 'ddarm_sim', 'ddarm_control', 'ddarm_tuner']),
    package_data={'ddarm.paper': ['data/*.yaml']},  # the paper's motions and settings
    # ros2 run finds a package through its ament index marker and runs lib/<package>/<executable>:
    # one marker and one executable folder per Python package the user names.
    data_files=[
        ('share/ament_index/resource_index/packages',
         [f'resource/{name}' for name in (PACKAGE, 'ddarm_sim', 'ddarm_control', 'ddarm_tuner')]),
        ('lib/ddarm_sim', ['scripts/plant', 'scripts/robot']),
        ('lib/ddarm_control', ['scripts/pd_gravity', 'scripts/computed_torque']),
        ('lib/ddarm_tuner', ['scripts/tuner']),
        (f'share/{PACKAGE}', ['package.xml']),
        # config/ and its example arms (config/arms/<arm>/), each folder's files where ros2 finds the share.
        *((f'share/{PACKAGE}/{folder.as_posix()}', sorted(str(path) for path in folder.iterdir() if path.is_file()))
          for folder in sorted({Path('config'), *(path.parent for path in Path('config').rglob('*') if path.is_file())})),
    ],
    # Versions seen working together on Python 3.11 (ROS 2 Jazzy from PyPI).
    install_requires=[
        'ros-jazzy-rclpy[fastrtps]==7.1.6',
        'ros-jazzy-common-interfaces==5.3.6',
        'pin==4.1.0',
        'rosbags==0.11.9',
        # rosbags reads and writes bag metadata with ruamel.yaml: its C parser and emitter are 7 times as fast.
        'ruamel.yaml.clib==0.2.15',
        'numpy==2.4.6',
        'scipy==1.17.1',
        'matplotlib==3.11.2',
        'cma==4.5.0',
        'numba==0.68.1',
        'PyYAML==6.0.3',
        'pymoo==0.6.2',
        'tqdm==4.70.1',
        'Markdown==3.11.3',
    ],
    extras_require={
        # `ddarm campaign --ray ADDRESS`: the searches as tasks on a Ray cluster (a cp311 wheel on the mirror).
        'ray': ['ray==2.60.0'],
        # `ddarm episode --mjcf`: MuJoCo as the robot.
        'mujoco': ['mujoco==4.0.1'],
        'test': ['pytest==9.2.0', 'colcon-common-extensions==0.3.0', 'selenium==4.31.0', 'ray==2.60.0',
                 'mujoco==4.0.1'],
    },
    zip_safe=True,
    entry_points={
        'console_scripts': [
            'ddarm = ddarm.cli.main:main',
        ],
    },
)
