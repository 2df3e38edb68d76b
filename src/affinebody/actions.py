"""Spatial and material affine transformations and their action on every quantity (eq. (13)).

Left (spatial) and right (material) regular translations of GL(n) (13):
L_A(phi) = A phi, R_B(phi) = phi B. Together with a spatial affine map of the centres,
x -> A x + b, they act on velocities and momenta as the induced (tangent / cotangent) maps,
so that the pairings (42) are preserved:

=============  =====================  ====================
quantity       spatial (A, b)          material (B)
=============  =====================  ====================
x              A x + b                 x
phi            A phi                   phi B
v              A v                     v
xi             A xi                    xi B
p              A^-T p                  p
pi             pi A^-1                 B^-1 pi
=============  =====================  ====================

Derived quantities then follow (14), (15), (24), (26), (27), (35), (36), (47), (48); the
tests check each of these against the formulas of the other modules.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, check_invertible, transpose
from affinebody.state import State, VelocityState


def left_translation(a, phi) -> jax.Array:
    """L_A(phi) = A phi, eq. (13): a spatial affine transformation of the body."""
    return as_matrix(a, "A") @ as_matrix(phi, "phi")


def right_translation(phi, b) -> jax.Array:
    """R_B(phi) = phi B, eq. (13): a material affine transformation of the body."""
    return as_matrix(phi, "phi") @ as_matrix(b, "B")


def _matvec(m: jax.Array, v: jax.Array) -> jax.Array:
    return jnp.einsum("...ij,...j->...i", m, v)


def transform_state(state: State, A=None, B=None, b=None) -> State:
    """Act on a canonical state by x -> A x + b, phi -> A phi B (13) and the cotangent maps.

    p -> A^-T p and pi -> B^-1 pi A^-1 keep <p, v> and Tr(pi xi) invariant (42). ``A``, ``B``
    default to the identity and ``b`` to zero; each may carry the body axis or not.
    """
    x, phi, p, pi = state
    if A is not None:
        A = as_matrix(A, "A")
        check_invertible(A, "A")
        x = _matvec(A, x)
        phi = A @ phi
        p = _matvec(transpose(linalg.inv(A)), p)
        pi = pi @ linalg.inv(A)
    if B is not None:
        B = as_matrix(B, "B")
        check_invertible(B, "B")
        phi = phi @ B
        pi = linalg.solve(B, pi)
    if b is not None:
        x = x + b
    return State(x, phi, p, pi)


def transform_velocity_state(state: VelocityState, A=None, B=None, b=None) -> VelocityState:
    """Act on a Lagrangian state: x -> A x + b, phi -> A phi B, v -> A v, xi -> A xi B (13)."""
    x, phi, v, xi = state
    if A is not None:
        A = as_matrix(A, "A")
        x, phi, v, xi = _matvec(A, x), A @ phi, _matvec(A, v), A @ xi
    if B is not None:
        B = as_matrix(B, "B")
        phi, xi = phi @ B, xi @ B
    if b is not None:
        x = x + b
    return VelocityState(x, phi, v, xi)


__all__ = [
    "left_translation", "right_translation", "transform_state", "transform_velocity_state"
]
