"""M(q) and q̈ from ddarm's compiled forward dynamics, for the tests that check them against Pinocchio."""

import numpy as np

from ddarm.physics.dynamics import forward_dynamics_at, inverse_dynamics_at


def compiled_mass_matrix_and_acceleration(chain, q, v, torque, mass_scale=None):
    """M(q) and q̈ by the compiled forward dynamics, for the states of q, v, torque (m, n): M⁻¹'s column j is
    q̈ at q̇ = 0 under G(q) + e_j, so M comes from the forward dynamics' own CRBA and Cholesky, not the RNEA."""
    n = chain.dof
    zero = np.zeros_like(q)
    gravity = inverse_dynamics_at(chain, q, zero, zero, mass_scale=mass_scale)
    inverse = np.stack([forward_dynamics_at(chain, q, zero, gravity + np.eye(n)[j], mass_scale=mass_scale)
                        for j in range(n)], axis=-1)
    return np.linalg.inv(inverse), forward_dynamics_at(chain, q, v, torque, mass_scale=mass_scale)
