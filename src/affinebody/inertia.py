"""Inertial characteristics of an affine body from its constituents (eqs. (8), (9)).

M = sum_p mu_p and J^kl = sum_p mu_p a_p^k a_p^l (8), the second moment of the mass
distribution in co-moving (Lagrange) coordinates a, measured from the centre of mass so that
translational and internal motion decouple in the d'Alembert kinetic energy (6).
J must be symmetric positive definite: the constituents may not all lie in a hyperplane.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from affinebody._checks import (
    as_float64,
    as_matrix,
    as_vector,
    check_symmetric_positive_definite,
    is_concrete,
)


def from_constituents(masses, positions) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(M, J, centre) of eq. (8) for point masses ``masses`` [P] at ``positions`` [P, n].

    Positions are in material coordinates; J is taken about the centre of mass ``centre``.
    Raises ValueError for non-positive masses or constituents spanning fewer than n dimensions.
    """
    masses = as_float64(masses, "masses")
    positions = as_vector(positions, "positions")
    if masses.ndim != 1 or positions.ndim != 2 or positions.shape[0] != masses.shape[0]:
        raise ValueError(
            f"masses must have shape [P] and positions [P, n] with the same P "
            f"(got {tuple(masses.shape)} and {tuple(positions.shape)})"
        )
    if is_concrete(masses) and not np.all(np.asarray(masses) > 0):
        raise ValueError("masses of constituents must all be > 0")
    total = jnp.sum(masses)
    centre = masses @ positions / total
    rel = positions - centre
    inertia = jnp.einsum("p,pk,pl->kl", masses, rel, rel)
    if is_concrete(inertia):
        try:
            check_symmetric_positive_definite(inertia, "J")
        except ValueError as err:
            raise ValueError(
                f"{err}: the constituents span fewer than n = {positions.shape[1]} dimensions "
                f"(need at least n + 1 points not in one hyperplane)"
            ) from None
    return total, inertia, centre


def check_inertia(J) -> jax.Array:
    """Return J as float64 after checking it is symmetric positive definite (8)."""
    J = as_matrix(J, "J")
    check_symmetric_positive_definite(J, "J")
    return J


def uniform_ball(mass, radius, n: int) -> jax.Array:
    """J of a uniform solid n-ball: M r^2 / (n + 2) Id (rod M r^2/3, disc M r^2/4, ball M r^2/5)."""
    return jnp.asarray(mass * radius**2 / (n + 2), jnp.float64) * jnp.eye(n)


__all__ = [
    "from_constituents", "check_inertia", "uniform_ball"
]
