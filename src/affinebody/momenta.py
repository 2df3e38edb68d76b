"""Canonical momenta, affine spin, spin and vorticity (paper §1, eqs. (42)-(49)).

The momentum pi conjugate to phi has the transposed index placement pi[a, i] = pi^a_i and
is paired with velocities as <pi, xi> = Tr(pi xi) (42); <p, v> = p^T v. Co-moving linear
momentum p_hat = phi^T p (43) keeps the pairing: p^T v = p_hat^T v_hat (44).

Affine spin Sigma = phi pi (spatial) and Sigma_hat = pi phi (co-moving) (45) are conjugate to
Omega and Omega_hat: Tr(Sigma Omega) = Tr(Sigma_hat Omega_hat) = Tr(pi xi) (46). They generate
left and right regular translations and transform as (47), (48). Their doubled skew parts
S = Sigma - Sigma^T (spin) and V = Sigma_hat - Sigma_hat^T (vorticity) generate spatial and
material rotations (49).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, as_vector, check_invertible, same_n, trace, transpose


def _matrices(phi, m, name: str) -> tuple[jax.Array, jax.Array]:
    phi = as_matrix(phi, "phi")
    m = as_matrix(m, name)
    same_n(phi, m, ("phi", name))
    return phi, m


def comoving_momentum(phi, p) -> jax.Array:
    """p_hat = phi^T p, eq. (43)."""
    phi = as_matrix(phi, "phi")
    p = as_vector(p, "p")
    same_n(phi, p, ("phi", "p"))
    return (transpose(phi) @ p[..., None])[..., 0]


def affine_spin(phi, pi) -> jax.Array:
    """Spatial affine spin Sigma = phi pi, eq. (45)."""
    phi, pi = _matrices(phi, pi, "pi")
    return phi @ pi


def comoving_affine_spin(phi, pi) -> jax.Array:
    """Co-moving affine spin Sigma_hat = pi phi, eq. (45)."""
    phi, pi = _matrices(phi, pi, "pi")
    return pi @ phi


def momentum_from_affine_spin(phi, sigma) -> jax.Array:
    """pi = phi^-1 Sigma (inverse of (45))."""
    phi, sigma = _matrices(phi, sigma, "Sigma")
    check_invertible(phi)
    return linalg.solve(phi, sigma)


def momentum_from_comoving_affine_spin(phi, sigma_hat) -> jax.Array:
    """pi = Sigma_hat phi^-1 (inverse of (45))."""
    phi, sigma_hat = _matrices(phi, sigma_hat, "Sigma_hat")
    check_invertible(phi)
    return transpose(linalg.solve(transpose(phi), transpose(sigma_hat)))


def spin(sigma) -> jax.Array:
    """S = Sigma - Sigma^T, generator of spatial rotations, eq. (49)."""
    sigma = as_matrix(sigma, "Sigma")
    return sigma - transpose(sigma)


def vorticity(sigma_hat) -> jax.Array:
    """V = Sigma_hat - Sigma_hat^T, generator of material rotations, eq. (49)."""
    sigma_hat = as_matrix(sigma_hat, "Sigma_hat")
    return sigma_hat - transpose(sigma_hat)


def translational_pairing(p, v) -> jax.Array:
    """<p, v> = p^T v = Tr(p v^T), eq. (42)."""
    p = as_vector(p, "p")
    v = as_vector(v, "v")
    return jnp.sum(p * v, axis=-1)


def internal_pairing(pi, xi) -> jax.Array:
    """<pi, xi> = Tr(pi xi), eq. (42); equals Tr(Sigma Omega) = Tr(Sigma_hat Omega_hat) (46)."""
    pi = as_matrix(pi, "pi")
    xi = as_matrix(xi, "xi")
    return trace(pi @ xi)


__all__ = [
    "comoving_momentum", "affine_spin", "comoving_affine_spin", "momentum_from_affine_spin",
    "momentum_from_comoving_affine_spin", "spin", "vorticity", "translational_pairing",
    "internal_pairing"
]
