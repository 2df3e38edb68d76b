"""Mutual tensors and invariants of a pair of internal configurations (eqs. (20)-(33a), (75)-(79)).

For psi, phi in GL(n):

- G[psi, phi] = psi^T phi and C[psi, phi] = phi^-T psi^-1 (20), reducing to G[psi], C[psi]
  for phi = psi; invariant under common spatial / material isometries (23);
- Gamma[psi, phi] = psi^-1 phi and Sigma[psi, phi] = phi psi^-1 (21), the group-theoretic
  "displacements": Gamma is spatially affine invariant (26), Sigma materially (27);
- strain forms (33) (with the mutual tensors: the printed (33) has a typo,
  docs/theory/paper-typos.md) and (33a);
- K_a[psi, phi] = Tr(G[psi, phi]^a) (28), invariant under A psi B, A phi B for orthogonal
  A, B (29); M_a[psi, phi] = Tr(Gamma^a) = Tr(Sigma^a) (30), invariant for all A, B in GL(n)
  (31; the printed O(n) there is a typo, docs/theory/paper-typos.md);
- the affinely invariant distance D of (75) built on the *mean* Cauchy tensor
  (C[phi_K] + C[phi_L])/2 (docs/theory/paper-typos.md: not the mutual C of (20)), invariant
  under the spatial affine action (76); the relative volume det Gamma = det phi_L / det phi_K (79).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, as_vector, check_invertible, eye_like, same_n, transpose
from affinebody.deformation import matrix_power_traces


def _pair(psi, phi) -> tuple[jax.Array, jax.Array]:
    psi = as_matrix(psi, "psi")
    phi = as_matrix(phi, "phi")
    same_n(psi, phi, ("psi", "phi"))
    return psi, phi


def mutual_green(psi, phi) -> jax.Array:
    """G[psi, phi] = psi^T phi, eq. (20)."""
    psi, phi = _pair(psi, phi)
    return transpose(psi) @ phi


def mutual_cauchy(psi, phi) -> jax.Array:
    """C[psi, phi] = phi^-T psi^-1, eq. (20)."""
    psi, phi = _pair(psi, phi)
    check_invertible(psi, "psi")
    check_invertible(phi, "phi")
    return transpose(linalg.inv(phi)) @ linalg.inv(psi)


def mutual_gamma(psi, phi) -> jax.Array:
    """Gamma[psi, phi] = psi^-1 phi, eq. (21) (material "displacement" of phi from psi)."""
    psi, phi = _pair(psi, phi)
    check_invertible(psi, "psi")
    return linalg.solve(psi, phi)


def mutual_sigma(psi, phi) -> jax.Array:
    """Sigma[psi, phi] = phi psi^-1, eq. (21) (spatial "displacement" of phi from psi)."""
    psi, phi = _pair(psi, phi)
    check_invertible(psi, "psi")
    return phi @ linalg.inv(psi)


def mutual_lagrange_strain(psi, phi) -> jax.Array:
    """E[psi, phi] = (G[psi, phi] - Id)/2, eq. (33) corrected (docs/theory/paper-typos.md)."""
    g = mutual_green(psi, phi)
    return 0.5 * (g - eye_like(g))


def mutual_euler_strain(psi, phi) -> jax.Array:
    """e[psi, phi] = (Id - C[psi, phi])/2, eq. (33) corrected (docs/theory/paper-typos.md)."""
    c = mutual_cauchy(psi, phi)
    return 0.5 * (eye_like(c) - c)


def mutual_gamma_strain(psi, phi) -> jax.Array:
    """gamma[psi, phi] = Gamma[psi, phi] - Id, eq. (33a)."""
    g = mutual_gamma(psi, phi)
    return g - eye_like(g)


def mutual_sigma_strain(psi, phi) -> jax.Array:
    """sigma[psi, phi] = Sigma[psi, phi] - Id, eq. (33a)."""
    s = mutual_sigma(psi, phi)
    return s - eye_like(s)


def mutual_trace_invariants(psi, phi) -> jax.Array:
    """K_a[psi, phi] = Tr(G[psi, phi]^a), a = 1..n, eq. (28); shape [..., n]."""
    g = mutual_green(psi, phi)
    return matrix_power_traces(g, g.shape[-1])


def affine_invariants(psi, phi) -> jax.Array:
    """M_a[psi, phi] = Tr(Gamma[psi, phi]^a) = Tr(Sigma[psi, phi]^a), a = 1..n, eq. (30)."""
    g = mutual_gamma(psi, phi)
    return matrix_power_traces(g, g.shape[-1])


def mean_cauchy_tensor(phi_k, phi_l) -> jax.Array:
    """(C[phi_K] + C[phi_L])/2, the metric of the affine distance (75) (printed C[phi_K, phi_L])."""
    phi_k, phi_l = _pair(phi_k, phi_l)
    check_invertible(phi_k, "phi_k")
    check_invertible(phi_l, "phi_l")
    inv_k, inv_l = linalg.inv(phi_k), linalg.inv(phi_l)
    return 0.5 * (transpose(inv_k) @ inv_k + transpose(inv_l) @ inv_l)


def affine_distance_squared(x_k, phi_k, x_l, phi_l) -> jax.Array:
    """D^2 = (x_K - x_L)^T (C[phi_K] + C[phi_L])/2 (x_K - x_L), eq. (75).

    Evaluated as (|phi_K^-1 u|^2 + |phi_L^-1 u|^2)/2 with u = x_K - x_L (linear solves, no
    explicit Cauchy tensors).
    """
    phi_k, phi_l = _pair(phi_k, phi_l)
    x_k = as_vector(x_k, "x_k")
    x_l = as_vector(x_l, "x_l")
    same_n(phi_k, x_k, ("phi_k", "x_k"))
    same_n(phi_k, x_l, ("phi_k", "x_l"))
    check_invertible(phi_k, "phi_k")
    check_invertible(phi_l, "phi_l")
    u = x_k - x_l
    a = linalg.solve(phi_k, u[..., None])[..., 0]
    b = linalg.solve(phi_l, u[..., None])[..., 0]
    return 0.5 * (jnp.sum(a * a, axis=-1) + jnp.sum(b * b, axis=-1))


def affine_distance(x_k, phi_k, x_l, phi_l) -> jax.Array:
    """The affinely invariant distance D of eq. (75); invariant under (A x, A phi), eq. (76).

    Its gradient at coincident centres (D = 0) is taken as 0 rather than NaN; a NaN centre
    gives NaN (the fallback 0 x d2, not 0: a NaN fails ``d2 > 0`` and read as D = 0).
    """
    d2 = affine_distance_squared(x_k, phi_k, x_l, phi_l)
    positive = d2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, d2, 1.0)), 0.0 * d2)


def relative_volume(phi_k, phi_l) -> jax.Array:
    """det Gamma[phi_K, phi_L] = det phi_L / det phi_K, eq. (79)."""
    phi_k, phi_l = _pair(phi_k, phi_l)
    check_invertible(phi_k, "phi_k")
    return linalg.det(phi_l) / linalg.det(phi_k)


__all__ = [
    "mutual_green", "mutual_cauchy", "mutual_gamma", "mutual_sigma", "mutual_lagrange_strain",
    "mutual_euler_strain", "mutual_gamma_strain", "mutual_sigma_strain", "mutual_trace_invariants",
    "affine_invariants", "mean_cauchy_tensor", "affine_distance_squared", "affine_distance",
    "relative_volume"
]
