"""Affine velocities and the velocity constraints of paper §1 (eqs. (34)-(41)).

With xi = dphi/dt (7): Omega = xi phi^-1 (spatial) and Omega_hat = phi^-1 xi (co-moving),
Eringen's "gyration" (34); v_hat = phi^-1 v (38). Under L_A: Omega -> A Omega A^-1,
Omega_hat fixed (35); under R_B: Omega fixed, Omega_hat -> B^-1 Omega_hat B (36).

Constraint residuals (zero when the constraint holds):
- gyroscopic (rigid) motion: Omega + Omega^T (39);
- spatially rotationless (purely deformative) motion: Omega - Omega^T (40);
- materially rotationless motion: Omega_hat - Omega_hat^T (41) — not equivalent to (40);
  both are non-holonomic (symmetric matrices are not a Lie subalgebra).
"""

from __future__ import annotations

import jax

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, as_vector, check_invertible, same_n, transpose


def _configuration_and_velocity(phi, xi) -> tuple[jax.Array, jax.Array]:
    phi = as_matrix(phi, "phi")
    xi = as_matrix(xi, "xi")
    same_n(phi, xi, ("phi", "xi"))
    check_invertible(phi)
    return phi, xi


def spatial_affine_velocity(phi, xi) -> jax.Array:
    """Omega = xi phi^-1, eq. (34)."""
    phi, xi = _configuration_and_velocity(phi, xi)
    return transpose(linalg.solve(transpose(phi), transpose(xi)))


def comoving_affine_velocity(phi, xi) -> jax.Array:
    """Omega_hat = phi^-1 xi, eq. (34)."""
    phi, xi = _configuration_and_velocity(phi, xi)
    return linalg.solve(phi, xi)


def comoving_velocity(phi, v) -> jax.Array:
    """v_hat = phi^-1 v, eq. (38)."""
    phi = as_matrix(phi, "phi")
    v = as_vector(v, "v")
    same_n(phi, v, ("phi", "v"))
    check_invertible(phi)
    return linalg.solve(phi, v[..., None])[..., 0]


def gyroscopic_residual(phi, xi) -> jax.Array:
    """Omega + Omega^T: zero for rigid (gyroscopic) motion, eq. (39)."""
    omega = spatial_affine_velocity(phi, xi)
    return omega + transpose(omega)


def spatial_rotationless_residual(phi, xi) -> jax.Array:
    """Omega - Omega^T: zero for spatially rotationless (purely deformative) motion, eq. (40)."""
    omega = spatial_affine_velocity(phi, xi)
    return omega - transpose(omega)


def material_rotationless_residual(phi, xi) -> jax.Array:
    """Omega_hat - Omega_hat^T: zero for materially rotationless motion, eq. (41)."""
    omega_hat = comoving_affine_velocity(phi, xi)
    return omega_hat - transpose(omega_hat)


__all__ = [
    "spatial_affine_velocity", "comoving_affine_velocity", "comoving_velocity",
    "gyroscopic_residual", "spatial_rotationless_residual", "material_rotationless_residual"
]
