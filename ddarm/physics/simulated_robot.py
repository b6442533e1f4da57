"""A MuJoCo robot as a ros2_control robot looks from outside: efforts in, measured joint states out.

What a real robot adds to its physics, each by a setting: the effort commands reach the joints after a latency,
a robot that hears no command for a while zeroes its efforts (as a hardware interface's watchdog does), a command
of the wrong length or with a value that is not finite is refused (the command in force is held), and the
positions and velocities it reports carry noise (Gaussian, seeded). The efforts applied are bounded by the MJCF's
own ranges (`MujocoPlant.saturate`). Times are the robot's seconds: the wall clock when it runs free, the sample
instants when it runs in lockstep; nothing here reads a clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ddarm.errors import DdarmError
from ddarm.physics.mujoco_plant import MujocoPlant, Robot


# s: a command is due at a time within this of its arrival plus the latency, which in lockstep is a sum of floats that
# may round a hair past the sample instant it names.
DUE_TOLERANCE = 1e-9


class RealismError(DdarmError, ValueError):
    """A realism setting ddarm cannot run a robot with."""


@dataclass(frozen=True)
class Realism:
    """How the robot departs from its physics: measurement noise, command latency and the command watchdog."""

    position_noise: float = 0.0  # standard deviation of each reported position, rad or m
    velocity_noise: float = 0.0  # of each reported velocity, rad/s or m/s
    seed: int = 0  # of the noise: the same seed, the same noise
    command_latency: float = 0.0  # s from a command's arrival to the joints
    command_timeout: float = 0.0  # s without a command after which the efforts are zeroed; 0: never
    # The joints held at the start state until the first command comes into force, as brakes hold a robot until its
    # controller starts; else the robot moves under gravity from the start.
    hold_until_commanded: bool = True

    def __post_init__(self) -> None:
        for name in ('position_noise', 'velocity_noise', 'command_latency', 'command_timeout'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise RealismError(f'{name} must be a finite number >= 0, got {value}')


class SimulatedRobot:
    """The robot's hardware side: `receive` takes commands as they arrive, `step` holds the effort in force over one
    period and returns the state the robot reports.

    The effort in force is the latest command whose arrival plus `command_latency` is due (zero before the first).
    Once no command has arrived for `command_timeout`, the efforts are zeroed until one does (`timed_out`).
    """

    def __init__(self, robot: Robot, q0, v0, realism: Realism = Realism()) -> None:
        self.robot = robot
        self.realism = realism
        self.plant = MujocoPlant(robot, q0, v0)
        self.dof = self.plant.dof
        self._noise = np.random.default_rng(realism.seed)
        self._pending: deque[tuple[float, np.ndarray]] = deque()  # (due time, effort), in arrival order
        self.effort = np.zeros(self.dof)  # the command in force
        self.commanded = False  # whether the effort in force is a command's (not the zero before one, or a timeout's)
        self.held = realism.hold_until_commanded  # the brakes: released when the first command comes into force
        self.applied = np.zeros(self.dof)  # what the actuators applied over the last period
        self.last_arrival: float | None = None
        self.timed_out = False
        self.counters = {'commands': 0, 'refused_commands': 0, 'timeouts': 0}

    def receive(self, values, now: float) -> str | None:
        """Take a command that arrived at `now`; the reason it is refused (the command in force is held), or None."""
        effort = np.asarray(values, dtype=float).ravel()
        if effort.shape != (self.dof,):
            reason = f'a command of {effort.size} efforts for the {self.dof} joints {list(self.robot.joint_names)}'
        elif not all(map(math.isfinite, effort.tolist())):
            reason = f'a command with a value that is not finite: {effort.tolist()}'
        else:
            self.counters['commands'] += 1
            self._pending.append((now + self.realism.command_latency, effort))
            self.last_arrival = now
            return None
        self.counters['refused_commands'] += 1
        return reason

    def time_out(self) -> None:
        """No command came in time: zero the efforts, and forget the commands on their way, until the next one."""
        if not self.timed_out:
            self.counters['timeouts'] += 1
        self.timed_out = True
        self._pending.clear()
        self.effort = np.zeros(self.dof)
        self.commanded = False

    def overdue(self, now: float) -> bool:
        """Whether no command has arrived for longer than the timeout by `now`, since the last one (before the first
        one the efforts are zero already: nothing is overdue)."""
        timeout = self.realism.command_timeout
        return timeout > 0 and self.last_arrival is not None and now - self.last_arrival > timeout

    def step(self, now: float) -> bool:
        """Hold the effort in force at `now` over one period; False once the robot diverged (its state frozen).
        After it, `effort` and `commanded` say what was in force over that period."""
        if self.overdue(now):
            self.time_out()
        while self._pending and self._pending[0][0] <= now + DUE_TOLERANCE:
            self.effort = self._pending.popleft()[1]
            self.timed_out, self.commanded, self.held = False, True, False
        if self.held:
            self.applied = np.zeros(self.dof)
            return True
        self.applied = self.plant.saturate(self.effort)
        return self.plant.advance(self.applied)

    def measured(self) -> tuple[np.ndarray, np.ndarray]:
        """The positions and velocities the robot reports: the true ones plus the noise of this sample."""
        q, v = self.plant.q, self.plant.v
        if self.realism.position_noise:
            q = q + self._noise.normal(0.0, self.realism.position_noise, self.dof)
        if self.realism.velocity_noise:
            v = v + self._noise.normal(0.0, self.realism.velocity_noise, self.dof)
        return q, v
