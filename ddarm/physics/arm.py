"""The arm's rigid-body model: a Pinocchio model built from the URDF, and its dynamics."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pinocchio as pin

from ddarm.errors import DdarmError

URDF_NAME = 'ddarm.urdf'


class ModelError(DdarmError, ValueError):
    """A URDF or model option that cannot describe the arm."""


def default_urdf_path() -> Path:
    """The arm's URDF: from the source tree, else from the share folder of the prefix this module is installed in."""
    package = Path(__file__).resolve().parents[1]
    candidates = [package.parent / 'config' / URDF_NAME]
    if len(package.parents) > 3:  # <prefix>/lib/pythonX.Y/site-packages/ddarm (colcon or pip)
        candidates.append(package.parents[3] / 'share' / 'ddarm' / 'config' / URDF_NAME)
    candidates.append(Path(sys.prefix) / 'share' / 'ddarm' / 'config' / URDF_NAME)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ModelError(f'{URDF_NAME} not found in {[str(c) for c in candidates]}')


@dataclass(frozen=True)
class Arm:
    """A serial arm with revolute joints, and a Pinocchio workspace for its dynamics.

    Like Pinocchio's own Model/Data pair, `model` is what the robot is and
    `data` is scratch space: an Arm is not to be shared between threads.
    """

    model: pin.Model
    data: pin.Data
    urdf_path: Path

    @classmethod
    def from_urdf(cls, urdf_path: Path | str | None = None,
                  mass_scale: np.ndarray | list[float] | None = None) -> Arm:
        """Load the URDF; `mass_scale` multiplies each moving link's inertia (mass and moments).

        A heavier link of the same shape and uniform density scales its whole
        spatial inertia, which is how the plant is made to differ from the model.
        """
        path = Path(urdf_path) if urdf_path is not None else default_urdf_path()
        if path.is_dir():
            raise ModelError(f'URDF {path} is a directory, not a URDF file')
        if not path.exists():
            raise ModelError(f'URDF {path} does not exist')
        try:
            # Pinocchio reports a file it cannot open as one without a valid model: ask the OS first.
            with path.open('rb'):
                pass
        except OSError as error:
            raise ModelError(f'URDF {path} cannot be read: {error.strerror}') from error
        try:
            model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as error:
            raise ModelError(f'URDF {path} is not a URDF the arm can be built from: {error}') from error
        if model.nq != model.nv:
            raise ModelError(f'URDF {path}: only revolute/prismatic joints are supported '
                             f'(nq={model.nq}, nv={model.nv})')
        if mass_scale is not None:
            scale = np.asarray(mass_scale, dtype=float)
            if scale.shape != (model.nv,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
                raise ModelError(f'mass_scale must be {model.nv} finite positive numbers, got {mass_scale!r}')
            for joint_id, factor in enumerate(scale, start=1):
                inertia = model.inertias[joint_id]
                model.inertias[joint_id] = pin.Inertia(
                    factor * inertia.mass, inertia.lever, factor * inertia.inertia)
        return cls(model=model, data=model.createData(), urdf_path=path)

    @property
    def dof(self) -> int:
        return self.model.nv

    @property
    def joint_names(self) -> list[str]:
        return list(self.model.names)[1:]

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """M(q) of (1.1), symmetric."""
        upper = pin.crba(self.model, self.data, q)
        return np.triu(upper) + np.triu(upper, 1).T

    def bias(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """V(q, q̇) + G(q) of (1.1)."""
        return pin.nonLinearEffects(self.model, self.data, q, v).copy()

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G(q) of (1.1)."""
        return pin.computeGeneralizedGravity(self.model, self.data, q).copy()

    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """q̈ solving M(q) q̈ + V(q, q̇) + G(q) = torque (articulated-body algorithm)."""
        return pin.aba(self.model, self.data, q, v, torque).copy()

    def inverse_dynamics(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """M(q) a + V(q, q̇) + G(q) (recursive Newton-Euler)."""
        return pin.rnea(self.model, self.data, q, v, a).copy()

    def energy(self, q: np.ndarray, v: np.ndarray) -> float:
        """Kinetic plus potential energy, for conservation checks."""
        kinetic = pin.computeKineticEnergy(self.model, self.data, q, v)
        potential = pin.computePotentialEnergy(self.model, self.data, q)
        return float(kinetic + potential)

    def frame_position(self, q: np.ndarray, frame: str) -> np.ndarray:
        """Position of a URDF link frame in the fixed frame."""
        if not self.model.existFrame(frame):
            raise ModelError(f'no frame {frame!r} in {self.urdf_path}')
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.model.getFrameId(frame)].translation.copy()


@lru_cache(maxsize=16)
def load_arm(urdf: str | None, mass_scale: tuple[float, ...] | None = None) -> Arm:
    """The arm from a URDF, loaded once per process (Arm holds scratch space: one thread only)."""
    return Arm.from_urdf(urdf, mass_scale)
